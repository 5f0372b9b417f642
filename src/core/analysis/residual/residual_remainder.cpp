// What is left after the residual loop: block means against the noise floor, top correlates, step changes.
#include <algorithm>
#include <cmath>
#include <numeric>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/util/stats.h"

namespace piezo::analysis {

namespace {

double corr(const std::vector<double>& a, const std::vector<double>& b) {
  const std::size_t n = a.size();
  if (n < 3) return 0.0;
  double ma = 0, mb = 0;
  for (std::size_t i = 0; i < n; ++i) ma += a[i], mb += b[i];
  ma /= static_cast<double>(n), mb /= static_cast<double>(n);
  double sab = 0, saa = 0, sbb = 0;
  for (std::size_t i = 0; i < n; ++i) {
    sab += (a[i] - ma) * (b[i] - mb);
    saa += (a[i] - ma) * (a[i] - ma);
    sbb += (b[i] - mb) * (b[i] - mb);
  }
  return saa > 0 && sbb > 0 ? sab / std::sqrt(saa * sbb) : 0.0;
}

// Every signal the model could read and the products position × each aux signal, position × time and position ×
// each other axis' signal (what a gain on that signal leaves).
struct Signals {
  std::vector<std::string> names;
  std::vector<const std::vector<double>*> cols;
  std::vector<std::vector<double>> products;
};

void add_with_product(Signals& s, const std::string& name, const std::vector<double>& v, const std::vector<double>& position) {
  const std::size_t n = v.size();
  const double ma = std::accumulate(position.begin(), position.end(), 0.0) / static_cast<double>(n);
  const double mb = std::accumulate(v.begin(), v.end(), 0.0) / static_cast<double>(n);
  std::vector<double> p(n);
  for (std::size_t i = 0; i < n; ++i) p[i] = (position[i] - ma) * (v[i] - mb);
  s.names.push_back(name);
  s.cols.push_back(&v);
  s.products.push_back(std::move(p));
  s.names.push_back("position × " + name);
  s.cols.push_back(&s.products.back());
}

Signals candidate_signals(const std::vector<double>& position, const io::Dataset& data, const std::string& axis) {
  Signals s;
  s.products.reserve(2 + data.aux.size() + 2 * data.axes.size());  // pointers into it must stay valid
  s.names = {"voltage", "position"};
  s.cols = {&data.axis(axis).voltage_v, &position};
  add_with_product(s, "time_s", data.time_s, position);
  for (const auto& a : data.aux) add_with_product(s, a.name, a.values, position);
  for (const auto& ax : data.axes) {
    if (ax.name == axis) continue;
    add_with_product(s, io::voltage_column(ax.name), ax.voltage_v, position);
    add_with_product(s, io::position_column(ax.name), ax.position_nm, position);
  }
  return s;
}

// Means over blocks of B rows with at least half of them scored.
struct Blocks {
  std::vector<double> residual;             // block mean of what is left
  std::vector<std::size_t> first;           // first row of each block
  std::vector<std::vector<double>> signal;  // block mean of each candidate signal
};

Blocks block_means(const std::vector<double>& residual, const Signals& sig, const std::vector<char>& mask, std::size_t B) {
  auto use = [&](std::size_t i) { return mask.empty() || mask[i]; };
  Blocks out;
  out.signal.resize(sig.cols.size());
  for (std::size_t b = 0; b + B <= residual.size(); b += B) {
    std::size_t k = 0;
    double s = 0;
    for (std::size_t i = b; i < b + B; ++i)
      if (use(i)) ++k, s += residual[i];
    if (k < B / 2) continue;
    out.residual.push_back(s / static_cast<double>(k));
    out.first.push_back(b);
    for (std::size_t c = 0; c < sig.cols.size(); ++c) {
      double t = 0;
      for (std::size_t i = b; i < b + B; ++i)
        if (use(i)) t += (*sig.cols[c])[i];
      out.signal[c].push_back(t / static_cast<double>(k));
    }
  }
  return out;
}

// Where, within ±B rows of `row`, the mean over W scored rows after differs most from the mean over W before.
std::size_t refine_step(const std::vector<double>& r, const std::vector<char>& mask, std::size_t row, std::size_t B,
                        std::size_t W) {
  const std::size_t n = r.size();
  std::vector<double> sum(n + 1, 0.0), cnt(n + 1, 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    const bool u = mask.empty() || mask[i];
    sum[i + 1] = sum[i] + (u ? r[i] : 0.0);
    cnt[i + 1] = cnt[i] + (u ? 1.0 : 0.0);
  }
  std::size_t best = row;
  double best_d = -1.0;
  for (std::size_t t = row > B ? row - B : 0; t <= std::min(n, row + B); ++t) {
    const std::size_t a = t > W ? t - W : 0, b = std::min(n, t + W);
    const double ka = cnt[t] - cnt[a], kb = cnt[b] - cnt[t];
    if (ka < 1 || kb < 1) continue;
    const double d = std::fabs((sum[b] - sum[t]) / kb - (sum[t] - sum[a]) / ka);
    if (d > best_d) best_d = d, best = t;
  }
  return best;
}

}  // namespace

// Steps are found on the block means: the mean over w blocks after each block boundary against the mean over w
// blocks before, in units of the block means' own scatter (a robust σ of their first differences, which holds
// the reading noise and whatever slow structure moves from block to block; floored at the noise alone), or of
// the window differences over the record where those are larger. w is 4
// blocks (2 min at 30 s): long enough to average the noise, short enough that slow wander adds little.
// Local maxima above z_min, at least w blocks apart, largest first; the time refined to the row.
std::vector<StepChange> find_steps(const std::vector<double>& residual, const std::vector<char>& mask,
                                   const std::vector<double>& time_s, const std::vector<double>& block_means,
                                   const std::vector<std::size_t>& block_first, std::size_t B, double noise_sigma_nm,
                                   double z_min, std::size_t max_steps) {
  const std::size_t K = block_means.size(), w = 4;
  std::vector<StepChange> out;
  if (K < 2 * w + 1) return out;
  std::vector<double> d(K - 1);
  for (std::size_t j = 0; j + 1 < K; ++j) d[j] = std::fabs(block_means[j + 1] - block_means[j]);
  const double scatter = std::max(1.4826 * util::median(d) / std::sqrt(2.0), noise_sigma_nm / std::sqrt(static_cast<double>(B)));
  const double se = scatter * std::sqrt(2.0 / static_cast<double>(w));
  std::vector<double> z(K, 0.0), size(K, 0.0);
  for (std::size_t j = w; j + w <= K; ++j) {
    const double after = std::accumulate(block_means.begin() + static_cast<long>(j), block_means.begin() + static_cast<long>(j + w), 0.0);
    const double before = std::accumulate(block_means.begin() + static_cast<long>(j - w), block_means.begin() + static_cast<long>(j), 0.0);
    size[j] = (after - before) / static_cast<double>(w);
    z[j] = size[j] / se;
  }
  // A step must also stand out from the window differences themselves (a robust σ of them over the record):
  // slow structure the model misses moves them by several block-noise units everywhere, a slip only at itself.
  std::vector<double> dev;
  for (std::size_t j = w; j + w <= K; ++j) dev.push_back(std::fabs(size[j]));
  const double typical = 1.4826 * util::median(dev);
  if (typical > se)
    for (std::size_t j = w; j + w <= K; ++j) z[j] = size[j] / typical;
  std::vector<std::size_t> order(K);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return std::fabs(z[a]) > std::fabs(z[b]); });
  std::vector<std::size_t> taken;
  for (std::size_t j : order) {
    if (std::fabs(z[j]) < z_min || out.size() >= max_steps) break;
    bool near = false;
    for (std::size_t t : taken) near = near || (j > t ? j - t : t - j) < w;
    if (near) continue;
    taken.push_back(j);
    const std::size_t row = refine_step(residual, mask, block_first[j], B, w * B);
    out.push_back(StepChange{time_s[std::min(row, time_s.size() - 1)], size[j], z[j]});
  }
  return out;
}

