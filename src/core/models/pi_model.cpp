#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/features/play_operator.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <stdexcept>

#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::models {

namespace {
using features::play;
}  // namespace

double OutputMap::operator()(double h) const {
  if (empty()) return h;
  const double mid = 0.5 * (lo_nm + hi_nm), half = 0.5 * (hi_nm - lo_nm);
  const double z = (h - mid) / half, zc = std::min(1.0, std::max(-1.0, z));
  const double inside = mid + half * zc + quadratic_nm * zc * zc + cubic_nm * zc * zc * zc;
  return inside + slope(h) * (h - (mid + half * zc));  // affine beyond the range
}

double OutputMap::slope(double h) const {
  if (empty()) return 1.0;
  const double mid = 0.5 * (lo_nm + hi_nm), half = 0.5 * (hi_nm - lo_nm);
  const double z = std::min(1.0, std::max(-1.0, (h - mid) / half));
  return 1.0 + (2.0 * quadratic_nm * z + 3.0 * cubic_nm * z * z) / half;
}

double OutputMap::min_slope() const {
  if (empty()) return 1.0;
  const double half = 0.5 * (hi_nm - lo_nm), mid = 0.5 * (lo_nm + hi_nm);
  double m = std::min(slope(lo_nm), slope(hi_nm));
  if (cubic_nm != 0) {  // the parabola S'(z) has its extremum at z = −a₂ / (3·a₃)
    const double z = -quadratic_nm / (3.0 * cubic_nm);
    if (z > -1.0 && z < 1.0) m = std::min(m, slope(mid + half * z));
  }
  return m;
}

void PiCreepModel::set_output_map(const OutputMap& map) {
  if (!map.empty()) {
    if (!std::isfinite(map.lo_nm) || !std::isfinite(map.hi_nm) || !(map.hi_nm > map.lo_nm))
      throw std::runtime_error("model.output_map.h_range_nm: expected two finite values, the first below the second");
    if (!std::isfinite(map.quadratic_nm) || !std::isfinite(map.cubic_nm))
      throw std::runtime_error("model.output_map: non-finite quadratic_nm or cubic_nm");
    if (!(map.min_slope() > 0))
      throw std::runtime_error("model.output_map: not increasing on h_range_nm (smallest slope " +
                               std::to_string(map.min_slope()) + "), so the model could not be inverted");
  }
  map_ = map;
}

