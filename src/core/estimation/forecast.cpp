#include "piezo_compensation/estimation/forecast.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>
#include <stdexcept>

namespace piezo::estimation {

ErrorForecast forecast_error(const NoiseModel& m, double dt_s, const FilterState& s, const ForecastPath& path, bool hold) {
  ErrorForecast f;
  if (!m.fuse) {
    f.sigma_nm = m.model_sigma_nm;
    f.var_nm2 = f.sigma_nm * f.sigma_nm;
    return f;
  }
  const double n = static_cast<double>(path.steps), T = n * dt_s;
  const double phin = std::exp(-T / std::max(m.fast_tau_s, 1e-9));
  const auto& c = s.covariance;  // ss, sf, sd, ff, fd, dd
  // g = (1, φⁿ, T): the error at the horizon as a function of the state now
  const double g[3] = {1.0, phin, T};
  const double P[3][3] = {{c[0], c[1], c[2]}, {c[1], c[3], c[4]}, {c[2], c[4], c[5]}};
  double var = 0.0;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) var += g[i] * P[i][j] * g[j];
  var += s.rate_scale * (m.q_rest_nm2_per_s * T + m.q_drift_nm2_per_s3 * T * T * T / 3.0 + m.q_motion_nm * path.path_nm +
                         m.q_fast_nm * path.fast_path_nm);
  // The slow error's rate stays out of the mean (its uncertainty is in the variance): its identified random walk is
  // weak, so its estimate is mostly noise, and h·rate over minutes turns that noise into an error of its own.
  f.mean_nm = s.slow_nm + phin * s.fast_nm;
  f.var_nm2 = std::max(0.0, var);
  f.sigma_nm = forecast_sigma_scale(m, T, hold) * std::sqrt(f.var_nm2);
  return f;
}

double forecast_sigma_scale(const NoiseModel& m, double horizon_s, bool hold) {
  const std::vector<double>& h = m.forecast_horizons_s;
  const std::vector<double>& k = hold ? m.forecast_sigma_scale_hold : m.forecast_sigma_scale_move;
  if (h.empty() || k.size() != h.size()) return 1.0;
  if (!(horizon_s > h.front())) return k.front();
  if (horizon_s >= h.back()) return k.back();
  const std::size_t j = static_cast<std::size_t>(std::upper_bound(h.begin(), h.end(), horizon_s) - h.begin());
  const double u = std::log(horizon_s / h[j - 1]) / std::log(h[j] / h[j - 1]);
  return k[j - 1] + u * (k[j] - k[j - 1]);
}

PathSums::PathSums(const std::vector<double>& p, double phi) : cum_(p.size(), 0.0), decayed_(p.size(), 0.0), phi2_(phi * phi) {
  for (std::size_t i = 1; i < p.size(); ++i) {
    const double d = std::isfinite(p[i]) && std::isfinite(p[i - 1]) ? std::abs(p[i] - p[i - 1]) : 0.0;
    cum_[i] = cum_[i - 1] + d;
    decayed_[i] = phi2_ * decayed_[i - 1] + d;
  }
}

ForecastPath PathSums::between(std::size_t row, std::size_t steps) const {
  ForecastPath f;
  f.steps = steps;
  const std::size_t end = std::min(row + steps, cum_.size() - 1);
  f.path_nm = cum_[end] - cum_[row];
  f.fast_path_nm = std::max(0.0, decayed_[end] - std::pow(phi2_, static_cast<double>(end - row)) * decayed_[row]);
  return f;
}

namespace {

struct CalibrationPoint {
  double err2, var, ref_var;
};

// The scale s whose ±2·√(s²·var + ref_var) holds `coverage` of the points, by bisection in log s on [1/16, 16].
double coverage_scale(const std::vector<CalibrationPoint>& pts, double coverage) {
  auto share = [&](double s) {
    std::size_t in = 0;
    for (const auto& p : pts) in += p.err2 <= 4.0 * (s * s * p.var + p.ref_var);
    return static_cast<double>(in) / static_cast<double>(pts.size());
  };
  double lo = std::log(1.0 / 16.0), hi = std::log(16.0);
  if (share(std::exp(lo)) >= coverage) return std::exp(lo);
  if (share(std::exp(hi)) < coverage) return std::exp(hi);
  for (int it = 0; it < 40; ++it) {
    const double mid = 0.5 * (lo + hi);
    (share(std::exp(mid)) >= coverage ? hi : lo) = mid;
  }
  return std::exp(hi);
}

// The rows the forecast table scores: 1 in the walk before a hold, 2 in a hold from hold_from_s; empty without holds.
std::vector<char> table_rows(std::size_t n, double dt_s, const ForecastCalibrationOptions& o) {
  if (o.holds.empty()) return {};
  std::vector<char> rows(n, 0);
  const std::size_t walk_n = static_cast<std::size_t>(std::lround(o.walk_s / dt_s));
  const std::size_t skip_n = static_cast<std::size_t>(std::lround(o.hold_from_s / dt_s));
  for (const auto& [b, e] : o.holds) {
    for (std::size_t i = b > walk_n ? b - walk_n : 0; i < std::min(b, n); ++i) rows[i] = 1;
    for (std::size_t i = b + skip_n; i < std::min(e, n); ++i) rows[i] = 2;
  }
  return rows;
}

}  // namespace

