// The residual loop: score every effect family on the current residual, add the best significant one, refit.
#include "piezo_compensation/analysis/residual.h"

#include "piezo_compensation/analysis/evaluation.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_common.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <set>
#include <sstream>
#include <stdexcept>

namespace piezo::analysis {

using models::EffectTerm;
using models::EffectTermStream;

const std::vector<std::string>& residual_family_names() {
  static const std::vector<std::string> names = {
      "time_drift",     "cross_axis", "position_periodic",    "rate_dependent", "aux_signal", "periodic_disturbance",
      "missing_memory", "voltage_nonlinearity", "time_gain", "cross_axis_gain", "aux_gain"};
  return names;
}

bool is_gain_family(const std::string& family) {
  return family == "time_gain" || family == "cross_axis_gain" || family == "aux_gain";
}

std::string additive_counterpart(const std::string& gain_family) {
  if (gain_family == "time_gain") return "time_drift";
  if (gain_family == "cross_axis_gain") return "cross_axis";
  if (gain_family == "aux_gain") return "aux_signal";
  return "";
}

bool extrapolates_in_time(const std::string& family) { return family == "time_drift" || family == "time_gain"; }

bool is_operating_point_family(const std::string& family) {
  return family == "voltage_nonlinearity" || family == "position_periodic" || family == "rate_dependent" ||
         family == "missing_memory";
}

namespace {
std::vector<double> run_model(models::Model& m, const io::Dataset& d, const std::string& axis, PredictionMode mode) {
  models::StreamOptions so;
  so.mode = mode;
  return models::stream_model(m, d, axis, so).prediction;
}
}  // namespace

bool continues_in_time(const io::Dataset& prev, const io::Dataset& next) {
  if (prev.size() < 2 || next.empty()) return false;
  const double dt = prev.time_s[1] - prev.time_s[0];
  return std::fabs(next.time_s.front() - (prev.time_s.back() + dt)) < 0.5 * dt;
}

namespace {

double mean_of(const std::vector<double>& v, std::size_t a, std::size_t b) {
  double s = 0;
  for (std::size_t i = a; i < b; ++i) s += v[i];
  return b > a ? s / static_cast<double>(b - a) : 0.0;
}

double mae_of(const std::vector<double>& r, std::size_t a, std::size_t b) {
  double s = 0;
  for (std::size_t i = a; i < b; ++i) s += std::fabs(r[i]);
  return b > a ? s / static_cast<double>(b - a) : 0.0;
}

bool reads_position(const std::vector<EffectTerm>& terms) {
  for (const auto& t : terms)
    if (t.signal == models::kSignalPosition) return true;
  return false;
}

// Everything the loop needs about TRAIN, computed once.
struct Context {
  const io::Dataset* data = nullptr;
  std::string axis;
  double fs = 11.0;
  std::vector<double> voltage, measured, x_base;  // x_base: base model prediction per row
  std::vector<std::string> other_axes;            // other axes' voltage and position column names
  std::vector<std::string> aux_names;             // auxiliary columns
  double x_at_zero_v = 0.0;                       // the stage's position at 0 V: where a stroke gain acts about
  // Start-state transients (ResidualOptions::start_transients): exp(−(t − t₀)/τ_j) per row, one column per τ_j.
  // A base started "at rest at the first voltage" on data that begins mid-history is wrong by the unknown initial
  // state of each of its creep modes, which decays with that mode's τ: fitted as nuisance terms, never put in the
  // model (the live model has the true history).
  std::vector<double> transient_taus_s;
  std::vector<std::vector<double>> transient;
};

// The fitted level of the base residual besides the effect terms: a constant and the start-state transients.
struct Level {
  double offset_nm = 0.0;
  std::vector<double> transient_nm;  // weight per Context::transient column [nm at t₀]
};

// Raw regressors of `terms` over all rows (streamed from row 0). `fixed` terms (already weighted) run in the
// same stream so that position terms see the corrected position; only `terms`' columns are returned.
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
    stream.raw(c.voltage[i], c.x_base[i], colv.data(), buf.data());
    std::copy(buf.begin() + static_cast<long>(skip), buf.end(), Z.begin() + static_cast<long>(i * k));
    stream.commit(c.voltage[i], c.x_base[i], colv.data());
  }
  return Z;
}