PiCreepModel::PiCreepModel(std::vector<double> thresholds_v, std::vector<double> weights, double bias_nm,
                           CreepParams creep, double sample_rate_hz, std::vector<std::vector<double>> knots_v,
                           bool input_map)
    : r_(std::move(thresholds_v)), w_(std::move(weights)), knots_(std::move(knots_v)), input_map_(input_map),
      b_(bias_nm), creep_(std::move(creep)), rate_hz_(sample_rate_hz) {
  if (r_.empty()) throw std::runtime_error("PI model: no play operators");
  if (r_.size() > static_cast<std::size_t>(kMaxPlayOperators))
    throw std::runtime_error("PI model: " + std::to_string(r_.size()) + " play operators (at most " +
                             std::to_string(kMaxPlayOperators) + ")");
  if (preisach()) creep_kind_name(creep_.kind, true);  // throws for a creep law the preisach kinds do not have
  if (!knots_.empty() && knots_.size() != r_.size())
    throw std::runtime_error("preisach model: " + std::to_string(knots_.size()) + " knot lists for " +
                             std::to_string(r_.size()) + " thresholds");
  if (input_map_ && (knots_.empty() || knots_[0].empty() ||
                     std::any_of(knots_.begin() + 1, knots_.end(), [](const auto& k) { return !k.empty(); })))
    throw std::runtime_error("PI model: an input map has knots on the first play operator and on no other");
  std::size_t pieces = 0;
  for (std::size_t i = 0; i < r_.size(); ++i) {
    first_.push_back(pieces);
    const std::vector<double> none;
    const std::vector<double>& k = knots_.empty() ? none : knots_[i];
    if (k.size() > static_cast<std::size_t>(kMaxKnotsPerPlay))
      throw std::runtime_error("preisach model: " + std::to_string(k.size()) + " knots on one play operator (at most " +
                               std::to_string(kMaxKnotsPerPlay) + ")");
    for (std::size_t j = 0; j < k.size(); ++j)
      if (!std::isfinite(k[j]) || (j > 0 && !(k[j] > k[j - 1])))
        throw std::runtime_error("preisach model: the knots of each play operator must be finite and increase");
    pieces += features::play_piece_count(k.size());
  }
  if (pieces > static_cast<std::size_t>(kMaxPieces))
    throw std::runtime_error("preisach model: " + std::to_string(pieces) + " pieces (at most " +
                             std::to_string(kMaxPieces) + ")");
  if (pieces != w_.size())
    throw std::runtime_error("PI model: " + std::to_string(w_.size()) + " weights for " + std::to_string(pieces) +
                             (knots_.empty() ? " thresholds" : " pieces"));
  for (std::size_t i = 0; i < r_.size(); ++i) {
    if (!(r_[i] >= 0) || !std::isfinite(r_[i])) throw std::runtime_error("PI model: thresholds must be >= 0");
    if (i > 0 && !(r_[i] > r_[i - 1])) throw std::runtime_error("PI model: thresholds must increase");
  }
  for (double w : w_)
    if (!std::isfinite(w)) throw std::runtime_error("PI model: non-finite weight");
  if (!std::isfinite(b_)) throw std::runtime_error("PI model: non-finite bias");
  if (!(rate_hz_ > 0)) throw std::runtime_error("PI model: sample rate must be > 0");
  creep_.modes(taus_, gains_);
  step_s_ = 1.0 / rate_hz_;
  for (double t : taus_) poles_.push_back(std::exp(-1.0 / (rate_hz_ * t)));
  for (std::size_t j = 0; j < taus_.size(); ++j)
    if (gains_[j] * poles_[j] != 0.0) live_modes_.push_back(j);
  meta.sample_rate_hz = rate_hz_;
  reset(0.0, 0.0);
}

void PiCreepModel::set_step_s(double dt_s) {
  if (!(dt_s > 0) || !std::isfinite(dt_s))
    throw std::invalid_argument("model '" + kind() + "': a step must be a finite time > 0 s, got " + std::to_string(dt_s));
  if (std::abs(dt_s - step_s_) <= 1e-9 * step_s_) return;  // the same step: the poles stand (bit for bit)
  step_s_ = dt_s;
  for (std::size_t j = 0; j < taus_.size(); ++j) poles_[j] = std::exp(-dt_s / taus_[j]);
}

double PiCreepModel::hysteresis(double v, const std::vector<double>& p, std::vector<double>* p_next) const {
  double h = 0;
  for (std::size_t i = 0; i < r_.size(); ++i) {
    const double q = play(v, r_[i], p[i]);
    if (p_next) (*p_next)[i] = q;
    h += knots_.empty() ? w_[i] * q : features::play_pieces_dot(q, knots_[i].data(), knots_[i].size(), &w_[first_[i]]);
  }
  return h;
}

void PiCreepModel::reset(double voltage_v, double /*position_nm*/) {
  p_.assign(r_.size(), voltage_v);
  const double h = hysteresis(voltage_v, p_);
  l_.assign(taus_.size(), creep_.on_hysteresis ? h : voltage_v);
}

double PiCreepModel::predict_v(double v) const {
  const double h = hysteresis(v, p_);
  const double u = creep_.on_hysteresis ? h : v;
  double y = b_ + map_(h);
  for (std::size_t j = 0; j < taus_.size(); ++j) y += gains_[j] * (poles_[j] * l_[j] + (1 - poles_[j]) * u);
  return y;
}

void PiCreepModel::commit(const ModelInput& in, double) {
  const double v = in.voltage_v;
  const double h = hysteresis(v, p_, &p_);
  const double u = creep_.on_hysteresis ? h : v;
  for (std::size_t j = 0; j < taus_.size(); ++j) l_[j] = poles_[j] * l_[j] + (1 - poles_[j]) * u;
}

