#include "piezo_compensation/estimation/error_filter.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <iomanip>
#include <limits>
#include <numeric>
#include <sstream>
#include <stdexcept>

#include <Eigen/Eigenvalues>

#include "piezo_compensation/estimation/quantised_reading.h"

namespace piezo::estimation {
namespace {

double field(const YAML::Node& node, const char* key, const std::string& where, double lo, double hi) {
  const YAML::Node v = node[key];
  if (!v) throw std::invalid_argument(where + ": estimator." + key + " is missing");
  double d = 0.0;
  try {
    d = v.as<double>();
  } catch (const YAML::Exception&) {
    throw std::invalid_argument(where + ": estimator." + key + " is not a number");
  }
  if (!std::isfinite(d) || d < lo || d > hi) {
    std::ostringstream s;
    s << where << ": estimator." << key << " = " << d << " is outside [" << lo << ", " << hi << "]";
    throw std::invalid_argument(s.str());
  }
  return d;
}

// Nelder–Mead on a few log-parameters: small, derivative-free, enough for a smooth 3-parameter likelihood.
template <std::size_t N, class F>
std::array<double, N> nelder_mead(F f, std::array<double, N> x0, const std::array<double, N>& step,
                                  std::size_t max_eval) {
  using P = std::array<double, N>;
  std::array<P, N + 1> s;
  std::array<double, N + 1> v;
  s[0] = x0;
  for (std::size_t i = 0; i < N; ++i) {
    s[i + 1] = x0;
    s[i + 1][i] += step[i];
  }
  std::size_t evals = 0;
  for (std::size_t i = 0; i <= N; ++i) v[i] = f(s[i]), ++evals;
  auto lin = [](const P& a, const P& b, double t) {  // a + t (b − a)
    P r;
    for (std::size_t i = 0; i < N; ++i) r[i] = a[i] + t * (b[i] - a[i]);
    return r;
  };
  while (evals < max_eval) {
    std::array<std::size_t, N + 1> o;
    std::iota(o.begin(), o.end(), 0);
    std::sort(o.begin(), o.end(), [&](std::size_t a, std::size_t b) { return v[a] < v[b]; });
    if (std::abs(v[o[N]] - v[o[0]]) < 1e-9 * (1.0 + std::abs(v[o[0]]))) break;
    P c{};
    for (std::size_t k = 0; k < N; ++k)
      for (std::size_t i = 0; i < N; ++i) c[i] += s[o[k]][i] / N;
    const std::size_t w = o[N];
    const P xr = lin(c, s[w], -1.0);
    const double fr = f(xr);
    ++evals;
    if (fr < v[o[0]]) {
      const P xe = lin(c, s[w], -2.0);
      const double fe = f(xe);
      ++evals;
      if (fe < fr) s[w] = xe, v[w] = fe;
      else s[w] = xr, v[w] = fr;
    } else if (fr < v[o[N - 1]]) {
      s[w] = xr, v[w] = fr;
    } else {
      const P xc = lin(c, s[w], fr < v[w] ? -0.5 : 0.5);
      const double fc = f(xc);
      ++evals;
      if (fc < std::min(fr, v[w])) {
        s[w] = xc, v[w] = fc;
      } else {  // shrink towards the best
        for (std::size_t k = 1; k <= N; ++k) {
          s[o[k]] = lin(s[o[0]], s[o[k]], 0.5);
          v[o[k]] = f(s[o[k]]);
          ++evals;
        }
      }
    }
  }
  return s[static_cast<std::size_t>(std::min_element(v.begin(), v.end()) - v.begin())];
}

// The model's slow error, 1σ: RMS of 30-s block means of reading − model, less the reading noise they keep.
double slow_error_sigma(const std::vector<double>& p, const std::vector<double>& y, double dt_s, double sigma) {
  const std::size_t block = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(30.0 / dt_s)));
  double sum2 = 0.0;
  std::size_t blocks = 0;
  for (std::size_t i0 = 0; i0 + block <= p.size(); i0 += block) {
    double s = 0.0;
    std::size_t n = 0;
    for (std::size_t i = i0; i < i0 + block; ++i)
      if (std::isfinite(y[i])) s += y[i] - p[i], ++n;
    if (n < block / 2) continue;
    const double m = s / n;
    sum2 += m * m - sigma * sigma / n;
    ++blocks;
  }
  return blocks ? std::sqrt(std::max(0.0, sum2 / blocks)) : 0.0;
}

