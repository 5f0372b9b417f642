// Building blocks of one simulated piezo axis: Prandtl–Ishlinskii hysteresis and multi-mode creep.
// Exposed so tests (and anyone curious) can check each piece on its own. Equations: docs/simulator.md.
#pragma once

#include <cstdint>
#include <vector>

#include "piezo_compensation/sim/simulator_config.h"

namespace piezo::sim {

// Weighted play operators on the centred voltage u = v − v_mid:
//   F_i(t) = max(u − r_i, min(u + r_i, F_i(t−1))),  H = Σ w_i F_i.
// Weights are derived from stroke_nm, loop_width_fraction and play_weight_decay_v (see docs/simulator.md).
class PrandtlIshlinskii {
 public:
  explicit PrandtlIshlinskii(const AxisConfig& axis);
  // Advances to voltage v; the non-linear operators (i ≥ 1) are weighted by nonlinear_scale (1 = rate
  // independent). Returns H [nm].
  double update(double voltage_v, double nonlinear_scale = 1.0);
  double output_nm() const { return output_nm_; }
  void reset();  // all operators to 0 (the state after a demagnetising sweep around v_mid)
  const std::vector<double>& thresholds_v() const { return thresholds_v_; }
  const std::vector<double>& weights_nm_per_v() const { return weights_; }

 private:
  double v_mid_ = 0.0;
  std::vector<double> thresholds_v_, weights_, state_;
  double output_nm_ = 0.0;
};

// Preisach hysteresis: relay hysterons γ_{α,β} (+1 once u ≥ α, −1 once u ≤ β, else unchanged) on a grid of
// switching voltages α ≥ β over the range, weighted by a density over their centre and half-width (see
// AxisConfig::preisach_*), plus a linear term:  H = w_0·u + s·Σ μ_k γ_k − H_start.
// w_0 and s are solved, like the play weights, so that the full-range loop spans stroke_nm and is
// loop_width_fraction·stroke wide at mid voltage. Starts demagnetised around v_mid (relays with centre below 0
// up, the rest down), with H = 0 there.
class Preisach {
 public:
  explicit Preisach(const AxisConfig& axis);
  // Advances to voltage v; the relay part is weighted by nonlinear_scale (1 = rate independent). Returns H [nm].
  double update(double voltage_v, double nonlinear_scale = 1.0);
  // The same step with every relay visited (the reference the incremental step is tested against).
  double update_every_relay(double voltage_v, double nonlinear_scale = 1.0) {
    synced_ = false;
    return update(voltage_v, nonlinear_scale);
  }
  double output_nm() const { return output_nm_; }
  void reset();
  std::size_t relay_count() const { return alpha_v_.size(); }
  double linear_weight_nm_per_v() const { return w0_; }

 private:
  void switch_to(std::size_t k, signed char s);
  void sort_thresholds();

  double v_mid_ = 0.0, w0_ = 0.0, start_sum_ = 0.0, output_nm_ = 0.0;
  std::vector<double> alpha_v_, beta_v_, weight_nm_;  // weights already scaled by s
  std::vector<signed char> state_, start_state_;
  // A step visits only the relays whose threshold the input crossed (the thresholds sorted once, with the relays'
  // indices), and keeps Σ weight·state up to date: O(relays crossed), not O(relays), per sample.
  bool synced_ = false;  // false: the next update sets every relay by the rule
  double u_prev_ = 0.0, relay_sum_ = 0.0;
  std::vector<std::size_t> by_alpha_, by_beta_;
  std::vector<double> alpha_sorted_, beta_sorted_;
};

// Creep: first-order modes x_j relaxing towards the hysteretic displacement h, with log-spaced τ_j (weights
// ∝ τ^(−α)) or the explicit spectrum creep_spectrum_tau_s / creep_spectrum_weights;
//   creep = Σ g_j x_j,  x_j(t+dt) = h + (x_j(t) − h)·exp(−dt/τ_j)  (exact for h held over dt).
class CreepModes {
 public:
  explicit CreepModes(const AxisConfig& axis);
  double update(double h_nm, double dt_s);  // returns the creep displacement Σ g_j x_j [nm]
  double output_nm() const;
  void reset();
  const std::vector<double>& tau_s() const { return tau_s_; }
  const std::vector<double>& gains() const { return gains_; }

 private:
  std::vector<double> tau_s_, gains_, state_, decay_;
  double decay_dt_s_ = -1.0;
};

}  // namespace piezo::sim
