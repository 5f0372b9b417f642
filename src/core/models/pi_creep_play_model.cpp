#include "piezo_compensation/models/pi_creep_play_model.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/features/play_operator.h"
#include "piezo_compensation/models/creep_models.h"
#include "piezo_compensation/models/yaml_fields.h"

namespace piezo::models {

namespace {

[[noreturn]] void play_model_error(const std::string& what) {
  throw std::runtime_error("pi_creep_play model: " + what);
}

}  // namespace

PiCreepPlayModel::PiCreepPlayModel(std::vector<double> thresholds_v, std::vector<double> weights,
                                   std::vector<double> taus_s, std::vector<double> gains, double bias_nm,
                                   double sample_rate_hz, PlayBends bends)
    : r_(std::move(thresholds_v)),
      w_(std::move(weights)),
      taus_(std::move(taus_s)),
      g_(std::move(gains)),
      b_(bias_nm),
      rate_hz_(sample_rate_hz),
      bends_(std::move(bends)) {
  const std::size_t n = r_.size(), J = taus_.size();
  if (n == 0) play_model_error("no play operators");
  if (n > static_cast<std::size_t>(kMaxPlayOperators))
    play_model_error(std::to_string(n) + " play operators (at most " + std::to_string(kMaxPlayOperators) +
                     ")");
  if (J == 0 || J > static_cast<std::size_t>(kMaxCreepModes))
    play_model_error(std::to_string(J) + " time constants (expected 1 to " +
                     std::to_string(kMaxCreepModes) + ")");
  if (n * J > static_cast<std::size_t>(kMaxPieces))
    play_model_error(std::to_string(n * J) + " creep gains (at most " + std::to_string(kMaxPieces) + ")");
  if (w_.size() != n)
    play_model_error(std::to_string(w_.size()) + " weights for " + std::to_string(n) + " thresholds");
  if (g_.size() != n * J)
    play_model_error(std::to_string(g_.size()) + " creep gains for " + std::to_string(n) + " plays × " +
                     std::to_string(J) + " time constants");
  if (r_[0] != 0) play_model_error("the first threshold must be 0 (the linear term)");
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(r_[i]) || (i > 0 && !(r_[i] > r_[i - 1])))
      play_model_error("thresholds must be finite and increase");
  for (double t : taus_)
    if (!(t > 0) || !std::isfinite(t)) play_model_error("time constants must be finite and > 0");
  for (double w : w_)
    if (!(w >= 0) || !std::isfinite(w)) play_model_error("weights must be finite and >= 0 (monotone loops)");
  for (double g : g_)
    if (!(g >= 0) || !std::isfinite(g))
      play_model_error("creep gains must be finite and >= 0 (monotone loops)");
  if (!bends_.empty()) {
    const auto& B = bends_;
    if (B.lo_v.size() != n || B.hi_v.size() != n || B.convex_nm_per_v.size() != n ||
        B.concave_nm_per_v.size() != n)
      play_model_error("the bends need one range and one pair of weights per play");
    for (std::size_t i = 0; i < n; ++i) {
      if (!std::isfinite(B.lo_v[i]) || !std::isfinite(B.hi_v[i]) || !(B.hi_v[i] > B.lo_v[i]))
        play_model_error("each bend range needs finite lo_v < hi_v");
      if (!(B.convex_nm_per_v[i] >= 0) || !(B.concave_nm_per_v[i] >= 0) ||
          !std::isfinite(B.convex_nm_per_v[i]) || !std::isfinite(B.concave_nm_per_v[i]))
        play_model_error("bend weights must be finite and >= 0 (monotone loops)");
    }
  }
  if (!std::isfinite(b_)) play_model_error("non-finite bias");
  if (!(rate_hz_ > 0) || !std::isfinite(rate_hz_)) play_model_error("sample rate must be > 0");
  for (double t : taus_) a_.push_back(std::exp(-1.0 / (rate_hz_ * t)));
  c_.assign(n, 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    c_[i] = w_[i];
    for (std::size_t j = 0; j < J; ++j) {
      c_[i] += g_[i * J + j] * (1.0 - a_[j]);
      if (g_[i * J + j] * a_[j] != 0.0) live_.push_back(i * J + j);
    }
  }
  if (!(c_[0] > 0))
    play_model_error("the linear term's slope must be > 0, else the model cannot be inverted");
  meta.sample_rate_hz = rate_hz_;
  reset(0.0, 0.0);
}