// A model-only block written by an identification under the quantised reading model starts with this; the
// method then says why the model is not identifiable on the data.
constexpr const char* kNotIdentifiable = "model-only: the quantised reading model is not identifiable";
constexpr std::size_t kMinLevelChanges = 10;

// Level changes between consecutive valid readings: the crossings and flicker that pin a quantised reading model.
std::size_t level_changes(const std::vector<double>& y) {
  std::size_t n = 0;
  double last = std::numeric_limits<double>::quiet_NaN();
  for (double v : y) {
    if (!std::isfinite(v)) continue;
    n += std::isfinite(last) && v != last;
    last = v;
  }
  return n;
}

// The forecast calibration's three lists: all or none, equal lengths, horizons rising, scales positive.
void read_forecast(const YAML::Node& node, const std::string& where, NoiseModel& m) {
  const char* keys[] = {"forecast_horizons_s", "forecast_sigma_scale_hold", "forecast_sigma_scale_move"};
  std::vector<double>* to[] = {&m.forecast_horizons_s, &m.forecast_sigma_scale_hold, &m.forecast_sigma_scale_move};
  const int present = !!node[keys[0]] + !!node[keys[1]] + !!node[keys[2]];
  if (present == 0) return;
  if (present != 3)
    throw std::invalid_argument(where + ": estimator: forecast_horizons_s, forecast_sigma_scale_hold and "
                                "forecast_sigma_scale_move go together");
  for (int k = 0; k < 3; ++k) {
    try {
      *to[k] = node[keys[k]].as<std::vector<double>>();
    } catch (const YAML::Exception&) {
      throw std::invalid_argument(where + ": estimator." + keys[k] + " is not a list of numbers");
    }
    for (std::size_t i = 0; i < to[k]->size(); ++i) {
      const double v = (*to[k])[i];
      if (!std::isfinite(v) || !(v > 0.0) || (k == 0 && i > 0 && !(v > (*to[k])[i - 1])))
        throw std::invalid_argument(where + ": estimator." + keys[k] + "[" + std::to_string(i) + "] = " +
                                    std::to_string(v) + (k == 0 ? " is not a rising positive time [s]" : " is not > 0"));
    }
    if (to[k]->size() != m.forecast_horizons_s.size())
      throw std::invalid_argument(where + ": estimator." + keys[k] + " has " + std::to_string(to[k]->size()) +
                                  " entries, forecast_horizons_s " + std::to_string(m.forecast_horizons_s.size()));
  }
}

}  // namespace

// √(r² − q²/12): the noise before the quantiser for a reading σ that includes the step's rounding; 0 when the
// rounding is all of it.
double noise_before_quantiser(double reading_sigma_nm, double step_nm) {
  return std::sqrt(std::max(0.0, reading_sigma_nm * reading_sigma_nm - step_nm * step_nm / 12.0));
}

// The σ a noise model without one (an old file, or built in code) runs with.
double effective_noise_sigma(const NoiseModel& m) {
  if (m.noise_sigma_nm > 0.0) return m.noise_sigma_nm;
  const double s = noise_before_quantiser(m.reading_sigma_nm, m.step_nm);
  return s > 0.0 ? s : m.reading_sigma_nm;
}

