// Kind "pi_creep_play": Prandtl–Ishlinskii hysteresis whose creep follows each hysteron (the Krejčí–Kuhnen
// creep operator in PI form). Every play operator's output q_i feeds its own first-order low-passes at a
// shared set of time constants τ_j [s]:
//   y = b + Σ_i w_i·q_i + Σ_i Σ_j g_ij·LP_τj(q_i),   q_i = play_{r_i}(V),  r_0 = 0 (the linear term),
//   LP_τ(q)_t = a·LP_τ(q)_{t−1} + (1 − a)·q_t,   a = exp(−Δt/τ), Δt = 1 / sample rate (one step per row).
// So the creep depends on which part of the loop moved (amplitude, direction, last reversal), where the
// pi_creep_* kinds have one creep on the summed output. Optionally each play output also has a bend: two
// monotone quadratic pieces on its training range [lo_i, hi_i] (play_bend_convex/concave below), +
// u_i·convex(q_i) + d_i·concave(q_i), so a branch can curve either way, which the straight plays can only
// follow in steps. All weights w_i, g_ij, u_i, d_i are ≥ 0 and the memory-free play's step slope w_0 + Σ_j
// g_0j·(1 − a_j) is > 0, so at every state the prediction is strictly increasing in V, piecewise linear
// (quadratic with bends) between the kinks p_i ± r_i (and lo_i ± r_i, hi_i ± r_i): the inverse is exact
// (closed form, with bends bisection within the kink interval), and the loops' ends (ascending and descending
// branches) are monotone.
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/models/model.h"

namespace piezo::models {

// The bend pieces of a play output q on [lo, hi] (s = hi − lo > 0), both non-decreasing and C¹, slopes in [0,
// 2]: convex (q − lo)²/s, 0 below lo, 2(q − lo) − s above hi; concave 2(q − lo) − (q − lo)²/s, 2(q − lo)
// below lo, s above hi. Non-negative weights on the pair give any quadratic bend of either sign on [lo, hi].
inline double play_bend_convex(double q, double lo, double hi) {
  const double s = hi - lo, x = q - lo;
  return x <= 0 ? 0.0 : q >= hi ? 2.0 * x - s : x * x / s;
}
inline double play_bend_concave(double q, double lo, double hi) {
  const double s = hi - lo, x = q - lo;
  return x <= 0 ? 2.0 * x : q >= hi ? s : 2.0 * x - x * x / s;
}

// The optional bends, one range and pair of weights per play (all empty: none).
struct PlayBends {
  std::vector<double> lo_v, hi_v, convex_nm_per_v, concave_nm_per_v;
  bool empty() const { return lo_v.empty(); }
};

class PiCreepPlayModel : public Model {
 public:
  // gains_nm_per_v: play by play, one gain per time constant (size thresholds × taus).
  PiCreepPlayModel(std::vector<double> thresholds_v, std::vector<double> weights_nm_per_v,
                   std::vector<double> taus_s, std::vector<double> gains_nm_per_v, double bias_nm,
                   double sample_rate_hz, PlayBends bends = {});

  std::string kind() const override { return "pi_creep_play"; }
  void reset(double voltage_v, double position_nm) override;
  double predict(const ModelInput& in) const override { return predict_v(in.voltage_v); }
  void commit(const ModelInput& in, double position_nm) override;
  std::unique_ptr<Model> clone() const override { return std::make_unique<PiCreepPlayModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override;
  std::vector<double> creep_mode_taus_s() const override { return taus_; }
  // The low-passes with a non-zero gain: each one's share g_ij·a_j·l_ij of the next prediction.
  std::size_t linear_state_count() const override { return live_.size(); }
  double linear_state_nm(std::size_t k) const override;
  void shift_linear_state(std::size_t k, double delta_nm) override;

  double predict_v(double voltage_v) const;
  // Exact inverse for the current state: the voltage whose predict() is target_nm.
  double inverse(double target_nm) const;

  const std::vector<double>& thresholds_v() const { return r_; }
  const std::vector<double>& weights() const { return w_; }
  const std::vector<double>& taus_s() const { return taus_; }
  const std::vector<double>& gains() const { return g_; }  // play by play
  const std::vector<double>& poles() const { return a_; }
  double bias_nm() const { return b_; }
  double sample_rate_hz() const { return rate_hz_; }
  // Per play: the prediction's slope in its play output at this step, w_i + Σ_j g_ij·(1 − a_j).
  const std::vector<double>& step_slopes() const { return c_; }
  const PlayBends& bends() const { return bends_; }

  static ModelPtr load(const YAML::Node& node);  // fitted by training::fit_pi_creep_play

 private:
  std::vector<double> r_, w_, taus_, g_, a_, c_;
  double b_, rate_hz_;
  PlayBends bends_;
  std::vector<std::size_t> live_;  // indices i·J + j with g_ij·a_j ≠ 0
  std::vector<double> p_, l_;      // state: play outputs, low-passes (play by play)
  double held_ = 0;                // Σ g_ij·a_j·l_ij: the low-passes' share of the next prediction

  void update_held();
  double bend(std::size_t i, double q) const;
};

}  // namespace piezo::models