void PiCreepPlayModel::update_held() {
  const std::size_t J = taus_.size();
  held_ = 0;
  for (std::size_t k : live_) held_ += g_[k] * a_[k % J] * l_[k];
}

void PiCreepPlayModel::reset(double voltage_v, double /*position_nm*/) {
  p_.assign(r_.size(), voltage_v);
  l_.assign(r_.size() * taus_.size(), voltage_v);
  update_held();
}

double PiCreepPlayModel::bend(std::size_t i, double q) const {
  const double lo = bends_.lo_v[i], hi = bends_.hi_v[i];
  return bends_.convex_nm_per_v[i] * play_bend_convex(q, lo, hi) +
         bends_.concave_nm_per_v[i] * play_bend_concave(q, lo, hi);
}

double PiCreepPlayModel::predict_v(double v) const {
  double y = b_ + held_;
  if (bends_.empty()) {
    for (std::size_t i = 0; i < r_.size(); ++i) y += c_[i] * features::play(v, r_[i], p_[i]);
  } else {
    for (std::size_t i = 0; i < r_.size(); ++i) {
      const double q = features::play(v, r_[i], p_[i]);
      y += c_[i] * q + bend(i, q);
    }
  }
  return y;
}

void PiCreepPlayModel::commit(const ModelInput& in, double /*position_nm*/) {
  const std::size_t J = taus_.size();
  for (std::size_t i = 0; i < r_.size(); ++i) {
    const double q = features::play(in.voltage_v, r_[i], p_[i]);
    p_[i] = q;
    for (std::size_t j = 0; j < J; ++j) l_[i * J + j] = a_[j] * l_[i * J + j] + (1.0 - a_[j]) * q;
  }
  update_held();
}

double PiCreepPlayModel::linear_state_nm(std::size_t k) const {
  const std::size_t at = live_.at(k);
  return g_[at] * a_[at % taus_.size()] * l_[at];
}

void PiCreepPlayModel::shift_linear_state(std::size_t k, double delta_nm) {
  const std::size_t at = live_.at(k);
  l_[at] += delta_nm / (g_[at] * a_[at % taus_.size()]);
  update_held();
}

double PiCreepPlayModel::inverse(double target) const {
  // predict_v is strictly increasing (slope ≥ c_0 > 0: the memory-free play follows V), smooth between the
  // kinks where a play starts or stops moving (p_i ± r_i) or a moving play crosses its bend range's ends,
  // affine beyond them: walk the kinks, then solve within the interval (linear: closed form; with bends:
  // bisection).
  std::vector<double> k;
  for (std::size_t i = 0; i < r_.size(); ++i) {
    k.push_back(p_[i] - r_[i]);
    if (r_[i] > 0) k.push_back(p_[i] + r_[i]);
    if (!bends_.empty())
      for (double e : {bends_.lo_v[i], bends_.hi_v[i]}) k.push_back(e - r_[i]), k.push_back(e + r_[i]);
  }
  std::sort(k.begin(), k.end());
  double x_prev = k.front(), f_prev = predict_v(x_prev);
  if (target <= f_prev) return x_prev + (target - f_prev) / (f_prev - predict_v(x_prev - 1.0));
  for (std::size_t n = 1; n < k.size(); ++n) {
    if (!(k[n] > x_prev)) continue;
    const double f = predict_v(k[n]);
    if (target <= f) {
      if (bends_.empty()) return x_prev + (target - f_prev) * (k[n] - x_prev) / (f - f_prev);
      double lo = x_prev, hi = k[n];
      for (int it = 0; it < 64; ++it) {
        const double mid = 0.5 * (lo + hi);
        if (predict_v(mid) < target)
          lo = mid;
        else
          hi = mid;
      }
      return 0.5 * (lo + hi);
    }
    x_prev = k[n];
    f_prev = f;
  }
  return x_prev + (target - f_prev) / (predict_v(x_prev + 1.0) - f_prev);
}