namespace {

// The block of an axis whose readings cannot identify the quantised reading model: model-only, σ the model's slow
// error, the reading σ the data's (at least the step's rounding), and the method saying why.
NoiseModel model_only(const std::vector<double>& p, const std::vector<double>& y, const IdentifyOptions& o,
                      std::size_t readings, std::size_t changes) {
  NoiseModel m;
  m.fuse = false;
  m.step_nm = o.step_nm;
  m.samples = readings;
  m.fast_tau_s = o.fast_tau_grid_s.empty() ? m.fast_tau_s : o.fast_tau_grid_s.front();
  m.model_sigma_nm = slow_error_sigma(p, y, o.dt_s, std::max(0.0, o.reading_sigma_nm));
  // one level only: the readings show no spread; the reading σ is then the step's rounding or the model's error
  m.reading_sigma_nm = std::max({o.reading_sigma_nm, o.step_nm / std::sqrt(12.0), m.model_sigma_nm, 1e-3});
  m.noise_sigma_nm = noise_before_quantiser(m.reading_sigma_nm, m.step_nm);
  if (!(m.noise_sigma_nm > 0.0)) m.noise_sigma_nm = m.step_nm > 0.0 ? 0.1 * m.step_nm : m.reading_sigma_nm;
  m.initial_sigma_nm = std::sqrt(m.reading_sigma_nm * m.reading_sigma_nm + 4.0 * m.model_sigma_nm * m.model_sigma_nm);
  std::ostringstream s;
  s << std::setprecision(4) << kNotIdentifiable << ": the encoder changed level " << changes << " times in "
    << readings << " readings";
  if (o.step_nm > 0.0) s << " (" << o.step_nm << " nm steps)";
  s << "; at least " << kMinLevelChanges << " crossings or flickers are needed to pin the model's error within a step";
  m.method = s.str();
  return m;
}

}  // namespace

YAML::Node NoiseModel::to_yaml() const {
  YAML::Node n(YAML::NodeType::Map);
  n["fuse"] = fuse;
  n["reading_sigma_nm"] = reading_sigma_nm;
  n["step_nm"] = step_nm;
  n["noise_sigma_nm"] = effective_noise_sigma(*this);
  n["q_rest_nm2_per_s"] = q_rest_nm2_per_s;
  n["q_motion_nm"] = q_motion_nm;
  n["q_fast_nm"] = q_fast_nm;
  n["q_drift_nm2_per_s3"] = q_drift_nm2_per_s3;
  n["fast_tau_s"] = fast_tau_s;
  n["initial_sigma_nm"] = initial_sigma_nm;
  n["model_sigma_nm"] = model_sigma_nm;
  n["adapt_window_s"] = adapt_window_s;
  n["adapt_k"] = adapt_k;
  n["gate_s"] = gate_s;
  if (!forecast_horizons_s.empty()) {
    n["forecast_horizons_s"] = forecast_horizons_s;
    n["forecast_sigma_scale_hold"] = forecast_sigma_scale_hold;
    n["forecast_sigma_scale_move"] = forecast_sigma_scale_move;
  }
  n["samples"] = samples;
  n["log_likelihood_per_reading"] = log_likelihood;
  n["method"] = method;
  return n;
}

NoiseModel NoiseModel::from_yaml(const YAML::Node& node, const std::string& where) {
  if (!node || !node.IsMap()) throw std::invalid_argument(where + ": estimator: expected a mapping");
  NoiseModel m;
  const double inf = std::numeric_limits<double>::max();
  try {
    m.fuse = node["fuse"] ? node["fuse"].as<bool>() : true;
  } catch (const YAML::Exception&) {
    throw std::invalid_argument(where + ": estimator.fuse is not true/false");
  }
  m.reading_sigma_nm = field(node, "reading_sigma_nm", where, 1e-6, inf);
  m.step_nm = field(node, "step_nm", where, 0.0, inf);
  if (node["noise_sigma_nm"]) {
    m.noise_sigma_nm = field(node, "noise_sigma_nm", where, 1e-6, inf);
  } else {  // a file from before the quantised reading model: its reading σ included the rounding
    m.noise_sigma_nm = effective_noise_sigma(m);
  }
  m.q_rest_nm2_per_s = field(node, "q_rest_nm2_per_s", where, 0.0, inf);
  m.q_motion_nm = field(node, "q_motion_nm", where, 0.0, inf);
  m.q_fast_nm = field(node, "q_fast_nm", where, 0.0, inf);
  if (node["q_drift_nm2_per_s3"]) m.q_drift_nm2_per_s3 = field(node, "q_drift_nm2_per_s3", where, 0.0, inf);
  m.fast_tau_s = field(node, "fast_tau_s", where, 1e-6, inf);
  m.initial_sigma_nm = field(node, "initial_sigma_nm", where, 0.0, inf);
  m.model_sigma_nm = field(node, "model_sigma_nm", where, 0.0, inf);
  if (node["adapt_window_s"]) m.adapt_window_s = field(node, "adapt_window_s", where, 1e-3, 86400.0);
  if (node["adapt_k"]) m.adapt_k = field(node, "adapt_k", where, 0.0, 1e3);
  if (node["gate_s"]) m.gate_s = field(node, "gate_s", where, 1.0, 1e3);
  read_forecast(node, where, m);
  if (node["samples"]) m.samples = node["samples"].as<std::size_t>(0);
  if (node["log_likelihood_per_reading"]) m.log_likelihood = node["log_likelihood_per_reading"].as<double>(0.0);
  if (node["method"]) m.method = node["method"].as<std::string>("");
  return m;
}

