// Kinds "pi", "pi_creep_log", "pi_creep_lti", "pi_creep_fractional": Prandtl–Ishlinskii hysteresis
//   y = b + Σ_i w_i · play_{r_i}(V)      (r_0 = 0, w_i ≥ 0, w_0 > 0: strictly increasing, so invertible)
// plus an optional creep law on the voltage (creep_models.h). Weights by constrained least squares (NNLS on the
// play weights); the creep law's time constants / exponent by a 1-D or coordinate search around it.
// Kinds "preisach", "preisach_creep_prony": the same with each play output cut into monotone pieces at knots
// (features/play_operator.h: play_pieces), one non-negative weight per piece,
//   y = b + Σ_i Σ_k w_ik · piece_k(play_{r_i}(V)) + creep,
// a discrete Preisach plane of ramp hysterons (centre = knot, half-width = r_i) that can be asymmetric, which the
// symmetric play operators cannot. Equal weights along a play give PI back. Still monotone in V, so invertible.
// The PI kinds may cut the memory-free play (r_0 = 0) alone into pieces: an input map, a monotone piecewise-linear
// function of V in front of the symmetric plays (the "modified PI" of asymmetric hysteresis; the fit chooses it by
// validation, training/fit_pi.cpp), stored as `input_map: {knots_v: [...]}`.
// Every PI and Preisach kind may carry an output map: a monotone static nonlinearity S of the hysteresis output H,
//   y = b + S(H) + creep,   S(H) = H + a₂·z² + a₃·z³,   z = (H − H_mid)/H_half on [H_lo, H_hi], affine beyond,
// (the superposition operator of the modified PI: loops whose middle and ends bend differently, which the odd play
// operators cannot; the real MM3E's c axis, docs/validation/models.md "Real recordings"). The creep input stays H. Stored as
// `output_map: {h_range_nm: [lo, hi], quadratic_nm, cubic_nm}`; S' > 0 on its range is checked on load.
#pragma once

#include <Eigen/Dense>

#include <string>
#include <vector>

#include "piezo_compensation/models/creep_models.h"
#include "piezo_compensation/models/model.h"

namespace piezo::models {

// The output map S (see above). Identity when empty().
struct OutputMap {
  double lo_nm = 0, hi_nm = 0, quadratic_nm = 0, cubic_nm = 0;
  bool empty() const { return quadratic_nm == 0 && cubic_nm == 0; }
  double operator()(double h_nm) const;
  double slope(double h_nm) const;  // dS/dH
  // Smallest dS/dH over [lo, hi] (the map is affine beyond).
  double min_slope() const;
};

class PiCreepModel : public Model {
 public:
  // knots_v: empty for the PI kinds; for the preisach kinds one (possibly empty) knot list per play operator, and
  // then one weight per piece (Σ_i (knots_i + 1) weights, play by play). input_map: a PI kind whose knots_v has
  // knots on the first play only (the input map); the kind stays PI.
  PiCreepModel(std::vector<double> thresholds_v, std::vector<double> weights_nm_per_v, double bias_nm,
               CreepParams creep, double sample_rate_hz, std::vector<std::vector<double>> knots_v = {},
               bool input_map = false);

  std::string kind() const override { return creep_kind_name(creep_.kind, preisach()); }
  void reset(double voltage_v, double position_nm) override;
  double predict(const ModelInput& in) const override { return predict_v(in.voltage_v); }
  void commit(const ModelInput& in, double position_nm) override;
  std::unique_ptr<Model> clone() const override { return std::make_unique<PiCreepModel>(*this); }
  bool uses_position_history() const override { return false; }
  bool is_affine_in_voltage() const override { return false; }
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override;
  // The creep modes with a non-zero gain: each one's low-pass state (its share g·pole·l of the next prediction).
  std::size_t linear_state_count() const override { return live_modes_.size(); }
  double linear_state_nm(std::size_t k) const override;
  void shift_linear_state(std::size_t k, double delta_nm) override;
  // The hysteresis has no time and the creep modes' time constants are in seconds: any step.
  std::string fixed_rate_reason() const override { return ""; }
  void set_step_s(double dt_s) override;  // the creep poles exp(−dt/τ) for the next commits
  double step_s() const { return step_s_; }

