// Shared building blocks of the residual loop: streamed regressors, the joint fit of effect terms, predictions.
#include "piezo_compensation/analysis/residual/residual_context.h"
#include "piezo_compensation/util/stats.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <numeric>

namespace piezo::analysis::detail {

using models::EffectTerm;
using models::EffectTermStream;

double mean_of(const std::vector<double>& v, std::size_t a, std::size_t b) { return util::mean(v, a, b); }

double mae_of(const std::vector<double>& r, std::size_t a, std::size_t b) { return util::mean_abs(r, a, b); }

double span_of(const std::vector<double>& v) {
  const auto [lo, hi] = std::minmax_element(v.begin(), v.end());
  return *hi - *lo;
}

SignalStats signal_stats(const Context& c, const std::string& signal) {
  models::InputResolver col(*c.data, {signal}, c.axis);
  std::vector<double> sv(c.x_base.size());
  for (std::size_t i = 0; i < sv.size(); ++i) col.fill(i, &sv[i]);
  SignalStats st;
  st.mean = mean_of(sv, 0, sv.size());
  double var = 0;
  for (double x : sv) var += (x - st.mean) * (x - st.mean);
  st.sd = std::sqrt(var / static_cast<double>(std::max<std::size_t>(1, sv.size())));
  return st;
}

bool reads_position(const std::vector<EffectTerm>& terms) {
  for (const auto& t : terms)
    if (t.signal == models::kSignalPosition) return true;
  return false;
}

EffectTerm make_term(const std::string& family, const std::string& type, const std::string& signal, double lag_s,
                     double tau_s) {
  EffectTerm t;
  t.family = family;
  t.type = type;
  t.signal = signal;
  t.lag_s = lag_s;
  t.time_constant_s = tau_s;
  // a sensor effect's term acts on the readings only (the estimator's reading model), never on the stage position
  t.acts_on = is_reading_family(family) ? models::kActsOnReadings : models::kActsOnPosition;
  return t;
}

std::vector<double> regressors(const Context& c, const std::vector<EffectTerm>& fixed, double offset,
                               const std::vector<EffectTerm>& terms, std::size_t& k_out) {
  std::vector<EffectTerm> all = reads_position(terms) ? fixed : std::vector<EffectTerm>{};
  const std::size_t skip = std::accumulate(all.begin(), all.end(), std::size_t{0},
                                           [](std::size_t s, const EffectTerm& t) { return s + t.num_regressors(); });
  for (const auto& t : terms) all.push_back(t);
  EffectTermStream stream(all, c.fs, reads_position(terms) ? offset : 0.0);
  models::InputResolver cols(*c.data, stream.column_signals(), c.axis);
  const std::size_t k_all = stream.num_regressors(), k = k_all - skip;
  k_out = k;
  const std::size_t n = c.x_base.size();
  std::vector<double> Z(n * k), buf(k_all), colv(std::max<std::size_t>(1, cols.size()));
  for (std::size_t i = 0; i < n; ++i) {
    cols.fill(i, colv.data());
    stream.raw_and_commit(c.voltage[i], c.x_base[i], colv.data(), buf.data());
    std::copy(buf.begin() + static_cast<long>(skip), buf.end(), Z.begin() + static_cast<long>(i * k));
  }
  return Z;
}

namespace {

// One pass of fit_terms: raw regressors with the current weights streaming (position terms see the corrected
// position), standardised on rows [a, b), then a ridge-stabilised least squares with offset and transients.
void fit_pass(const Context& c, std::vector<EffectTerm>& terms, Level& level, std::size_t a, std::size_t b) {
  const std::size_t n = c.x_base.size(), m = c.transient.size();
  EffectTermStream stream(terms, c.fs, level.offset_nm);
  models::InputResolver cols(*c.data, stream.column_signals(), c.axis);
  const std::size_t k = stream.num_regressors();
  std::vector<double> Z(n * k), colv(std::max<std::size_t>(1, cols.size()));
  for (std::size_t i = 0; i < n; ++i) {
    cols.fill(i, colv.data());
    stream.raw_and_commit(c.voltage[i], c.x_base[i], colv.data(), Z.data() + i * k);
  }
  std::vector<double> mu(k, 0.0), sd(k, 0.0);
  const double rows = static_cast<double>(b - a);
  for (std::size_t j = 0; j < k; ++j) {
    for (std::size_t i = a; i < b; ++i) mu[j] += Z[i * k + j];
    mu[j] /= rows;
    for (std::size_t i = a; i < b; ++i) sd[j] += (Z[i * k + j] - mu[j]) * (Z[i * k + j] - mu[j]);
    sd[j] = std::sqrt(sd[j] / rows);
    if (!(sd[j] > 1e-12)) sd[j] = 1.0;  // constant on the fit rows: weight will be ~0
  }
  const std::size_t kk = k + 1 + m;  // offset, the terms' regressors, the start-state transients
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(kk, kk);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(kk), x(kk);
  for (std::size_t i = a; i < b; ++i) {
    x[0] = 1.0;
    for (std::size_t j = 0; j < k; ++j) x[j + 1] = (Z[i * k + j] - mu[j]) / sd[j];
    for (std::size_t j = 0; j < m; ++j) x[k + 1 + j] = c.transient[j][i];
    G.selfadjointView<Eigen::Lower>().rankUpdate(x);
    rhs += x * (c.measured[i] - c.x_base[i]);
  }
  G = G.selfadjointView<Eigen::Lower>();
  for (std::size_t j = 1; j < kk; ++j) G(j, j) += 1e-6 * rows;
  const Eigen::VectorXd beta = G.ldlt().solve(rhs);
  level.offset_nm = beta[0];
  for (std::size_t j = 0; j < m; ++j) level.transient_nm[j] = beta[static_cast<Eigen::Index>(k + 1 + j)];
  std::size_t j = 0;
  for (auto& t : terms)
    for (std::size_t q = 0; q < t.num_regressors(); ++q, ++j) {
      if (t.center.size() != t.num_regressors()) t.center.assign(t.num_regressors(), 0.0);
      if (t.scale.size() != t.num_regressors()) t.scale.assign(t.num_regressors(), 1.0);
      t.center[q] = mu[j];
      t.scale[q] = sd[j];
      t.weight[q] = beta[j + 1];
    }
}

}  // namespace

// Position terms depend on the other weights, so the fit is repeated until it settles.
void fit_terms(const Context& c, std::vector<EffectTerm>& terms, Level& level, std::size_t a, std::size_t b) {
  const int passes = reads_position(terms) ? 3 : 1;
  level.offset_nm = 0.0;
  level.transient_nm.assign(c.transient.size(), 0.0);
  for (auto& t : terms) {
    const std::size_t k = t.num_regressors();
    if (t.weight.size() != k) t.weight.assign(k, 0.0);
  }
  for (int pass = 0; pass < passes; ++pass) fit_pass(c, terms, level, a, b);
}

// Exact in free-run, where the base never sees the correction; in one-step the base is committed with
// measurement − correction, a second-order difference.
std::vector<double> corrected(const Context& c, const std::vector<EffectTerm>& terms, const Level& level) {
  EffectTermStream stream(terms, c.fs, level.offset_nm);
  models::InputResolver cols(*c.data, stream.column_signals(), c.axis);
  std::vector<double> out(c.x_base.size()), colv(std::max<std::size_t>(1, cols.size()));
  for (std::size_t i = 0; i < out.size(); ++i) {
    cols.fill(i, colv.data());
    out[i] = c.x_base[i] + stream.commit(c.voltage[i], c.x_base[i], colv.data());
    for (std::size_t j = 0; j < level.transient_nm.size(); ++j) out[i] += level.transient_nm[j] * c.transient[j][i];
  }
  return out;
}

std::vector<double> residual_of(const Context& c, const std::vector<EffectTerm>& terms, const Level& level) {
  std::vector<double> r = corrected(c, terms, level);
  for (std::size_t i = 0; i < r.size(); ++i) r[i] = c.measured[i] - r[i];
  return r;
}

}  // namespace piezo::analysis::detail