std::string NoiseModel::describe() const {
  std::ostringstream s;
  s << std::setprecision(3);
  if (!fuse && method.rfind(kNotIdentifiable, 0) == 0) {
    s << method << "; model error 1σ " << model_sigma_nm << " nm";
    return s.str();
  }
  if (!fuse) {
    s << "model-only: encoder step " << step_nm << " nm against reading noise σ " << reading_sigma_nm
      << " nm; model error 1σ " << model_sigma_nm << " nm (identified before the quantised reading model: "
      << "re-identify with piezo track --identify-on to fuse)";
    return s.str();
  }
  s << "fused: noise σ " << noise_sigma_nm << " nm before a " << step_nm << " nm step, slow error " << q_rest_nm2_per_s
    << " nm²/s at rest + " << q_motion_nm << " nm²/nm moved, fast error " << q_fast_nm << " nm²/nm settling in "
    << fast_tau_s << " s, ramp " << q_drift_nm2_per_s3 << " nm²/s³, cold start 1σ " << initial_sigma_nm << " nm";
  return s.str();
}

ErrorFilter::ErrorFilter(const NoiseModel& model, double dt_s) : model_(model), dt_s_(dt_s) {
  if (!(dt_s > 0.0) || !std::isfinite(dt_s)) throw std::invalid_argument("ErrorFilter: dt_s must be > 0");
  if (!(model.reading_sigma_nm > 0.0)) throw std::invalid_argument("ErrorFilter: reading_sigma_nm must be > 0");
  model_.noise_sigma_nm = effective_noise_sigma(model);  // built in code without it: as an old file loads
  phi_ = std::exp(-dt_s / std::max(model.fast_tau_s, 1e-9));
  sigma_ = model_.noise_sigma_nm;
  const double scales[] = {1.0, 6.0, 30.0};
  for (std::size_t w = 0; w < windows_.size(); ++w) {
    windows_[w].n = std::max<std::size_t>(10, static_cast<std::size_t>(std::lround(scales[w] * model.adapt_window_s / dt_s)));
    windows_[w].alpha = 1.0 / static_cast<double>(windows_[w].n);
  }
  reset();
}

void ErrorFilter::reset() { reset(0.0, model_.initial_sigma_nm); }

void ErrorFilter::reset(double slow_error_nm, double slow_sigma_nm) {
  if (!std::isfinite(slow_error_nm)) throw std::invalid_argument("ErrorFilter: the start offset is not finite");
  if (slow_sigma_nm < 0) throw std::invalid_argument("ErrorFilter: the start offset's sigma is negative");
  if (!std::isfinite(slow_sigma_nm)) slow_sigma_nm = model_.initial_sigma_nm;
  x_.setZero();
  x_(0) = slow_error_nm;
  P_.setZero();
  P_(0, 0) = slow_sigma_nm * slow_sigma_nm;
  started_ = false;
  since_reading_ = 0;
  rejected_run_ = 0;
  taken_ = 0;
  have_level_ = false;
  for (auto& w : windows_) w.nu_bar = w.s_bar = 0.0, w.count = 0;
  rate_scale_ = 1.0;
  spread_ = SpreadBlock{};
}

double ErrorFilter::sigma_nm() const {
  if (!model_.fuse) return model_.model_sigma_nm;
  return std::sqrt(std::max(0.0, var_error(P_)));
}

// One sample ahead: the slow error walks and ramps, the fast one settles; the walks are driven by the model's motion
// |Δp|; the ramp's rate walks (an integrated random walk for the slow error).
void ErrorFilter::predict(double dp, Eigen::Vector3d& x, Eigen::Matrix3d& P) const {
  const double dt = dt_s_;
  Eigen::Matrix3d F;
  F << 1.0, 0.0, dt, 0.0, phi_, 0.0, 0.0, 0.0, 1.0;
  x = F * x;
  P = F * P * F.transpose();
  const double k = rate_scale_, qd = k * model_.q_drift_nm2_per_s3;
  P(0, 0) += k * (model_.q_rest_nm2_per_s * dt + model_.q_motion_nm * dp) + qd * dt * dt * dt / 3.0;
  P(0, 2) += qd * dt * dt / 2.0;
  P(2, 0) = P(0, 2);
  P(2, 2) += qd * dt;
  P(1, 1) += k * model_.q_fast_nm * dp;
}