// Fits centre/scale and weights of `terms` (jointly, with an offset) to the base residual on rows [a, b).
// Position terms depend on the other weights, so the fit is repeated until it settles.
void fit_terms(const Context& c, std::vector<EffectTerm>& terms, Level& level, std::size_t a, std::size_t b) {
  const std::size_t n = c.x_base.size();
  const int passes = reads_position(terms) ? 3 : 1;
  const std::size_t m = c.transient.size();
  double& offset = level.offset_nm;
  offset = 0.0;
  level.transient_nm.assign(m, 0.0);
  for (auto& t : terms) {
    const std::size_t k = t.num_regressors();
    if (t.weight.size() != k) t.weight.assign(k, 0.0);
  }
  for (int pass = 0; pass < passes; ++pass) {
    EffectTermStream stream(terms, c.fs, offset);
    models::InputResolver cols(*c.data, stream.column_signals(), c.axis);
    const std::size_t k = stream.num_regressors();
    std::vector<double> Z(n * k), colv(std::max<std::size_t>(1, cols.size()));
    for (std::size_t i = 0; i < n; ++i) {
      cols.fill(i, colv.data());
      stream.raw(c.voltage[i], c.x_base[i], colv.data(), Z.data() + i * k);
      stream.commit(c.voltage[i], c.x_base[i], colv.data());
    }
    std::vector<double> mu(k, 0.0), sd(k, 0.0);
    for (std::size_t j = 0; j < k; ++j) {
      for (std::size_t i = a; i < b; ++i) mu[j] += Z[i * k + j];
      mu[j] /= static_cast<double>(b - a);
      for (std::size_t i = a; i < b; ++i) sd[j] += (Z[i * k + j] - mu[j]) * (Z[i * k + j] - mu[j]);
      sd[j] = std::sqrt(sd[j] / static_cast<double>(b - a));
      if (!(sd[j] > 1e-12)) sd[j] = 1.0;  // constant on the fit rows: weight will be ~0
    }
    const std::size_t kk = k + 1 + m;  // offset, the terms' regressors, the start-state transients
    Eigen::MatrixXd G = Eigen::MatrixXd::Zero(kk, kk);
    Eigen::VectorXd rhs = Eigen::VectorXd::Zero(kk);
    Eigen::VectorXd x(kk);
    for (std::size_t i = a; i < b; ++i) {
      x[0] = 1.0;
      for (std::size_t j = 0; j < k; ++j) x[j + 1] = (Z[i * k + j] - mu[j]) / sd[j];
      for (std::size_t j = 0; j < m; ++j) x[k + 1 + j] = c.transient[j][i];
      G.selfadjointView<Eigen::Lower>().rankUpdate(x);
      rhs += x * (c.measured[i] - c.x_base[i]);
    }
    G = G.selfadjointView<Eigen::Lower>();
    for (std::size_t j = 1; j < kk; ++j) G(j, j) += 1e-6 * static_cast<double>(b - a);
    const Eigen::VectorXd beta = G.ldlt().solve(rhs);
    offset = beta[0];
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
}

// Model prediction on TRAIN rows from x_base plus the terms (exact in free-run, where the base never sees the
// correction; in one-step the base is committed with measurement − correction, a second-order difference).
std::vector<double> corrected(const Context& c, const std::vector<EffectTerm>& terms, const Level& level) {
  EffectTermStream stream(terms, c.fs, level.offset_nm);
  models::InputResolver cols(*c.data, stream.column_signals(), c.axis);
  std::vector<double> out(c.x_base.size()), colv(std::max<std::size_t>(1, cols.size()));
  for (std::size_t i = 0; i < out.size(); ++i) {
    cols.fill(i, colv.data());
    out[i] = c.x_base[i] + stream.correction(c.voltage[i], c.x_base[i], colv.data());
    for (std::size_t j = 0; j < level.transient_nm.size(); ++j) out[i] += level.transient_nm[j] * c.transient[j][i];
    stream.commit(c.voltage[i], c.x_base[i], colv.data());
  }
  return out;
}

EffectTerm term(const std::string& family, const std::string& type, const std::string& signal, double lag_s = 0.0,
                double tau_s = 0.0) {
  EffectTerm t;
  t.family = family;
  t.type = type;
  t.signal = signal;
  t.lag_s = lag_s;
  t.time_constant_s = tau_s;
  return t;
}

double span_of(const std::vector<double>& v) {
  const auto [lo, hi] = std::minmax_element(v.begin(), v.end());
  return *hi - *lo;
}

struct FamilyCandidates {
  std::vector<Candidate> variants;
  bool spectral = false;      // p-value from the periodogram test, not from shifts
  PeriodicPeak peak;
  std::string note;
};

FamilyCandidates candidates(const std::string& family, const Context& c, const std::vector<double>& residual,
                            const std::vector<double>& position, std::size_t stride) {
  FamilyCandidates fc;
  const double dt = 1.0 / c.fs;
  const double duration = dt * static_cast<double>(c.x_base.size());
  auto add = [&](std::vector<EffectTerm> terms, std::map<std::string, double> p, std::map<std::string, std::string> l = {}) {
    fc.variants.push_back(Candidate{family, std::move(terms), std::move(p), std::move(l)});
  };
  if (family == "time_drift") {
    // A constant drift rate: the one time basis that extrapolates sanely past the training data.
    add({term(family, "linear", models::kSignalTime)}, {});
  } else if (family == "cross_axis") {
    if (c.other_axes.empty()) fc.note = "no other axis in the data";
    for (const auto& col : c.other_axes) {
      for (double lag : {0.0, 0.5, 1.0, 2.0, 5.0, 10.0})
        for (double tau : {0.0, 2.0, 10.0, 60.0})
          add({term(family, "linear", col, lag, tau)}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", col}});
      EffectTerm play = term(family, "play", col);
      play.threshold = 10.0;
      add({term(family, "linear", col), play}, {{"lag_s", 0.0}, {"play_threshold_v", 10.0}}, {{"signal", col}});
    }
  } else if (family == "aux_signal") {
    if (c.aux_names.empty()) fc.note = "no auxiliary column in the data";
    for (const auto& col : c.aux_names)
      for (double lag : {0.0, 10.0, 60.0})
        for (double tau : {0.0, 30.0, 300.0})
          add({term(family, "linear", col, lag, tau)}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", col}});
  } else if (is_gain_family(family)) {
    // The base output scaled by 1 + f(signal) (f linear here; quadratic and gain-on-voltage are tried at
    // validation, see trace_residual). Signals as in the additive families, lags/low-passes chosen by the data.
    std::vector<std::string> sigs;
    std::vector<double> lags{0.0}, taus{0.0};
    if (family == "time_gain") {
      sigs = {models::kSignalTime};
    } else if (family == "cross_axis_gain") {
      sigs = c.other_axes;
      lags = {0.0, 1.0, 5.0};
      taus = {0.0, 10.0, 60.0};
      if (sigs.empty()) fc.note = "no other axis in the data";
    } else {
      sigs = c.aux_names;
      // Thermal paths are slow: delays up to minutes, low-passes up to ~20 min.
      lags = {0.0, 15.0, 45.0, 120.0};
      taus = {0.0, 30.0, 100.0, 300.0, 1000.0};
      if (sigs.empty()) fc.note = "no auxiliary column in the data";
    }
    for (const auto& sig : sigs) {
      models::InputResolver col(*c.data, {sig}, c.axis);
      std::vector<double> sv(c.x_base.size());
      for (std::size_t i = 0; i < sv.size(); ++i) col.fill(i, &sv[i]);
      const double mu = mean_of(sv, 0, sv.size());
      double var = 0;
      for (double x : sv) var += (x - mu) * (x - mu);
      const double sd = std::sqrt(var / static_cast<double>(std::max<std::size_t>(1, sv.size())));
      if (!(sd > 0)) continue;
      for (double lag : lags)
        for (double tau : taus) {
          EffectTerm t = term(family, "gain", sig, lag, tau);
          t.scales = models::kSignalPosition;
          t.reference = c.x_at_zero_v;
          t.pre_center = mu;
          t.pre_scale = sd;
          add({t}, {{"lag_s", lag}, {"time_constant_s", tau}}, {{"signal", sig}, {"scales", "position"}});
        }
    }
    if (fc.variants.empty() && fc.note.empty()) fc.note = "signal constant";
  } else if (family == "rate_dependent") {
    for (double tau : {0.0, 1.0, 5.0, 20.0, 60.0})
      add({term(family, "rate", models::kSignalVoltage, 0.0, tau)}, {{"time_constant_s", tau}});
  } else if (family == "missing_memory") {
    for (double tau : {10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0})
      add({term(family, "linear", models::kSignalVoltage, 0.0, tau)}, {{"time_constant_s", tau}});
    for (double r : {5.0, 20.0})
      for (double tau : {30.0, 300.0, 1000.0}) {
        EffectTerm t = term(family, "play", models::kSignalVoltage, 0.0, tau);
        t.threshold = r;
        add({t}, {{"time_constant_s", tau}, {"play_threshold_v", r}});
      }
  } else if (family == "voltage_nonlinearity") {
    auto powers = [&](const std::string& sig, const std::vector<double>& v) {
      EffectTerm t = term(family, "powers", sig);
      t.pre_center = mean_of(v, 0, v.size());
      t.pre_scale = std::max(1e-9, span_of(v) / 2.0);
      return t;
    };
    add({powers(models::kSignalVoltage, c.voltage)}, {}, {{"signal", models::kSignalVoltage}});
    add({powers(models::kSignalPosition, position)}, {}, {{"signal", models::kSignalPosition}});
  } else if (family == "periodic_disturbance" || family == "position_periodic") {
    fc.spectral = true;
    const bool in_time = family == "periodic_disturbance";
    std::vector<double> u, r;
    if (in_time) {
      u = c.data->time_s;
      r = residual;
    } else {
      for (std::size_t i = 0; i < residual.size(); i += stride) {
        u.push_back(position[i]);
        r.push_back(residual[i]);
      }
    }
    const double range = span_of(u);
    // Time: at least 8 full periods inside TRAIN (fewer cannot be told from slow structure such as creep the
    // model misses), up to 0.98·Nyquist. Position: at least 4 full periods across the visited range (a smooth
    // shape over the stroke is voltage_nonlinearity's or a gain's; a random walk traverses each period many
    // times), down to 30 nm.
    const double f_min = in_time ? 8.0 / duration : 4.0 / std::max(range, 1e-9);
    const double f_max = in_time ? 0.49 * c.fs : 1.0 / 30.0;
    if (f_max <= f_min) {
      fc.note = in_time ? "data too short" : "position range too small";
      return fc;
    }
    fc.peak = find_periodic_peak(u, r, f_min, f_max, 4.0);
    if (fc.peak.frequency <= 0) {
      fc.note = "no spectrum";
      return fc;
    }
    const double period = 1.0 / fc.peak.frequency;
    EffectTerm t = term(family, "sincos", in_time ? models::kSignalTime : models::kSignalPosition);
    t.period = period;
    if (in_time)
      add({t}, {{"period_s", period}, {"frequency_hz", fc.peak.frequency}, {"power_ratio", fc.peak.power_ratio}});
    else
      add({t}, {{"period_nm", period}, {"power_ratio", fc.peak.power_ratio}});
    std::ostringstream os;
    os << "peak " << fc.peak.power_ratio << "× the red-noise background, " << fc.peak.searched << " frequencies searched";
    fc.note = os.str();
  } else {
    throw std::invalid_argument("unknown effect family '" + family + "'");
  }
  return fc;
}

double normal_tail(double z) { return 0.5 * std::erfc(z / std::sqrt(2.0)); }

FamilyScore score_family(const std::string& family, const Context& c, const std::vector<EffectTerm>& fixed, const Level& level,
                         const std::vector<double>& residual, const std::vector<double>& position,
                         const ResidualOptions& o, std::mt19937_64& rng) {
  FamilyScore fs;
  fs.family = family;
  const std::size_t n = residual.size();
  const std::size_t stride = std::max<std::size_t>(1, (n + o.max_score_samples - 1) / o.max_score_samples);
  FamilyCandidates fc = candidates(family, c, residual, position, stride);
  fs.variants = fc.variants.size();
  fs.note = fc.note;
  if (fc.variants.empty()) {
    fs.available = false;
    return fs;
  }
  std::vector<double> rd;
  for (std::size_t i = 0; i < n; i += stride) rd.push_back(residual[i]);
  const std::size_t nd = rd.size();
  std::vector<std::size_t> shifts;
  if (!fc.spectral) {
    std::uniform_int_distribution<std::size_t> pick(nd / 10, nd - nd / 10);
    for (int s = 0; s < o.permutations; ++s) shifts.push_back(pick(rng));
  }
  std::vector<double> null_max(shifts.size(), -1e300);
  double best = -1e300;
  for (const auto& cand : fc.variants) {
    std::size_t k = 0;
    const std::vector<double> Z = regressors(c, fixed, level.offset_nm, cand.terms, k);
    std::vector<double> Zd;
    Zd.reserve(nd * k);
    for (std::size_t i = 0; i < n; i += stride) Zd.insert(Zd.end(), Z.begin() + static_cast<long>(i * k), Z.begin() + static_cast<long>((i + 1) * k));
    const CvScore s = cv_explained_variance(rd, Zd, k, o.cv_folds, shifts);
    if (s.explained_variance > best) {
      best = s.explained_variance;
      fs.best = cand;
    }
    for (std::size_t q = 0; q < shifts.size(); ++q) null_max[q] = std::max(null_max[q], s.null_explained_variance[q]);
  }
  fs.explained_variance = best;
  if (fc.spectral) {
    fs.p_value = fc.peak.p_value;
  } else {
    // The observed best against the best of each circularly shifted draw (same search, alignment destroyed):
    // a Gaussian tail beyond the draws, the empirical rank within them.
    double m = 0, v = 0, above = 0;
    for (double x : null_max) m += x;
    m /= static_cast<double>(null_max.size());
    for (double x : null_max) {
      v += (x - m) * (x - m);
      if (x >= best) above += 1;
    }
    const double sd = std::sqrt(v / std::max<std::size_t>(1, null_max.size() - 1));
    const double p_emp = (1.0 + above) / (1.0 + static_cast<double>(null_max.size()));
    const double p_gauss = sd > 0 ? normal_tail((best - m) / sd) : (best > m ? 0.0 : 1.0);
    fs.p_value = above > 0 ? p_emp : std::min(p_emp, p_gauss);
    std::ostringstream os;
    os << "circular-shift null: mean " << m << ", sd " << sd << " over " << null_max.size() << " draws";
    fs.note = os.str();
  }
  fs.significant = fs.p_value < o.alpha && fs.explained_variance >= o.min_explained_variance;
  return fs;
}

// Fitted parameters of one effect from the weights of its terms.
void describe(const std::vector<EffectTerm>& terms, std::size_t first, std::size_t count, FoundEffect& e) {
  for (std::size_t i = first; i < first + count; ++i) {
    const EffectTerm& t = terms[i];
    auto w = [&](std::size_t q) { return t.weight[q] / t.scale[q]; };  // per raw unit
    const std::string pre = count > 1 ? "term" + std::to_string(i - first) + "_" : "";
    if (t.type == "sincos") {
      e.parameters[pre + "amplitude_nm"] = std::hypot(w(0), w(1));
      e.parameters[pre + "phase_rad"] = std::atan2(w(1), w(0));
    } else if (t.type == "linear" || t.type == "play") {
      if (t.signal == models::kSignalTime) {
        e.parameters["drift_nm_per_h"] = w(0) * 3600.0;
      } else {
        const std::string unit = t.signal == models::kSignalVoltage || t.signal.find("_voltage_v") != std::string::npos
                                     ? "nm_per_v"
                                     : "nm_per_unit";
        e.parameters[pre + (t.type == "play" ? "play_gain_" : "gain_") + unit] = w(0);
      }
    } else if (t.type == "rate") {
      e.parameters["gain_nm_per_v_step"] = w(0);
      e.parameters["gain_nm_per_abs_v_step"] = w(1);
      e.parameters["gain_nm_per_signed_v2_step"] = w(2);
    } else if (t.is_gain()) {
      // f(s) = w·g(s)/(q − ref) per unit of the centred signal: relative gain change per signal unit.
      const std::string sig = t.signal == models::kSignalTime ? "per_h" : "per_unit";
      const double k = t.signal == models::kSignalTime ? 3600.0 : 1.0;
      // On the voltage the change is in nm per volt (the relative change is that over the stage's nm/V).
      e.parameters[pre + (t.scales == models::kSignalVoltage ? "gain_change_nm_per_v_" : "gain_change_") + sig] =
          w(0) / t.pre_scale * k;
      if (t.type == "gain_quadratic") e.parameters[pre + "gain_change_quadratic"] = t.weight[1] / t.scale[1];
      e.labels["scales"] = t.scales;
      e.labels["form"] = t.type == "gain" ? "linear" : "quadratic";
    } else if (t.type == "powers") {
      e.parameters["quadratic_nm"] = w(0);
      e.parameters["cubic_nm"] = w(1);
    }
  }
}

// Time constants of the start-state transients: the base's own creep modes that TRAIN can see decay (τ from 5 s
// to twice its duration; longer ones are an offset over TRAIN), or, for a base without modes, a decade grid in
// the same range.
std::vector<double> start_transient_taus(const models::Model& base, const io::Dataset& train) {
  const double duration = train.time_s.back() - train.time_s.front();
  const models::Model* m = &base;
  if (const auto* aug = dynamic_cast<const models::AugmentedModel*>(m)) m = &aug->base();
  std::vector<double> taus;
  if (const auto* pi = dynamic_cast<const models::PiCreepModel*>(m)) taus = pi->mode_taus_s();
  if (taus.empty()) taus = {10.0, 100.0, 1000.0};
  std::vector<double> out;
  for (double t : taus)
    if (t >= 5.0 && t <= 2.0 * duration) out.push_back(t);
  std::sort(out.begin(), out.end());
  return out;
}

// Where a stroke gain acts about: the stage's position at 0 V. The base at rest at 0 V after a reset is a virgin
// state the stage need not be in (hysteresis leaves it anywhere within the loop at 0 V); the mean of what the stage
// did at 0 V is read from the data: a straight line through the measured positions of the rows within ±2.5 % of
// the voltage span of 0 V, taken at 0 V (the line removes the slope across the band, so the band's width matters
// little). Where the data come near 0 V in fewer than max(200, 0.5 % of the rows) rows, `fallback`.
double position_at_zero_volts(const std::vector<double>& v, const std::vector<double>& y, double fallback) {
  const double band = 0.025 * span_of(v);
  double n = 0, sv = 0, sy = 0, svv = 0, svy = 0;
  for (std::size_t i = 0; i < v.size(); ++i)
    if (std::fabs(v[i]) <= band) n += 1, sv += v[i], sy += y[i], svv += v[i] * v[i], svy += v[i] * y[i];
  if (n < std::max(200.0, 0.005 * static_cast<double>(v.size()))) return fallback;
  const double mv = sv / n, my = sy / n, var = svv / n - mv * mv;
  if (!(var > 1e-12 * band * band)) return my;
  return my - (svy / n - mv * my) / var * mv;
}

std::vector<double> truth_or_empty(const io::Dataset& d, const std::string& axis) {
  const auto& ax = d.axis(axis);
  return ax.has_truth() ? ax.true_position_nm : std::vector<double>{};
}

}  // namespace

ResidualResult trace_residual(const models::Model& base, const io::Dataset& train, const io::Dataset& test,
                              const ResidualOptions& o) {
  auto log = [&](const std::string& s) {
    if (o.log) o.log(s);
  };
  train.validate();
  test.validate();
  if (train.size() < 200) throw io::DataError((train.source.empty() ? "TRAIN" : train.source) + ": too few rows for the residual tool (need ≥ 200)");
  if (test.empty()) throw io::DataError((test.source.empty() ? "TEST" : test.source) + ": no rows");
  const double fs = train.sample_rate_hz();
  if (std::fabs(test.sample_rate_hz() / fs - 1.0) > 0.02)
    throw io::DataError("TRAIN and TEST have different sample rates (" + std::to_string(fs) + " vs " +
                        std::to_string(test.sample_rate_hz()) + " Hz)");
  if (!(o.validation_fraction > 0.05 && o.validation_fraction < 0.8))
    throw std::invalid_argument("validation fraction must be in (0.05, 0.8)");
  for (const auto& f : o.families)
    if (std::find(residual_family_names().begin(), residual_family_names().end(), f) == residual_family_names().end())
      throw std::invalid_argument("unknown effect family '" + f + "'");

  Context c;
  c.data = &train;
  c.axis = o.axis;
  c.fs = fs;
  const auto& ax = train.axis(o.axis);
  c.voltage = ax.voltage_v;
  c.measured = ax.position_nm;
  {
    models::ModelPtr b = base.clone();
    c.x_base = run_model(*b, train, o.axis, o.mode);
  }
  for (const auto& other : train.axes)
    if (other.name != o.axis && test.has_axis(other.name)) {
      c.other_axes.push_back(io::voltage_column(other.name));
      c.other_axes.push_back(io::position_column(other.name));
    }
  {
    // Inputs held at their first values: only the rest position at 0 V matters here.
    models::ModelPtr b = base.clone();
    b->reset(0.0, ax.position_nm[0]);
    models::InputResolver in(train, b->aux_inputs(), o.axis);
    c.x_at_zero_v = b->predict(models::ModelInput{0.0, in.at(0)});
    if (!std::isfinite(c.x_at_zero_v)) c.x_at_zero_v = mean_of(c.x_base, 0, c.x_base.size());
  }
  {
    const double fallback = c.x_at_zero_v;
    c.x_at_zero_v = position_at_zero_volts(c.voltage, c.measured, fallback);
    std::ostringstream os;
    os << "stroke-gain pivot: measured position at 0 V " << c.x_at_zero_v << " nm (the base at rest at 0 V: " << fallback << " nm)";
    log(os.str());
  }
  for (const auto& a : train.aux)
    if (test.find_aux(a.name)) c.aux_names.push_back(a.name);
  if (o.start_transients) {
    c.transient_taus_s = start_transient_taus(base, train);
    for (double tau : c.transient_taus_s) {
      std::vector<double> col(train.size());
      for (std::size_t i = 0; i < col.size(); ++i) col[i] = std::exp(-(train.time_s[i] - train.time_s[0]) / tau);
      c.transient.push_back(std::move(col));
    }
  }

  const std::size_t n = train.size();
  const std::size_t n_fit = static_cast<std::size_t>(std::lround(static_cast<double>(n) * (1.0 - o.validation_fraction)));
  const std::vector<double> truth_test = truth_or_empty(test, o.axis);
  const std::vector<double>& meas_test = test.axis(o.axis).position_nm;

  ResidualResult res;
  res.warm_started = o.warm_start && continues_in_time(train, test);
  res.anchor_s = o.anchor_s;
  models::StreamOptions test_run;
  test_run.mode = o.mode;
  test_run.warmup = res.warm_started ? &train : nullptr;
  test_run.anchor_s = o.anchor_s;
  // With start transients and TEST continuing TRAIN, the transients fitted on TRAIN run on into TEST: the base's
  // cold-start error is not the model's (a live model has the true history), so it is not scored against it.
  auto run_test = [&](models::Model& m, const Level& lv) {
    const models::StreamResult r = models::stream_model(m, test, o.axis, test_run);
    res.test_first_scored = r.first_scored;
    std::vector<double> p = r.prediction;
    if (res.warm_started)
      for (std::size_t j = 0; j < lv.transient_nm.size(); ++j)
        for (std::size_t i = 0; i < p.size(); ++i)
          p[i] += lv.transient_nm[j] * std::exp(-(test.time_s[i] - train.time_s[0]) / c.transient_taus_s[j]);
    return p;
  };
  {
    Level lv0;  // the transients alone (no effect terms): the base's TEST error without its cold start
    if (!c.transient.empty()) {
      std::vector<EffectTerm> none;
      fit_terms(c, none, lv0, 0, n);
      lv0.offset_nm = 0.0;  // an offset is not the base's: only the decays are carried
      std::ostringstream os;
      os << "start transients (mid-history): τ";
      for (std::size_t j = 0; j < lv0.transient_nm.size(); ++j)
        os << (j ? ", " : " ") << c.transient_taus_s[j] << " s: " << lv0.transient_nm[j] << " nm";
      log(os.str());
    }
    models::ModelPtr b = base.clone();
    res.test_pred_before = run_test(*b, lv0);
  }
  res.test_mask.assign(test.size(), 1);
  for (std::size_t i = 0; i < res.test_first_scored && i < test.size(); ++i) res.test_mask[i] = 0;
  res.before_test = error_stats(res.test_pred_before, meas_test, res.test_mask);
  if (!truth_test.empty()) res.before_test_truth = error_stats(res.test_pred_before, truth_test, res.test_mask);

  models::ModelPtr cur_base = base.clone();  // refitted by backfitting when options.refit_base is set
  std::vector<EffectTerm> terms;           // accepted, fitted on all of TRAIN
  std::vector<std::size_t> effect_first;   // first term index of each effect
  Level level;
  std::mt19937_64 rng(o.seed);
  const auto& fams = o.families.empty() ? residual_family_names() : o.families;

  // Validation: terms fitted on TRAIN's first part, scored on the rest; separately inside holds (the hold guard).
  const std::vector<char> holds = hold_mask(train);
  std::size_t n_val_hold = 0;
  for (std::size_t i = n_fit; i < n; ++i) n_val_hold += holds[i] != 0;
  struct Val {
    double mae = 0, hold_mae = 0, mae1 = 0, mae2 = 0;
    std::vector<double> abs_err;  // per validation sample, for paired comparisons
  };
  auto validate = [&](std::vector<EffectTerm> t) {
    Level off;
    fit_terms(c, t, off, 0, n_fit);
    const std::vector<double> pred = corrected(c, t, off);
    Val v;
    double sh = 0;
    const std::size_t mid = n_fit + (n - n_fit) / 2;
    for (std::size_t i = n_fit; i < n; ++i) {
      const double e = std::fabs(c.measured[i] - pred[i]);
      v.abs_err.push_back(e);
      v.mae += e;
      (i < mid ? v.mae1 : v.mae2) += e;  // the two halves of the validation part, in the same pass
      if (holds[i]) sh += e;
    }
    if (mid > n_fit) v.mae1 /= static_cast<double>(mid - n_fit);
    if (n > mid) v.mae2 /= static_cast<double>(n - mid);
    v.mae /= static_cast<double>(n - n_fit);
    v.hold_mae = n_val_hold ? sh / static_cast<double>(n_val_hold) : 0.0;
    return v;
  };
  {
    std::vector<double> r(n);
    for (std::size_t i = 0; i < n; ++i) r[i] = c.measured[i] - c.x_base[i];
    res.before_validation.mae_nm = mae_of(r, n_fit, n);
  }
  // Validation MAE of `fixed` plus the family's best variant; a gain's form (on the output or, to first order,
  // on the voltage; f linear or quadratic) is chosen here. The output gain with f linear is the default; another
  // form must be clearly better (paired 5-min blocks, > 2 SE; a quadratic also 1 % better): on the other-axis gain
  // stage the voltage form had won by 0.005 nm of 17.5 nm validation MAE and left 12.3 nm on TEST against the
  // truth, the output form 5.0 nm.
  auto validate_family = [&](FamilyScore& s, const std::vector<EffectTerm>& fixed, const Val& now, bool choose_form = true) {
    auto score = [&](const Candidate& cand) {
      std::vector<EffectTerm> trial = fixed;
      for (const auto& t : cand.terms) trial.push_back(t);
      return validate(trial);
    };
    const auto block = static_cast<std::size_t>(std::lround(300.0 * c.fs));  // the paired tests' 5-min blocks
    Val v = score(s.best);
    if (is_gain_family(s.family) && choose_form) {
      const Candidate base_cand = s.best;
      for (const char* scales : {models::kSignalPosition, models::kSignalVoltage})
        for (const char* form : {"gain", "gain_quadratic"}) {
          Candidate alt = base_cand;
          alt.terms[0].scales = scales;
          alt.terms[0].type = form;
          alt.terms[0].reference = std::string(scales) == models::kSignalVoltage ? 0.0 : c.x_at_zero_v;
          alt.terms[0].center.clear(), alt.terms[0].scale.clear(), alt.terms[0].weight.clear();
          if (alt.terms[0].scales == base_cand.terms[0].scales && alt.terms[0].type == base_cand.terms[0].type) continue;
          const Val va = score(alt);
          {
            std::ostringstream os;
            os << "    form " << form << " on the " << scales << ": validation MAE " << va.mae << " nm (linear on the output "
               << v.mae << " nm)";
            log(os.str());
          }
          const double need = std::string(form) == "gain_quadratic" ? 0.99 : 1.0;
          if (va.mae < need * v.mae && training::validation_prefers(va.abs_err, v.abs_err, block)) {
            v = va;
            s.best = alt;
            s.best.labels["scales"] = scales;
          }
        }
      s.best.labels["form"] = s.best.terms[0].type == "gain" ? "linear" : "quadratic";
    }
    // The grid's low-pass is a factor ~3 off at worst (a 20-s thermal lag read through 30 s leaves a phase error
    // of ~11° on a 200-s cycle, ~10 nm on a 90-nm swing): each term's time constant is refined by a pattern search
    // in log τ (factor 2, then √2, … down to 1.1; within a factor 4 of the grid's choice) on the RMS of the joint
    // fit over all of TRAIN — more rows than the validation part, so τ is not chosen on its noise. The family's
    // significance stays that of the grid search; its validation gain is that of the refined τ. (Refining the lag
    // the same way was tried on the 4 %/°C gain behind 45 s + 240 s: it moved 120 s + 119 s to 145 s + 100 s,
    // 4.90 → 4.86 nm against the truth; not kept.)
    auto train_ms = [&](const Candidate& cand) {
      std::vector<EffectTerm> trial = fixed;
      for (const auto& t : cand.terms) trial.push_back(t);
      Level lv;
      fit_terms(c, trial, lv, 0, n);
      const std::vector<double> p = corrected(c, trial, lv);
      double ss = 0.0;
      for (std::size_t i = 0; i < n; ++i) ss += (c.measured[i] - p[i]) * (c.measured[i] - p[i]);
      return ss / static_cast<double>(n);
    };
    bool refined = false;
    for (std::size_t q = 0; q < s.best.terms.size(); ++q) {
      if (!(s.best.terms[q].time_constant_s > 0.0)) continue;
      const double tau0 = s.best.terms[q].time_constant_s;
      double best_ms = train_ms(s.best);
      for (double f = 2.0; f > 1.1; f = std::sqrt(f)) {
        for (bool moved = true; moved;) {
          moved = false;
          for (double k : {f, 1.0 / f}) {
            const double tau = s.best.terms[q].time_constant_s * k;
            if (tau > 4.0 * tau0 * (1 + 1e-9) || tau < tau0 / 4.0 * (1 - 1e-9)) continue;
            Candidate alt = s.best;
            alt.terms[q].time_constant_s = tau;
            alt.terms[q].center.clear(), alt.terms[q].scale.clear(), alt.terms[q].weight.clear();
            const double ms = train_ms(alt);
            if (ms < best_ms * (1.0 - 1e-4)) {
              best_ms = ms;
              s.best = alt;
              moved = refined = true;
              break;
            }
          }
        }
      }
      if (s.best.terms.size() == 1 || q == 0) s.best.parameters["time_constant_s"] = s.best.terms[q].time_constant_s;
    }
    if (refined) v = score(s.best);
    s.validation_gain = 1.0 - v.mae / now.mae;
    s.hold_validation_gain = n_val_hold ? 1.0 - v.hold_mae / now.hold_mae : 0.0;
    s.validation_gain_halves = {1.0 - v.mae1 / now.mae1, 1.0 - v.mae2 / now.mae2};
    {
      // Worse in a half only counts when it is clearly worse there (paired 5-min blocks, > 2 SE; with under four
      // blocks in the half the lower mean decides, as a plain comparison would).
      const std::size_t nv = std::min(v.abs_err.size(), now.abs_err.size()), h = nv / 2;
      auto part = [](const std::vector<double>& e, std::size_t b, std::size_t en) {
        return std::vector<double>(e.begin() + static_cast<long>(b), e.begin() + static_cast<long>(en));
      };
      s.half_clearly_worse = training::validation_prefers(part(now.abs_err, 0, h), part(v.abs_err, 0, h), block) ||
                             training::validation_prefers(part(now.abs_err, h, nv), part(v.abs_err, h, nv), block);
    }
    s.parameters = 0;
    for (const auto& t : s.best.terms) s.parameters += t.num_regressors();
    std::ostringstream variant;
    for (const auto& [k, x] : s.best.parameters) variant << " " << k << "=" << x;
    for (const auto& [k, x] : s.best.labels) variant << " " << k << "=" << x;
    const bool clearly = training::validation_prefers(v.abs_err, now.abs_err, block);
    log("  validation MAE gain of " + s.family + variant.str() + ": " + std::to_string(100.0 * s.validation_gain) + " %" +
        (n_val_hold ? ", in holds " + std::to_string(100.0 * s.hold_validation_gain) + " %" : "") + " (halves " +
        std::to_string(100.0 * s.validation_gain_halves.first) + " / " + std::to_string(100.0 * s.validation_gain_halves.second) + " %)" +
        (clearly ? ", clearly better" : ", not clearly better") + " (paired 5-min blocks)");
  };

  for (int step = 0; step < o.max_effects; ++step) {
    const std::vector<double> pred = corrected(c, terms, level);
    std::vector<double> r(n);
    for (std::size_t i = 0; i < n; ++i) r[i] = c.measured[i] - pred[i];
    std::vector<FamilyScore> ranking;
    for (const auto& f : fams) {
      ranking.push_back(score_family(f, c, terms, level, r, pred, o, rng));
      const auto& s = ranking.back();
      std::ostringstream os;
      os << "step " << step + 1 << ": " << f;
      if (!s.available) os << " (" << s.note << ")";
      else os << ": explained variance " << s.explained_variance << ", p " << s.p_value << (s.significant ? " *" : "");
      log(os.str());
    }
    std::stable_sort(ranking.begin(), ranking.end(), [](const FamilyScore& a, const FamilyScore& b) {
      if (a.available != b.available) return a.available;
      return a.explained_variance > b.explained_variance;
    });
    const Val now = validate(terms);
    // Every significant family is validated: competing explanations are compared on data they were not fitted on.
    // A gain's form is chosen after the base has been refitted without it (below) where the base is refitted: the
    // first base absorbed part of the effect, and what it left looks curved (on the temperature-gain stage with the
    // earlier Preisach fit the quadratic won here and at each refit, and ended at 6.4 nm against the truth; chosen
    // after the refits the linear form stays, 4.0 nm).
    const bool form_after_refits = o.refit_base && std::max(o.backfit_iterations, o.gain_backfit_iterations) > 0;
    for (auto& s : ranking)
      if (s.available && s.significant) validate_family(s, terms, now, !form_after_refits);
    // Eligible: enough validation gain and, where the validation part has holds, no worse inside them.
    FamilyScore* best_phys = nullptr;
    FamilyScore* best_op = nullptr;
    for (auto& s : ranking) {
      if (!s.available || !s.significant) continue;
      const double need = extrapolates_in_time(s.family) ? o.time_trend_min_validation_gain : o.min_validation_gain;
      if (s.validation_gain < need) {
        s.verdict = "validation gain below " + std::to_string(100.0 * need).substr(0, 4) + " %";
      } else if (n_val_hold && s.hold_validation_gain < -o.hold_tolerance) {
        s.verdict = "worsens the validation error inside holds";
      } else if (std::min(s.validation_gain_halves.first, s.validation_gain_halves.second) < -o.half_tolerance &&
                 (extrapolates_in_time(s.family) || s.half_clearly_worse)) {
        // Slow structure the base misses (creep modes longer than the fit part, a slow thermal wander) lets a
        // trend or slow term fitted on the fit part win just after it and lose further on: a real effect keeps
        // helping in both halves of the validation part. Except for lines in time, which extrapolate, a half counts
        // only when clearly worse (half_clearly_worse): on the 200-bin Preisach walk a 1.5 %/µm other-axis gain
        // (p 3e-67, +7.0 % in the second half) lost 0.3 % in the first, within its noise, and was refused (TEST
        // stayed at 50 nm against the truth); on the Preisach creep protocol a time_drift lost a half by as little
        // and is refused as before.
        s.verdict = "does not generalise in time: worsens one half of the validation part";
      }
    }
    // A gain on a signal against the additive term on the same signal: where the base output varies little
    // (holds, a compensated axis parked near one set point) the two fit the same residual, and the gain's
    // extrapolation to other positions is a guess. It is kept only with a clear margin over the additive one.
    for (auto& s : ranking) {
      if (!s.available || !s.significant || !s.verdict.empty() || !is_gain_family(s.family)) continue;
      const std::string additive = additive_counterpart(s.family);
      const auto sig = s.best.labels.find("signal");
      for (const auto& a : ranking) {
        if (a.family != additive || !a.available || !a.significant || !a.verdict.empty()) continue;
        const auto asig = a.best.labels.find("signal");
        if (additive != "time_drift" &&
            (sig == s.best.labels.end() || asig == a.best.labels.end() || sig->second != asig->second))
          continue;
        const double need = o.gain_margin * a.validation_gain + o.min_validation_gain;
        if (s.validation_gain < need) {
          std::ostringstream why;
          why.precision(3);
          why << "a gain that did not beat the additive " << additive << " (" << 100 * a.validation_gain
              << " %) by the margin (needs ≥ " << 100 * need << " %)";
          s.verdict = why.str();
        }
      }
    }
    for (auto& s : ranking) {
      if (!s.available || !s.significant || !s.verdict.empty()) continue;
      FamilyScore*& slot = is_operating_point_family(s.family) ? best_op : best_phys;
      if (!slot || s.validation_gain > slot->validation_gain) slot = &s;
    }
    FamilyScore* winner = best_phys;
    if (best_op && (!best_phys || best_op->validation_gain >= o.operating_point_margin * best_phys->validation_gain +
                                                                   o.min_validation_gain))
      winner = best_op;
    if (!winner) {
      res.final_ranking = ranking;
      break;
    }
    std::vector<FamilyScore> competitors;
    for (auto& s : ranking) {
      if (&s == winner || !s.available || !s.significant || !s.verdict.empty()) continue;
      std::ostringstream why;
      why.precision(3);
      if (is_operating_point_family(s.family) && !is_operating_point_family(winner->family) &&
          s.validation_gain >= winner->validation_gain)
        why << "depends on the operating point and did not beat " << winner->family << " (" << 100 * winner->validation_gain
            << " %) by the margin (needs ≥ " << 100 * (o.operating_point_margin * winner->validation_gain + o.min_validation_gain)
            << " %)";
      else
        why << "validates worse than " << winner->family << ": " << 100 * s.validation_gain << " % vs "
            << 100 * winner->validation_gain << " %";
      s.verdict = why.str();
      competitors.push_back(s);
    }
    winner->verdict = "kept";
    effect_first.push_back(terms.size());
    for (const auto& t : winner->best.terms) terms.push_back(t);
    fit_terms(c, terms, level, 0, n);
    // A gain is fitted on the base's residual, and each refit of the base on data with the gain taken out gives
    // back only part of what the base had absorbed (on the Preisach stage ~30 % is kept at each round: plain
    // backfitting reached 97 % of a 4 %/°C gain after five refits). The size of the effect fitted after a refit
    // against the size taken out before it is close to a line, F(a) ≈ F(0) + ρ·a, whose fixed point is the joint
    // fit of base and gain: each refit after the first takes out that fixed point (secant on the last two rounds;
    // ρ outside (0, 0.9) or a jump beyond 2× the fitted size falls back to the plain step).
    const bool gain_effect = is_gain_family(winner->family);
    int rounds = gain_effect ? std::max(o.backfit_iterations, o.gain_backfit_iterations) : o.backfit_iterations;
    bool plain_step = false;  // the next refit takes the effect out once (a new form: the secant's points are another's)
    bool extended = false;
    double point_a = 0.0, point_f = 0.0, removed_last = 0.0;  // the secant's previous point, the size last taken out
    for (int it = 0; o.refit_base && it < rounds; ++it) {
      const std::vector<double> p = corrected(c, terms, level);
      std::vector<double> part;  // the new effect's part of the correction on TRAIN
      double kappa = 1.0;        // that part is taken out κ times
      if (gain_effect) {
        const std::vector<EffectTerm> others(terms.begin(), terms.begin() + static_cast<long>(effect_first.back()));
        const std::vector<double> p_o = corrected(c, others, level);
        part.resize(n);
        double ss = 0.0;
        for (std::size_t i = 0; i < n; ++i) part[i] = p[i] - p_o[i], ss += part[i] * part[i];
        const double fitted = std::sqrt(ss / static_cast<double>(n));
        double target = fitted;
        if (it > 0 && !plain_step && std::fabs(removed_last - point_a) > 1e-9 * (1.0 + fitted)) {
          const double slope = (fitted - point_f) / (removed_last - point_a);
          if (slope > 0.0 && slope < 0.9) target = (fitted - slope * removed_last) / (1.0 - slope);
        }
        if (it == 0) point_a = 0.0, point_f = fitted;
        else point_a = removed_last, point_f = fitted;
        kappa = fitted > 0.0 ? std::clamp(target / fitted, 0.5, 2.0) : 1.0;
        removed_last = kappa * fitted;
        std::ostringstream os;
        os << "  backfit " << it + 1 << ": " << winner->family << " part " << fitted << " nm RMS, taken out × " << kappa;
        log(os.str());
      }
      io::Dataset adj = train;
      auto& pos = adj.axis(o.axis).position_nm;
      for (std::size_t i = 0; i < n; ++i) pos[i] = c.measured[i] - (p[i] - c.x_base[i]) - (kappa - 1.0) * (part.empty() ? 0.0 : part[i]);
      models::ModelPtr nb = o.refit_base(adj.slice(0, n_fit), adj.slice(n_fit, n));
      if (!nb) throw std::runtime_error("refit_base returned no model");
      {
        models::ModelPtr runner = nb->clone();
        c.x_base = run_model(*runner, adj, o.axis, o.mode);
      }
      cur_base = std::move(nb);
      fit_terms(c, terms, level, 0, n);
      log("  backfit " + std::to_string(it + 1) + ": base refitted without the effect terms' part");
      // The first base absorbed the part of the effect its own regressors could express (a slow gain change
      // projects onto long creep modes), which shifts the residual's apparent lag and shape. On the refitted
      // base's residual the effect's variant (lag, low-pass, form) is chosen again.
      if (winner->variants > 1 || is_gain_family(winner->family)) {
        const std::size_t first = effect_first.back();
        std::vector<EffectTerm> others(terms.begin(), terms.begin() + static_cast<long>(first));
        Level off_o;
        if (!others.empty() || !c.transient.empty()) fit_terms(c, others, off_o, 0, n);
        const std::vector<double> p_o = corrected(c, others, off_o);
        std::vector<double> r_o(n);
        for (std::size_t i = 0; i < n; ++i) r_o[i] = c.measured[i] - p_o[i];
        ResidualOptions o_again = o;
        o_again.permutations = 0;  // the family is already accepted: only its variant is chosen again
        FamilyScore again = score_family(winner->family, c, others, off_o, r_o, p_o, o_again, rng);
        if (!again.available) continue;
        const bool last = it + 1 == rounds;
        validate_family(again, others, validate(others), last);
        plain_step = false;
        if (again.best.parameters != winner->best.parameters || again.best.labels != winner->best.labels) {
          log("  " + winner->family + " chosen again on the refitted base's residual");
          // A gain's form chosen at the last refit that is not the one the base was refitted without: one refit
          // more with it taken out (on the other-axis gain stage with seed 23 and the earlier Preisach fit the
          // voltage form won there, and without that refit ended 1.5 nm worse against the truth than with the form
          // chosen at every refit).
          const EffectTerm& was = terms[first];
          const EffectTerm& now_t = again.best.terms[0];
          if (last && form_after_refits && is_gain_family(winner->family) && !extended &&
              (was.type != now_t.type || was.scales != now_t.scales)) {
            ++rounds;
            plain_step = extended = true;
            log("  the gain's form changed at the last refit: one refit more");
          }
          winner->best = again.best;
          terms.resize(first);
          for (const auto& t : again.best.terms) terms.push_back(t);
          fit_terms(c, terms, level, 0, n);
        }
      }
    }

    FoundEffect e;
    e.family = winner->family;
    e.parameters = winner->best.parameters;
    e.labels = winner->best.labels;
    e.explained_variance = winner->explained_variance;
    e.p_value = winner->p_value;
    e.validation_gain = winner->validation_gain;
    e.ranking = ranking;
    e.competitors = competitors;
    e.hold_validation_gain = winner->hold_validation_gain;
    models::AugmentedModel m(cur_base->clone(), terms, level.offset_nm, fs);
    const std::vector<double> pt = run_test(m, level);
    e.test_after = error_stats(pt, meas_test, res.test_mask);
    e.test_prediction = pt;
    if (!truth_test.empty()) e.test_after_truth = error_stats(pt, truth_test, res.test_mask);
    log("added " + e.family + ": TEST MAE " + std::to_string(e.test_after.mae_nm) + " nm" +
        (truth_test.empty() ? "" : " (against the truth " + std::to_string(e.test_after_truth.mae_nm) + " nm)"));
    res.effects.push_back(std::move(e));
    if (step + 1 == o.max_effects) res.final_ranking = ranking;
  }

  // Parameters from the final joint fit.
  for (std::size_t q = 0; q < res.effects.size(); ++q) {
    const std::size_t first = effect_first[q];
    const std::size_t last = q + 1 < effect_first.size() ? effect_first[q + 1] : terms.size();
    describe(terms, first, last - first, res.effects[q]);
  }
  auto model = std::make_unique<models::AugmentedModel>(cur_base->clone(), terms, level.offset_nm, fs);
  res.test_pred_after = run_test(*model, level);
  res.after_test = error_stats(res.test_pred_after, meas_test, res.test_mask);
  if (!truth_test.empty()) res.after_test_truth = error_stats(res.test_pred_after, truth_test, res.test_mask);
  {
    const std::vector<double> p = corrected(c, terms, level);
    std::vector<double> r(n);
    for (std::size_t i = 0; i < n; ++i) r[i] = c.measured[i] - p[i];
    res.after_validation.mae_nm = mae_of(r, n_fit, n);
  }
  {
    std::vector<double> r(test.size());
    for (std::size_t i = 0; i < r.size(); ++i) r[i] = meas_test[i] - res.test_pred_after[i];
    res.remainder = assess_remainder(r, res.test_pred_after, test, o.axis, res.test_mask, o.alpha);
    std::ostringstream os;
    if (res.remainder.explained)
      os << "what is left is at the noise floor (σ " << res.remainder.noise_sigma_nm << " nm estimated from the data)";
    else
      os << "not explained: " << res.remainder.structure_nm << " nm of slow structure above the noise floor (σ "
         << res.remainder.noise_sigma_nm << " nm), top correlate " << res.remainder.correlates.front().first;
    log(os.str());
  }
  res.model = std::move(model);
  return res;
}

}  // namespace piezo::analysis