  double predict_v(double voltage_v) const;
  // Exact inverse for the current state: the voltage whose predict() is target_nm (piecewise-linear, closed
  // form between breakpoints). Unique when the model is strictly increasing in V (w_0 > 0, creep slope ≥ 0).
  double inverse(double target_nm) const;

  const std::vector<double>& thresholds_v() const { return r_; }
  const std::vector<double>& weights() const { return w_; }  // per piece when there are knots
  bool preisach() const { return !knots_.empty() && !input_map_; }  // the preisach kinds
  bool has_input_map() const { return input_map_; }                 // a PI kind with an input map
  // One knot list per play operator (empty: one weight per play); for an input map, knots on the first play only.
  const std::vector<std::vector<double>>& knots_v() const { return knots_; }
  // Hysteresis output Σ w·pieces for input v from play states p; writes the advanced states to p_next if given.
  double hysteresis(double v, const std::vector<double>& p, std::vector<double>* p_next = nullptr) const;
  double bias_nm() const { return b_; }
  const OutputMap& output_map() const { return map_; }
  // Sets the output map; throws when it is not finite, its range is empty or S' ≤ 0 somewhere on it.
  void set_output_map(const OutputMap& map);
  const CreepParams& creep() const { return creep_; }
  const std::vector<double>& mode_taus_s() const { return taus_; }
  std::vector<double> creep_mode_taus_s() const override { return taus_; }
  const PiCreepModel* pi_family() const override { return this; }
  PiCreepModel* pi_family() override { return this; }
  bool takes_output_map() const override { return true; }
  const std::vector<double>& mode_gains() const { return gains_; }
  const std::vector<double>& mode_poles() const { return poles_; }
  double sample_rate_hz() const { return rate_hz_; }

  static ModelPtr load(const YAML::Node& node);  // fitted by training::fit_pi_creep (training/fitters.h)

 private:
  std::vector<double> r_, w_;
  std::vector<std::vector<double>> knots_;
  bool input_map_ = false;
  std::vector<std::size_t> first_;  // index in w_ of each play's first piece
  double b_;
  OutputMap map_;
  CreepParams creep_;
  double rate_hz_;   // the training rate (the model file's sample_rate_hz)
  double step_s_;    // the step the poles are for (1 / rate_hz_ until set_step_s)
  std::vector<double> taus_, gains_, poles_;  // expanded creep modes
  std::vector<std::size_t> live_modes_;       // modes with g·pole ≠ 0 (the linear states)
  std::vector<double> p_, l_;                 // state: play outputs, mode low-passes

  double inverse_piecewise(double target_nm) const;  // exact without an output map
};

// The classical inverse PI operator (Kuhnen / Al Janaideh): V = Σ_i w'_i · play_{r'_i}(y − b) with
// w'_0 = 1/w_0, w'_i = −w_i / (W_i W_{i−1}), r'_i = Σ_{j≤i} w_j (r_i − r_j), W_i = Σ_{j≤i} w_j.
// Exact inverse of the hysteresis part when both start from the zero state.
class PiInverse {
 public:
  PiInverse(const std::vector<double>& thresholds_v, const std::vector<double>& weights, double bias_nm);
  void reset(double position_nm);  // rest: all play states at position − bias
  double step(double target_nm);   // voltage for the target, advancing the state
  const std::vector<double>& thresholds_nm() const { return r_; }
  const std::vector<double>& weights() const { return w_; }

 private:
  std::vector<double> r_, w_, p_;
  double b_;
};

}  // namespace piezo::models