double PiCreepModel::linear_state_nm(std::size_t k) const {
  const std::size_t j = live_modes_.at(k);
  return gains_[j] * poles_[j] * l_[j];
}

void PiCreepModel::shift_linear_state(std::size_t k, double delta_nm) {
  const std::size_t j = live_modes_.at(k);
  l_[j] += delta_nm / (gains_[j] * poles_[j]);
}

double PiCreepModel::inverse(double target) const {
  const double v0 = inverse_piecewise(target);
  if (map_.empty()) return v0;
  // With an output map predict_v is still increasing in V but curved between kinks: bracket the piecewise guess,
  // then bisect (each step one predict_v; 60 halvings of the bracket reach the double's resolution).
  double lo = v0, hi = v0, step = 1.0;
  for (int i = 0; i < 64 && predict_v(lo) > target; ++i, step *= 2) lo = v0 - step;
  step = 1.0;
  for (int i = 0; i < 64 && predict_v(hi) < target; ++i, step *= 2) hi = v0 + step;
  for (int i = 0; i < 60 && hi - lo > 1e-9 * (1.0 + std::abs(v0)); ++i) {
    const double mid = 0.5 * (lo + hi);
    (predict_v(mid) < target ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

double PiCreepModel::inverse_piecewise(double target) const {
  // predict_v is piecewise linear with kinks at p_i ± r_i and, for the preisach kinds, where a play output that
  // moves crosses a knot (c + r above the state, c − r below it); walk the sorted kinks.
  std::vector<double> k;
  for (std::size_t i = 0; i < r_.size(); ++i) {
    k.push_back(p_[i] - r_[i]);
    if (r_[i] > 0) k.push_back(p_[i] + r_[i]);
    if (!knots_.empty())
      for (double c : knots_[i]) {
        if (c >= p_[i]) k.push_back(c + r_[i]);
        if (c <= p_[i]) k.push_back(c - r_[i]);
      }
  }
  std::sort(k.begin(), k.end());
  // Outside the kinks the prediction is affine: its slopes from one volt beyond them.
  const double f0 = predict_v(k.front()), f_last = predict_v(k.back());
  const double slope_lo = f0 - predict_v(k.front() - 1.0), slope_hi = predict_v(k.back() + 1.0) - f_last;
  if (target <= f0) return slope_lo > 0 ? k.front() + (target - f0) / slope_lo : k.front();
  double x_prev = k.front(), f_prev = f0;
  for (std::size_t n = 1; n < k.size(); ++n) {
    const double f = n + 1 == k.size() ? f_last : predict_v(k[n]);
    if (target <= f && f > f_prev) return x_prev + (target - f_prev) * (k[n] - x_prev) / (f - f_prev);
    if (target <= f) return 0.5 * (x_prev + k[n]);
    x_prev = k[n];
    f_prev = f;
  }
  return slope_hi > 0 ? x_prev + (target - f_prev) / slope_hi : x_prev;
}

std::size_t PiCreepModel::num_parameters() const {
  std::size_t n = w_.size() + 1;
  if (creep_.kind == CreepKind::kLti) n += 2 * creep_.taus_s.size();
  if (creep_.kind == CreepKind::kLog || creep_.kind == CreepKind::kFractional) n += 2;
  if (creep_.kind == CreepKind::kProny) n += creep_.gains_nm_per_v.size();
  if (!map_.empty()) n += 2;
  return n;
}

YAML::Node PiCreepModel::to_yaml() const {
  YAML::Node n;
  n["thresholds_v"] = yaml_list(r_);
  n["weights_nm_per_v"] = yaml_list(w_);
  n["bias_nm"] = b_;
  if (input_map_) {
    YAML::Node im;
    im["knots_v"] = yaml_list(knots_[0]);
    n["input_map"] = im;
  } else if (preisach()) {
    // Flat, with a count per play operator: [[...], []] would read as a list of lists everywhere else.
    std::vector<double> counts, flat;
    for (const auto& k : knots_) {
      counts.push_back(static_cast<double>(k.size()));
      flat.insert(flat.end(), k.begin(), k.end());
    }
    YAML::Node pn;
    pn["knot_counts"] = yaml_list(counts);
    pn["knots_v"] = yaml_list(flat);
    n["preisach"] = pn;
  }
  if (!map_.empty()) {
    YAML::Node om;
    om["h_range_nm"] = yaml_list(std::vector<double>{map_.lo_nm, map_.hi_nm});
    om["quadratic_nm"] = map_.quadratic_nm;
    om["cubic_nm"] = map_.cubic_nm;
    n["output_map"] = om;
  }
  if (creep_.kind != CreepKind::kNone) {
    YAML::Node c;
    c["input"] = creep_.on_hysteresis ? "hysteresis" : "voltage";
    switch (creep_.kind) {
      case CreepKind::kLog:
        c["gamma_nm_per_v"] = creep_.gamma_nm_per_v;
        c["t1_s"] = creep_.t1_s;
        c["decades"] = creep_.decades;
        c["modes_per_decade"] = creep_.modes_per_decade;
        break;
      case CreepKind::kFractional:
        c["alpha"] = creep_.alpha;
        c["b_nm_per_v"] = creep_.b_nm_per_v;
        c["tau_min_s"] = creep_.tau_min_s;
        c["tau_max_s"] = creep_.tau_max_s;
        c["modes_per_decade"] = creep_.modes_per_decade;
        break;
      case CreepKind::kProny:
        c["tau_min_s"] = creep_.tau_min_s;
        c["tau_max_s"] = creep_.tau_max_s;
        c["modes_per_decade"] = creep_.modes_per_decade;
        c["mode_gains"] = yaml_list(creep_.gains_nm_per_v);  // per mode on the grid; nm/V, or nm/nm on H
        break;
      case CreepKind::kLti: {
        c["taus_s"] = yaml_list(creep_.taus_s);
        c["gains_nm_per_v"] = yaml_list(creep_.gains_nm_per_v);
        // The seed's spring–damper form, for reading: k_j = 1/g_j [V/nm], c_j = τ_j·k_j [V·s/nm].
        std::vector<double> k, cc;
        for (std::size_t j = 0; j < creep_.taus_s.size(); ++j) {
          k.push_back(creep_.gains_nm_per_v[j] != 0 ? 1.0 / creep_.gains_nm_per_v[j] : 0.0);
          cc.push_back(k.back() * creep_.taus_s[j]);
        }
        c["k0_v_per_nm"] = w_[0] != 0 ? 1.0 / w_[0] : 0.0;
        c["k_v_per_nm"] = yaml_list(k);
        c["c_v_s_per_nm"] = yaml_list(cc);
        break;
      }
      default: break;
    }
    n["creep"] = c;
  }
  return n;
}

namespace {
// The `creep:` block of a PI/Preisach model node (absent: no creep). Errors are named model.creep.<key>.
CreepParams read_creep_block(const YAML::Node& c) {
  CreepParams cp;
  if (!c) return cp;
  if (!c.IsMap()) throw std::runtime_error("model.creep: expected a mapping");
  try {
    if (c["input"]) {
      const std::string in = yaml_string(c, "input");
      if (in != "voltage" && in != "hysteresis") throw std::runtime_error("model.input: expected voltage or hysteresis");
      cp.on_hysteresis = in == "hysteresis";
    }
    if (c["gamma_nm_per_v"]) {
      cp.kind = CreepKind::kLog;
      cp.gamma_nm_per_v = yaml_number(c, "gamma_nm_per_v");
      cp.t1_s = yaml_number(c, "t1_s");
      cp.decades = yaml_int(c, "decades");
      cp.modes_per_decade = yaml_int(c, "modes_per_decade");
    } else if (c["alpha"]) {
      cp.kind = CreepKind::kFractional;
      cp.alpha = yaml_number(c, "alpha");
      cp.b_nm_per_v = yaml_number(c, "b_nm_per_v");
      cp.tau_min_s = yaml_number(c, "tau_min_s");
      cp.tau_max_s = yaml_number(c, "tau_max_s");
      cp.modes_per_decade = yaml_int(c, "modes_per_decade");
    } else if (c["mode_gains"]) {
      cp.kind = CreepKind::kProny;
      cp.tau_min_s = yaml_number(c, "tau_min_s");
      cp.tau_max_s = yaml_number(c, "tau_max_s");
      cp.modes_per_decade = yaml_int(c, "modes_per_decade");
      const auto grid = log_tau_grid(cp.tau_min_s, cp.tau_max_s, cp.modes_per_decade);
      if (grid.size() > static_cast<std::size_t>(kMaxCreepModes))
        throw std::runtime_error("model.creep: the prony grid has " + std::to_string(grid.size()) +
                                 " modes (at most " + std::to_string(kMaxCreepModes) + ")");
      cp.gains_nm_per_v = yaml_numbers(c, "mode_gains", static_cast<long>(grid.size()));
    } else if (c["taus_s"]) {
      cp.kind = CreepKind::kLti;
      cp.taus_s = yaml_numbers(c, "taus_s");
      cp.gains_nm_per_v = yaml_numbers(c, "gains_nm_per_v", static_cast<long>(cp.taus_s.size()));
    } else {
      throw std::runtime_error(
          "model.creep: expected gamma_nm_per_v (log), alpha (fractional), mode_gains (prony) or taus_s (lti)");
    }
    cp.check_sizes();
  } catch (const std::runtime_error& e) {
    std::string msg = e.what();
    if (msg.rfind("model.", 0) == 0) msg = "model.creep." + msg.substr(6);
    throw std::runtime_error(msg);
  }
  return cp;
}

}  // namespace

ModelPtr PiCreepModel::load(const YAML::Node& node) {
  const double rate = yaml_number(node, "sample_rate_hz");
  const auto r = yaml_numbers(node, "thresholds_v");
  if (r.size() > static_cast<std::size_t>(kMaxPlayOperators))
    throw std::runtime_error("model.thresholds_v: " + std::to_string(r.size()) + " play operators (at most " +
                             std::to_string(kMaxPlayOperators) + ")");
  bool preisach = false;
  const CreepKind expected =
      node["kind"] ? creep_kind_from_name(yaml_string(node, "kind"), &preisach) : CreepKind::kNone;
  const bool input_map = bool(node["input_map"]);
  if (input_map && (preisach || node["preisach"]))
    throw std::runtime_error("model.input_map: only the PI kinds have one (the preisach kinds cut every play)");
  if (node["kind"] && preisach != bool(node["preisach"]))
    throw std::runtime_error(std::string("model.preisach: kind ") + yaml_string(node, "kind") +
                             (preisach ? " needs" : " has no") + " a preisach mapping (knot_counts, knots_v)");
  std::vector<std::vector<double>> knots;
  std::size_t pieces = r.size();
  if (input_map) {
    const YAML::Node im = node["input_map"];
    if (!im.IsMap()) throw std::runtime_error("model.input_map: expected a mapping with knots_v");
    check_keys(im, {"knots_v"}, "model.input_map");
    const auto k = yaml_numbers(im, "knots_v", -1, "model.input_map");
    if (k.empty() || k.size() > static_cast<std::size_t>(kMaxKnotsPerPlay))
      throw std::runtime_error("model.input_map.knots_v: expected 1.." + std::to_string(kMaxKnotsPerPlay) + " knots");
    knots.assign(r.size(), {});
    if (!knots.empty()) knots[0] = k;
    pieces = r.size() + k.size();
  }
  if (node["preisach"]) {
    const YAML::Node pn = node["preisach"];
    if (!pn.IsMap()) throw std::runtime_error("model.preisach: expected a mapping");
    const auto counts = yaml_numbers(pn, "knot_counts", static_cast<long>(r.size()), "model.preisach");
    std::size_t total = 0;
    for (double c : counts) {
      if (!(c >= 0 && c <= kMaxKnotsPerPlay && c == std::floor(c)))
        throw std::runtime_error("model.preisach.knot_counts: expected whole numbers in 0.." +
                                 std::to_string(kMaxKnotsPerPlay));
      total += static_cast<std::size_t>(c);
    }
    const auto flat = yaml_numbers(pn, "knots_v", static_cast<long>(total), "model.preisach");
    std::size_t at = 0;
    for (double c : counts) {
      knots.emplace_back(flat.begin() + at, flat.begin() + at + static_cast<std::size_t>(c));
      at += static_cast<std::size_t>(c);
    }
    pieces = total + r.size();
    if (pieces > static_cast<std::size_t>(kMaxPieces))
      throw std::runtime_error("model.preisach: " + std::to_string(pieces) + " pieces (at most " +
                               std::to_string(kMaxPieces) + ")");
  }
  const auto w = yaml_numbers(node, "weights_nm_per_v", static_cast<long>(pieces));
  const double b = yaml_number(node, "bias_nm");
  const CreepParams cp = read_creep_block(node["creep"]);
  if (node["kind"] && cp.kind != expected)
    throw std::runtime_error("model.creep: kind " + creep_kind_name(expected, preisach) + " needs " +
                             (expected == CreepKind::kNone      ? std::string("no creep key")
                              : expected == CreepKind::kLog     ? std::string("gamma_nm_per_v, t1_s, ...")
                              : expected == CreepKind::kLti     ? std::string("taus_s, gains_nm_per_v")
                              : expected == CreepKind::kProny   ? std::string("mode_gains, tau_min_s, ...")
                                                                : std::string("alpha, b_nm_per_v, ...")));
  auto m = std::make_unique<PiCreepModel>(r, w, b, cp, rate, knots, input_map);
  if (node["output_map"]) {
    const YAML::Node om = node["output_map"];
    if (!om.IsMap()) throw std::runtime_error("model.output_map: expected a mapping with h_range_nm, quadratic_nm, cubic_nm");
    check_keys(om, {"h_range_nm", "quadratic_nm", "cubic_nm"}, "model.output_map");
    const auto range = yaml_numbers(om, "h_range_nm", 2, "model.output_map");
    OutputMap map;
    map.lo_nm = range[0], map.hi_nm = range[1];
    map.quadratic_nm = yaml_number(om, "quadratic_nm", "model.output_map");
    map.cubic_nm = yaml_number(om, "cubic_nm", "model.output_map");
    m->set_output_map(map);
  }
  return m;
}

// ---- classical inverse -------------------------------------------------------------------------

PiInverse::PiInverse(const std::vector<double>& r, const std::vector<double>& w, double bias_nm) : b_(bias_nm) {
  if (r.empty() || r.size() != w.size() || r[0] != 0) throw std::runtime_error("PI inverse: need r_0 = 0 and one weight per threshold");
  if (!(w[0] > 0)) throw std::runtime_error("PI inverse: w_0 must be > 0 for the inverse to exist");
  double W_prev = 0, W = 0;
  for (std::size_t i = 0; i < r.size(); ++i) {
    if (w[i] < 0) throw std::runtime_error("PI inverse: weights must be >= 0");
    W_prev = W;
    W += w[i];
    double ri = 0;
    for (std::size_t j = 0; j <= i; ++j) ri += w[j] * (r[i] - r[j]);
    r_.push_back(ri);
    w_.push_back(i == 0 ? 1.0 / w[0] : -w[i] / (W * W_prev));
  }
  reset(bias_nm);
}

void PiInverse::reset(double position_nm) { p_.assign(r_.size(), position_nm - b_); }

double PiInverse::step(double target_nm) {
  const double y = target_nm - b_;
  double v = 0;
  for (std::size_t i = 0; i < r_.size(); ++i) {
    p_[i] = play(y, r_[i], p_[i]);
    v += w_[i] * p_[i];
  }
  return v;
}

}  // namespace piezo::models
