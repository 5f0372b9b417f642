#include "piezo_compensation/analysis/evaluation/noise_floor.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/evaluation/metrics.h"
#include "piezo_compensation/util/stats.h"

namespace piezo::analysis {

namespace {

constexpr std::size_t kMinHoldDiffs = 200;

// σ of white noise from its second differences: trimmed at 5 robust σ, then the plain standard deviation.
double sigma_from_second_differences(std::vector<double> d2) {
  if (d2.empty()) return NAN;
  std::vector<double> a(d2.size());
  for (std::size_t i = 0; i < d2.size(); ++i) a[i] = std::fabs(d2[i]);
  double mad = util::median(std::move(a));
  // Quantised readings can make half the differences exactly 0: fall back to the mean absolute value.
  if (mad <= 0.0) {
    double s = 0.0;
    for (double x : d2) s += std::fabs(x);
    mad = 0.6745 * (s / d2.size()) / 0.7979;  // E|x| = 0.7979σ, MAD = 0.6745σ
  }
  const double limit = 5.0 * 1.4826 * mad;
  double ss = 0.0;
  std::size_t n = 0;
  for (double x : d2)
    if (limit <= 0.0 || std::fabs(x) <= limit) ss += x * x, ++n;
  return n ? std::sqrt(ss / n / 6.0) : NAN;
}

}  // namespace

double reading_step_nm(const std::vector<double>& readings) {
  std::vector<double> v;
  v.reserve(readings.size());
  for (double x : readings)
    if (std::isfinite(x)) v.push_back(x);
  std::sort(v.begin(), v.end());
  v.erase(std::unique(v.begin(), v.end()), v.end());
  if (v.size() < 3) return 0.0;
  double q = INFINITY;
  for (std::size_t i = 1; i < v.size(); ++i) q = std::min(q, v[i] - v[i - 1]);
  const double span = v.back() - v.front();
  // Continuous readings: nearly as many distinct values as samples, spacing far below the span.
  if (!(q > 1e-9 * std::max(1.0, span))) return 0.0;
  std::size_t on_grid = 0;
  for (std::size_t i = 1; i < v.size(); ++i) {
    const double k = (v[i] - v[0]) / q;
    on_grid += std::fabs(k - std::nearbyint(k)) < 1e-3;
  }
  return on_grid >= 0.95 * (v.size() - 1) ? q : 0.0;
}

NoiseFloor noise_floor_from_sigma(double sigma_nm) {
  if (!(sigma_nm >= 0.0) || !std::isfinite(sigma_nm))
    throw std::invalid_argument("noise sigma must be a finite number >= 0 nm");
  NoiseFloor f;
  f.sigma_nm = sigma_nm;
  f.floor_mae_nm = noise_floor_mae_nm(sigma_nm);
  f.method = "given";
  return f;
}

NoiseFloor estimate_noise_floor(const io::Dataset& data, const std::string& axis,
                                const std::vector<double>* prediction) {
  const auto& ax = data.axis(axis);
  const std::vector<double>& y = ax.position_nm;
  const std::vector<double>& v = ax.voltage_v;
  const std::size_t n = y.size();
  if (n < 3) throw std::invalid_argument("noise floor: axis " + axis + " has fewer than 3 samples");
  if (prediction && prediction->size() != n)
    throw std::invalid_argument("noise floor: prediction has " + std::to_string(prediction->size()) +
                                " samples, the data " + std::to_string(n));
  NoiseFloor f;
  f.quantisation_nm = reading_step_nm(y);

  // Holds: runs of equal voltage; skip the start of each, where fast creep modes still bend the position.
  std::vector<double> d2;
  std::size_t run_begin = 0;
  auto take_run = [&](std::size_t b, std::size_t e) {  // [b, e) has one voltage
    if (e - b < 3) return;
    const std::size_t skip = (e - b) / 50;
    for (std::size_t i = b + skip + 1; i + 1 < e; ++i)
      if (std::isfinite(y[i - 1]) && std::isfinite(y[i]) && std::isfinite(y[i + 1]))
        d2.push_back(y[i + 1] - 2.0 * y[i] + y[i - 1]);
  };
  for (std::size_t i = 1; i <= n; ++i)
    if (i == n || v[i] != v[run_begin]) take_run(run_begin, i), run_begin = i;
  f.method = "holds";
  if (d2.size() < kMinHoldDiffs) {
    d2.clear();
    f.method = prediction ? "residual" : "all samples";
    for (std::size_t i = 1; i + 1 < n; ++i) {
      double a = y[i - 1], b = y[i], c = y[i + 1];
      if (prediction) a -= (*prediction)[i - 1], b -= (*prediction)[i], c -= (*prediction)[i + 1];
      if (std::isfinite(a) && std::isfinite(b) && std::isfinite(c)) d2.push_back(c - 2.0 * b + a);
    }
  }
  f.samples = d2.size();
  const double sigma = sigma_from_second_differences(d2);
  if (!std::isfinite(sigma)) throw std::invalid_argument("noise floor: no finite readings on axis " + axis);
  const double rounding = f.quantisation_nm / std::sqrt(12.0);
  f.sigma_nm = std::max(sigma, rounding);
  f.floor_mae_nm = sigma >= rounding ? noise_floor_mae_nm(f.sigma_nm) : f.quantisation_nm / 4.0;
  return f;
}

std::string NoiseFloor::describe() const {
  std::ostringstream os;
  os.setf(std::ios::fixed);
  os.precision(sigma_nm < 10 ? 2 : 1);
  os << "σ = " << sigma_nm << " nm (" << method;
  if (method != "given") os << ", " << samples << " samples";
  if (quantisation_nm > 0) os << "; encoder step " << quantisation_nm << " nm";
  os << ") → a perfect predictor scored against the readings has MAE ≈ " << floor_mae_nm << " nm";
  return os.str();
}

}  // namespace piezo::analysis