bool ErrorFilter::zero_known() const {
  return model_.fuse && sigma_nm() <= std::max(model_.step_nm / 8.0, 0.5 * sigma_);
}

void ErrorFilter::hold(std::size_t samples) {
  if (!model_.fuse || samples == 0) return;
  // n samples at rest in closed form: F^n = [[1, 0, T], [0, φ^n, 0], [0, 0, 1]], the process noise summed over them
  const double n = static_cast<double>(samples), T = n * dt_s_, phin = std::pow(phi_, n),
               qd = rate_scale_ * model_.q_drift_nm2_per_s3;
  Eigen::Matrix3d F;
  F << 1.0, 0.0, T, 0.0, phin, 0.0, 0.0, 0.0, 1.0;
  x_ = F * x_;
  P_ = F * P_ * F.transpose();
  P_(0, 0) += rate_scale_ * model_.q_rest_nm2_per_s * T + qd * T * T * T / 3.0;
  P_(0, 2) += qd * T * T / 2.0;
  P_(2, 0) = P_(0, 2);
  P_(2, 2) += qd * T;
  since_reading_ += samples;
}

FilterState ErrorFilter::state() const {
  FilterState s;
  s.slow_nm = x_(0), s.fast_nm = x_(1), s.drift_nm_per_s = x_(2);
  s.covariance = {P_(0, 0), P_(0, 1), P_(0, 2), P_(1, 1), P_(1, 2), P_(2, 2)};
  s.last_predicted_nm = last_p_;
  s.rate_scale = rate_scale_;
  s.started = started_;
  return s;
}

void ErrorFilter::set_state(const FilterState& s) {
  Eigen::Matrix3d P;
  const auto& c = s.covariance;
  P << c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5];
  if (!std::isfinite(s.slow_nm) || !std::isfinite(s.fast_nm) || !std::isfinite(s.drift_nm_per_s) ||
      !std::isfinite(s.last_predicted_nm) || !P.allFinite())
    throw std::invalid_argument("ErrorFilter: the filter state holds a non-finite number");
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(P, Eigen::EigenvaluesOnly);
  if (eig.eigenvalues().minCoeff() < -1e-9 * std::max(1.0, P.diagonal().maxCoeff()))
    throw std::invalid_argument("ErrorFilter: the filter state's covariance is not positive semi-definite");
  x_ << s.slow_nm, s.fast_nm, s.drift_nm_per_s;
  P_ = P;
  last_p_ = s.last_predicted_nm;
  rate_scale_ = std::isfinite(s.rate_scale) ? std::clamp(s.rate_scale, 1.0, kMaxRateScale) : 1.0;
  started_ = s.started;
  rejected_run_ = 0;
  have_level_ = false;
}

void ErrorFilter::step(double predicted_nm, double measured_nm, bool valid, double reading_offset_nm) {
  if (!std::isfinite(reading_offset_nm)) throw std::invalid_argument("ErrorFilter::step: the reading offset is not finite");
  const double dp = started_ ? std::abs(predicted_nm - last_p_) : 0.0;
  last_p_ = predicted_nm;
  started_ = true;
  if (!model_.fuse) return;
  predict(dp, x_, P_);
  if (have_level_) predict(dp, level_x_, level_free_P_);
  if (!valid || !std::isfinite(measured_nm) || !track_level(measured_nm, predicted_nm) ||
      !take_reading(measured_nm - predicted_nm - reading_offset_nm, measured_nm)) {
    ++since_reading_;
    return;
  }
  if (level_n_ == 0) {
    level_first_var_ = var_error(P_);
    level_x_ = x_;
    level_P_ = level_free_P_ = P_;
  } else {
    floor_unchanged_level();
  }
  since_reading_ = 0;
}