std::vector<FilterState> filter_states(const NoiseModel& m, double dt_s, const std::vector<double>& p,
                                       const std::vector<double>& y) {
  ErrorFilter f(m, dt_s);
  std::vector<FilterState> states(p.size());
  for (std::size_t i = 0; i < p.size(); ++i) {
    f.step(p[i], y[i], std::isfinite(y[i]));
    states[i] = f.state();
  }
  return states;
}

RunForecaster::RunForecaster(const NoiseModel& m, double dt_s, const std::vector<double>& p, const std::vector<double>& y,
                             const std::vector<double>& v, std::vector<FilterState> states, double window_s)
    : m_(m), dt_(dt_s), p_(p), y_(y), states_(std::move(states)),
      sums_(p, std::exp(-dt_s / std::max(m.fast_tau_s, 1e-9))) {
  const std::size_t n = p.size();
  if (y.size() != n || v.size() != n || states_.size() != n)
    throw std::invalid_argument("RunForecaster: predictions, readings, voltages and states differ in length");
  ys_.assign(n + 1, 0.0), yn_.assign(n + 1, 0.0), ps_.assign(n + 1, 0.0), vc_.assign(n + 1, 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    const bool ok = std::isfinite(y[i]);
    ys_[i + 1] = ys_[i] + (ok ? y[i] : 0.0);
    yn_[i + 1] = yn_[i] + (ok ? 1.0 : 0.0);
    ps_[i + 1] = ps_[i] + (ok ? p[i] : 0.0);
    vc_[i + 1] = vc_[i] + (i > 0 && v[i] != v[i - 1] ? 1.0 : 0.0);
  }
  w_ = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(window_s / dt_s)));
}

WindowForecast RunForecaster::at(std::size_t i, double horizon_s) const {
  WindowForecast r;
  const std::size_t steps = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(horizon_s / dt_)));
  const std::size_t a = i + steps, b = a + w_;  // reference rows (a, b]
  if (b >= p_.size()) return r;
  const double cnt = yn_[b + 1] - yn_[a + 1];
  if (cnt < 0.5 * static_cast<double>(w_)) return r;
  r.held = vc_[b + 1] - vc_[i + 1] == 0.0;
  const ErrorForecast e = forecast_error(m_, dt_, states_[i], sums_.between(i, steps), r.held);
  r.forecast_nm = (ps_[b + 1] - ps_[a + 1]) / cnt + e.mean_nm;
  r.reference_nm = (ys_[b + 1] - ys_[a + 1]) / cnt;
  r.var_nm2 = e.var_nm2;
  r.sigma_nm = e.sigma_nm;
  r.reference_var_nm2 = m_.reading_sigma_nm * m_.reading_sigma_nm / cnt;
  r.ok = true;
  return r;
}

WindowForecast RunForecaster::next_reading(std::size_t i) const {
  WindowForecast r;
  if (i + 1 >= p_.size() || !std::isfinite(y_[i + 1])) return r;
  r.held = vc_[i + 2] - vc_[i + 1] == 0.0;
  const ErrorForecast e = forecast_error(m_, dt_, states_[i], sums_.between(i, 1), r.held);
  r.forecast_nm = p_[i + 1] + e.mean_nm;
  r.reference_nm = y_[i + 1];
  r.var_nm2 = e.var_nm2;
  r.sigma_nm = e.sigma_nm;
  r.reference_var_nm2 = m_.reading_sigma_nm * m_.reading_sigma_nm;
  r.ok = true;
  return r;
}

void calibrate_forecast(NoiseModel& m, double dt_s, const std::vector<double>& p, const std::vector<double>& y,
                        const std::vector<double>& v, const ForecastCalibrationOptions& o) {
  if (p.size() != y.size() || p.size() != v.size())
    throw std::invalid_argument("calibrate_forecast: predictions, readings and voltages differ in length");
  if (!m.fuse || o.horizons_s.empty()) return;
  m.forecast_horizons_s.clear();  // the propagated σ, unscaled, is what is calibrated
  const RunForecaster run(m, dt_s, p, y, v, filter_states(m, dt_s, p, y), o.reference_window_s);
  const std::vector<char> scored = table_rows(run.size(), dt_s, o);
  std::vector<double> hs, hold_k, move_k;
  std::ostringstream note;
  note << std::setprecision(3) << "; forecast σ calibrated to " << 100.0 * o.coverage << " %"
       << (scored.empty() ? "" : " on the table's rows") << " (hold/move scale per horizon:";
  for (double h : o.horizons_s) {
    std::vector<CalibrationPoint> hold, move;
    for (std::size_t i = 0; i < run.size(); ++i) {
      const char row = scored.empty() ? 1 : scored[i];
      if (!row) continue;
      const WindowForecast f = run.at(i, h);
      if (!f.ok || (row == 2 && !f.held)) continue;  // the table scores a hold's windows inside it only
      const double e = f.forecast_nm - f.reference_nm;
      (f.held ? hold : move).push_back({e * e, f.var_nm2, f.reference_var_nm2});
    }
    auto scale = [&](const std::vector<CalibrationPoint>& pts) {
      return pts.size() >= o.min_samples ? coverage_scale(pts, o.coverage) : 1.0;
    };
    hs.push_back(std::max(1.0, std::round(h / dt_s)) * dt_s);
    hold_k.push_back(scale(hold));
    move_k.push_back(scale(move));
    note << " " << h << " s " << hold_k.back() << "/" << move_k.back();
  }
  m.forecast_horizons_s = hs;
  m.forecast_sigma_scale_hold = hold_k;
  m.forecast_sigma_scale_move = move_k;
  m.method += note.str() + ")";
}

}  // namespace piezo::estimation