Remainder assess_remainder(const std::vector<double>& residual, const std::vector<double>& position, const io::Dataset& data,
                           const std::string& axis, const std::vector<char>& mask, double alpha, double block_s) {
  Remainder out;
  const std::size_t n = residual.size();
  if (position.size() != n || data.size() != n || (!mask.empty() && mask.size() != n))
    throw std::invalid_argument("assess_remainder: sizes differ");
  const std::size_t used = mask.empty() ? n : static_cast<std::size_t>(std::count(mask.begin(), mask.end(), 1));
  if (used < 20) return out;
  // σ from the data (analysis/evaluation/noise_floor.h: second differences in holds, else of this residual).
  const NoiseFloor nf = estimate_noise_floor(data, axis, &position);
  out.noise_sigma_nm = nf.sigma_nm;
  out.noise_floor = nf.describe();
  const double fs = data.sample_rate_hz();
  const std::size_t B = std::max<std::size_t>(2, static_cast<std::size_t>(std::lround(block_s * fs)));
  out.block_s = static_cast<double>(B) / fs;
  const Signals sig = candidate_signals(position, data, axis);
  const Blocks bl = block_means(residual, sig, mask, B);
  const std::vector<double>& rm = bl.residual;
  out.blocks = rm.size();
  if (rm.size() < 4) return out;
  const double mean = std::accumulate(rm.begin(), rm.end(), 0.0) / static_cast<double>(rm.size());
  double ss = 0;
  for (double x : rm) ss += (x - mean) * (x - mean);
  const double var_noise = out.noise_sigma_nm * out.noise_sigma_nm / static_cast<double>(B);
  const double dof = static_cast<double>(rm.size() - 1);
  const double q = var_noise > 0 ? ss / var_noise : 1e300;
  // χ²(dof) tail by the Wilson–Hilferty cube-root normal approximation.
  const double z = (std::cbrt(q / dof) - (1.0 - 2.0 / (9.0 * dof))) / std::sqrt(2.0 / (9.0 * dof));
  out.p_value = 0.5 * std::erfc(z / std::sqrt(2.0));
  out.structure_nm = std::sqrt(std::max(0.0, ss / dof - var_noise));
  out.explained = !(out.p_value < alpha);
  for (std::size_t c = 0; c < sig.cols.size(); ++c) out.correlates.emplace_back(sig.names[c], corr(rm, bl.signal[c]));
  std::stable_sort(out.correlates.begin(), out.correlates.end(),
                   [](const auto& a, const auto& b) { return std::fabs(a.second) > std::fabs(b.second); });
  // Steps at z ≥ 6: Bonferroni over a few hundred boundaries a run leaves a false step about once in 10⁵ runs.
  if (!out.explained) out.steps = find_steps(residual, mask, data.time_s, rm, bl.first, B, out.noise_sigma_nm, 6.0, 5);
  return out;
}

std::string describe_remainder(const Remainder& r) {
  std::ostringstream os;
  if (r.explained) {
    os << "what is left is at the noise floor (σ " << r.noise_sigma_nm << " nm estimated from the data)";
    return os.str();
  }
  os << "not explained: " << r.structure_nm << " nm of slow structure above the noise floor (σ " << r.noise_sigma_nm << " nm)";
  if (!r.correlates.empty()) os << ", top correlate " << r.correlates.front().first;
  for (std::size_t i = 0; i < r.steps.size(); ++i)
    os << (i ? ", " : "; steps ") << (r.steps[i].size_nm >= 0 ? "+" : "") << r.steps[i].size_nm << " nm at t = " << r.steps[i].time_s << " s";
  return os.str();
}

}  // namespace piezo::analysis