bool ErrorFilter::track_level(double measured_nm, double predicted_nm) {
  if (!have_level_ || measured_nm != level_nm_) {
    have_level_ = true;
    level_nm_ = measured_nm;
    level_p_min_ = level_p_max_ = predicted_nm;
    level_n_ = 0;
    level_stale_ = false;
    return true;
  }
  level_p_min_ = std::min(level_p_min_, predicted_nm);
  level_p_max_ = std::max(level_p_max_, predicted_nm);
  const double grown = std::max(0.0, var_error(level_free_P_) - level_first_var_);
  const double reach = model_.step_nm + 3.0 * std::sqrt(grown) + 2.0 * sigma_;
  if (level_stale_ || (model_.step_nm > 0.0 && level_p_max_ - level_p_min_ > reach)) {
    if (!level_stale_) {  // the readings since the level was first read were stale too: undo them
      level_stale_ = true;
      x_ = level_x_;
      P_ = level_free_P_;
    }
    ++stale_;
    return false;
  }
  ++level_n_;
  return true;
}

// N readings of one level without a flicker: the truth stayed d = σ·Q⁻¹(1/N) inside the cell's edges.
void ErrorFilter::floor_unchanged_level() {
  if (!(model_.step_nm > 0.0)) return;
  const double n = static_cast<double>(level_n_ + 1);
  double d = 0.0;
  if (n >= 3.0) {  // Q(z) ≈ φ(z)/z: z² = 2(log N − log z − log √(2π)), two fixed-point steps
    double z = std::sqrt(2.0 * std::log(n));
    for (int k = 0; k < 2; ++k) z = std::sqrt(std::max(0.0, 2.0 * (std::log(n) - std::log(z) - 0.9189385332)));
    d = sigma_ * z;
  }
  const double w = std::max(0.0, model_.step_nm - 2.0 * d);
  // Narrower than the noise (dithered readings: c's 20 nm under 20 nm of noise), the posterior is Gaussian-shaped
  // and repeated levels average down as they should.
  if (w <= 2.0 * sigma_) return;
  const double floor = std::min(var_error(level_free_P_), w * w / 12.0);
  const double var_e = var_error(P_);
  if (var_e < floor) P_(0, 0) += floor - var_e;
}

// The reading of y − p = e_slow + e_fast + noise, quantised: the exact update of the scalar e = h·x, carried to both
// parts (x | e is Gaussian and linear in e, so the moment-matched e moves the state along P·hᵀ).
bool ErrorFilter::take_reading(double y_nm, double level_nm) {
  const Eigen::Vector3d ph = P_.col(0) + P_.col(1);  // P·hᵀ, h = (1, 1, 0)
  const double var_e = ph(0) + ph(1);
  ReadingUpdate u = quantised_update(error_nm(), var_e, y_nm, sigma_, model_.step_nm);
  if (u.cell_distance > model_.gate_s) {
    if (rejected_run_ == 0) rejected_level_nm_ = level_nm, rejected_level_changed_ = false;
    rejected_level_changed_ = rejected_level_changed_ || level_nm != rejected_level_nm_;
    ++rejected_run_;
    ++rejections_;
    // The level last taken, read again and again while the model moved away: a stuck encoder, not taken. A level
    // that moves, or one never taken (a cold start whose zero is cells off, a held axis: nothing else will tell
    // the filter; a slip to a new level that then stays): the model's error is larger than its covariance says, and
    // the slow error is widened to reach the reading.
    const bool stuck = !rejected_level_changed_ && taken_ > 0 && rejected_level_nm_ == taken_level_nm_;
    if (rejected_run_ < 3 || stuck) return false;
    const double reach = u.cell_distance * std::sqrt(var_e + sigma_ * sigma_);
    P_(0, 0) += reach * reach;
    ++widenings_;
    return take_reading(y_nm, level_nm);
  }
  rejected_run_ = 0;
  ++taken_;
  taken_level_nm_ = level_nm;
  if (var_e > 0.0) {
    x_ += ph * ((u.mean_nm - error_nm()) / var_e);
    P_ += (ph * ph.transpose()) * ((u.var_nm2 - var_e) / (var_e * var_e));
    P_ = 0.5 * (P_ + P_.transpose()).eval();
  }
  innovation_ = u.innovation_nm;
  loglik_ += u.log_p;
  ++updates_;
  check_consistency(u.explained_nm2);
  return true;
}