std::size_t PiCreepPlayModel::num_parameters() const {
  std::size_t n = 1;  // bias
  for (double w : w_) n += w != 0;
  for (double g : g_) n += g != 0;
  if (!bends_.empty())
    for (std::size_t i = 0; i < r_.size(); ++i)
      n += (bends_.convex_nm_per_v[i] != 0) + (bends_.concave_nm_per_v[i] != 0);
  return n;
}

YAML::Node PiCreepPlayModel::to_yaml() const {
  YAML::Node n;
  n["thresholds_v"] = yaml_list(r_);
  n["weights_nm_per_v"] = yaml_list(w_);
  n["bias_nm"] = b_;
  YAML::Node c;
  c["taus_s"] = yaml_list(taus_);
  c["gains_nm_per_v"] = yaml_list(g_);  // play by play: play i's gains at g[i·J .. i·J + J)
  n["creep"] = c;
  if (!bends_.empty()) {
    YAML::Node bn;
    bn["lo_v"] = yaml_list(bends_.lo_v);
    bn["hi_v"] = yaml_list(bends_.hi_v);
    bn["convex_nm_per_v"] = yaml_list(bends_.convex_nm_per_v);
    bn["concave_nm_per_v"] = yaml_list(bends_.concave_nm_per_v);
    n["bends"] = bn;
  }
  return n;
}

ModelPtr PiCreepPlayModel::load(const YAML::Node& node) {
  if (node["kind"] && yaml_string(node, "kind") != "pi_creep_play")
    throw std::runtime_error("model.kind: expected pi_creep_play");
  const double rate = yaml_number(node, "sample_rate_hz");
  const auto r = yaml_numbers(node, "thresholds_v");
  if (r.empty() || r.size() > static_cast<std::size_t>(kMaxPlayOperators))
    throw std::runtime_error("model.thresholds_v: expected 1.." + std::to_string(kMaxPlayOperators) +
                             " thresholds");
  const auto w = yaml_numbers(node, "weights_nm_per_v", static_cast<long>(r.size()));
  const double b = yaml_number(node, "bias_nm");
  const YAML::Node c = node["creep"];
  if (!c || !c.IsMap())
    throw std::runtime_error("model.creep: expected a mapping with taus_s and gains_nm_per_v");
  check_keys(c, {"taus_s", "gains_nm_per_v"}, "model.creep");
  const auto taus = yaml_numbers(c, "taus_s", -1, "model.creep");
  if (taus.size() > static_cast<std::size_t>(kMaxCreepModes))
    throw std::runtime_error("model.creep.taus_s: at most " + std::to_string(kMaxCreepModes) +
                             " time constants");
  const auto g = yaml_numbers(c, "gains_nm_per_v", static_cast<long>(r.size() * taus.size()), "model.creep");
  PlayBends bends;
  if (const YAML::Node bn = node["bends"]) {
    if (!bn.IsMap())
      throw std::runtime_error(
          "model.bends: expected a mapping with lo_v, hi_v, convex_nm_per_v, concave_nm_per_v");
    check_keys(bn, {"lo_v", "hi_v", "convex_nm_per_v", "concave_nm_per_v"}, "model.bends");
    const long np = static_cast<long>(r.size());
    bends.lo_v = yaml_numbers(bn, "lo_v", np, "model.bends");
    bends.hi_v = yaml_numbers(bn, "hi_v", np, "model.bends");
    bends.convex_nm_per_v = yaml_numbers(bn, "convex_nm_per_v", np, "model.bends");
    bends.concave_nm_per_v = yaml_numbers(bn, "concave_nm_per_v", np, "model.bends");
  }
  return std::make_unique<PiCreepPlayModel>(r, w, taus, g, b, rate, bends);
}

}  // namespace piezo::models