// The innovations' spread against the one the filter expects: for the moment-matched update E[ν²] = E[explained]
// exactly (the law of total variance on y* ~ N(m, s²) given its cell), on every axis. Per block of readings,
// z = (Σν² − Σe)/√(2Σe²); beyond adapt_k the rates are scaled up by the block's ratio Σν²/Σe (at most ×2 a block,
// at most kMaxRateScale in all), below −adapt_k down again (never below the identified rates). Coarse steps only.
void ErrorFilter::check_spread(double nu, double explained) {
  // Dithered readings (c: 20 nm steps under 20 nm of noise) measure the error at every sample and are checked by the
  // consistency test; the forecast's σ scales are calibrated on the filter as identified.
  if (!(model_.step_nm > 2.0 * sigma_)) return;
  spread_.nu2 += nu * nu;
  spread_.e += explained;
  spread_.e2 += explained * explained;
  if (++spread_.count < windows_[1].n) return;
  const SpreadBlock b = spread_;
  spread_ = SpreadBlock{};
  if (!(b.e2 > 0.0)) return;
  const double z = (b.nu2 - b.e) / std::sqrt(2.0 * b.e2);
  if (z > model_.adapt_k) {
    rate_scale_ = std::min(kMaxRateScale, rate_scale_ * std::min(2.0, b.nu2 / b.e));
    ++rate_scalings_;
  } else if (z < -model_.adapt_k && rate_scale_ > 1.0) {
    rate_scale_ = std::max(1.0, rate_scale_ / std::min(2.0, b.e / std::max(b.nu2, 1e-300)));
  }
}

void ErrorFilter::check_consistency(double s) {
  if (!(model_.adapt_k > 0.0)) return;
  check_spread(innovation_, s);
  for (auto& w : windows_) {
    w.nu_bar += w.alpha * (innovation_ - w.nu_bar);
    w.s_bar += w.alpha * (s - w.s_bar);
    if (++w.count < w.n) continue;
    // an exponential mean of white innovations of variance S has variance S·α/(2 − α)
    const double var_mean = w.s_bar * w.alpha / (2.0 - w.alpha);
    if (w.nu_bar * w.nu_bar <= model_.adapt_k * model_.adapt_k * var_mean) continue;
    P_(0, 0) += w.nu_bar * w.nu_bar;
    for (auto& v : windows_) v.nu_bar = 0.0, v.count = 0;  // the state will move: every window starts again
    ++adaptations_;
    return;
  }
}

FilterTrace run_filter(const NoiseModel& model, double dt_s, const std::vector<double>& predicted_nm,
                       const std::vector<double>& measured_nm) {
  if (predicted_nm.size() != measured_nm.size())
    throw std::invalid_argument("run_filter: predictions and readings differ in length");
  ErrorFilter f(model, dt_s);
  FilterTrace t;
  t.fused_nm.reserve(predicted_nm.size());
  t.sigma_nm.reserve(predicted_nm.size());
  for (std::size_t i = 0; i < predicted_nm.size(); ++i) {
    f.step(predicted_nm[i], measured_nm[i], std::isfinite(measured_nm[i]));
    t.fused_nm.push_back(f.fused_nm());
    t.sigma_nm.push_back(f.sigma_nm());
  }
  t.log_likelihood = f.log_likelihood();
  return t;
}

NoiseModel identify_noise_model(const std::vector<double>& predicted_nm, const std::vector<double>& measured_nm,
                                const IdentifyOptions& o) {
  if (predicted_nm.size() != measured_nm.size())
    throw std::invalid_argument("identify_noise_model: predictions and readings differ in length");
  if (!(o.dt_s > 0.0)) throw std::invalid_argument("identify_noise_model: dt_s must be > 0");
  std::size_t readings = 0;
  for (std::size_t i = 0; i < predicted_nm.size(); ++i) {
    if (!std::isfinite(predicted_nm[i]))
      throw std::invalid_argument("identify_noise_model: prediction " + std::to_string(i) + " is not finite");
    readings += std::isfinite(measured_nm[i]) ? 1 : 0;
  }
  if (readings < 200)
    throw std::invalid_argument("identify_noise_model: " + std::to_string(readings) + " readings (need ≥ 200)");
  // The noise σ before a quantiser and the error's rates show only in level changes (crossings during moves, flicker
  // in holds); without them the likelihood is flat in them, and the axis runs model-only.
  const std::size_t changes = level_changes(measured_nm);
  if (changes < kMinLevelChanges) return model_only(predicted_nm, measured_nm, o, readings, changes);
  if (!(o.reading_sigma_nm > 0.0)) throw std::invalid_argument("identify_noise_model: reading σ must be > 0");

  NoiseModel m;
  m.reading_sigma_nm = o.reading_sigma_nm;
  m.step_nm = o.step_nm;
  m.samples = readings;
  m.model_sigma_nm = slow_error_sigma(predicted_nm, measured_nm, o.dt_s, o.reading_sigma_nm);
  m.initial_sigma_nm = std::sqrt(o.reading_sigma_nm * o.reading_sigma_nm + 4.0 * m.model_sigma_nm * m.model_sigma_nm);
  // The σ before the quantiser starts from the noise floor's, less the rounding it includes; where rounding is all
  // of the floor (σ ≪ q: the readings of a hold rarely flicker) from a tenth of a step.
  double sigma0 = noise_before_quantiser(o.reading_sigma_nm, o.step_nm);
  if (o.step_nm > 0.0 && sigma0 < 0.05 * o.step_nm) sigma0 = 0.1 * o.step_nm;
  // Parameters are searched in log space, bounded so the filter stays defined; a rate at the lower bound (e^-25) is
  // one the data do not show: 0.
  auto unpack = [](const std::array<double, 5>& z, NoiseModel& t) {
    auto rate = [](double x) { return x <= -25.0 ? 0.0 : std::exp(std::min(x, 12.0)); };
    t.q_rest_nm2_per_s = rate(z[0]);
    t.q_motion_nm = rate(z[1]);
    t.q_fast_nm = rate(z[2]);
    t.noise_sigma_nm = std::exp(std::clamp(z[3], -7.0, 12.0));
    t.reading_sigma_nm = std::sqrt(t.noise_sigma_nm * t.noise_sigma_nm + t.step_nm * t.step_nm / 12.0);
    t.q_drift_nm2_per_s3 = z[4] <= -40.0 ? 0.0 : std::exp(std::min(z[4], 0.0));
  };
  NoiseModel best = m;
  double best_ll = -std::numeric_limits<double>::infinity();
  for (double tau : o.fast_tau_grid_s) {
    NoiseModel trial = m;
    trial.fast_tau_s = tau;
    // The rates are those of the model itself; the consistency test and the gate are guards against what the data
    // identified on did not show, so they stay out of the likelihood (with them in, the rates they cover shrink).
    trial.adapt_k = 0.0;
    trial.gate_s = 1e3;
    auto nll = [&](const std::array<double, 5>& z) {
      unpack(z, trial);
      ErrorFilter f(trial, o.dt_s);
      for (std::size_t i = 0; i < predicted_nm.size(); ++i)
        f.step(predicted_nm[i], measured_nm[i], std::isfinite(measured_nm[i]));
      return -f.log_likelihood() / static_cast<double>(readings);
    };
    const std::array<double, 5> z =
        nelder_mead<5>(nll, {std::log(0.01), std::log(0.01), std::log(0.1), std::log(sigma0), std::log(1e-6)},
                       {std::log(30.0), std::log(30.0), std::log(30.0), std::log(1.5), std::log(100.0)},
                       o.max_evaluations);
    const double ll = -nll(z);
    if (ll > best_ll) {
      best_ll = ll;
      unpack(z, trial);
      best = trial;
    }
  }
  best.log_likelihood = best_ll;
  best.adapt_k = m.adapt_k;
  best.gate_s = m.gate_s;
  // the cold start covers the reading's own spread as identified
  best.initial_sigma_nm = std::sqrt(best.reading_sigma_nm * best.reading_sigma_nm + 4.0 * m.model_sigma_nm * m.model_sigma_nm);
  std::ostringstream s;
  s << "maximum likelihood of the quantised readings on " << readings << " readings (σ before the quantiser and fast τ from {";
  for (std::size_t i = 0; i < o.fast_tau_grid_s.size(); ++i) s << (i ? ", " : "") << o.fast_tau_grid_s[i];
  s << "} s)";
  best.method = s.str();
  return best;
}

}  // namespace piezo::estimation
