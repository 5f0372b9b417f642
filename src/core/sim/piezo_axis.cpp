#include "piezo_compensation/sim/piezo_axis.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace piezo::sim {

PrandtlIshlinskii::PrandtlIshlinskii(const AxisConfig& axis) {
  const int n = axis.play_operator_count;
  const double half_range_v = 0.5 * (axis.voltage_max_v - axis.voltage_min_v);
  v_mid_ = 0.5 * (axis.voltage_max_v + axis.voltage_min_v);
  thresholds_v_.resize(n);
  std::vector<double> shape(n, 0.0);
  // Full-range loop: operator i spans 2(R − r_i) and is 2·min(r_i, R − r_i) wide at mid voltage.
  double width = 0.0, span_rest = 0.0;
  for (int i = 0; i < n; ++i) {
    thresholds_v_[i] = half_range_v * i / n;
    if (i == 0) continue;
    shape[i] = std::exp(-thresholds_v_[i] / axis.play_weight_decay_v);
    width += shape[i] * 2.0 * std::min(thresholds_v_[i], half_range_v - thresholds_v_[i]);
    span_rest += shape[i] * 2.0 * (half_range_v - thresholds_v_[i]);
  }
  // The linear operator (r_0 = 0) sets the width fraction: width / (2R·w_0 + span_rest) = f.
  const double f = axis.loop_width_fraction;
  double w0 = 0.0;
  if (f <= 0.0) {
    std::fill(shape.begin(), shape.end(), 0.0);
    span_rest = 0.0;
    w0 = 1.0;
  } else {
    w0 = (width / f - span_rest) / (2.0 * half_range_v);
    if (w0 < 0.0)
      throw std::invalid_argument("simulator parameter axes." + axis.name +
                                  ".loop_width_fraction: too wide for play_weight_decay_v (raise the decay)");
  }
  shape[0] = w0;
  const double span = 2.0 * half_range_v * w0 + span_rest;
  weights_.resize(n);
  for (int i = 0; i < n; ++i) weights_[i] = shape[i] * axis.stroke_nm / span;
  state_.assign(n, 0.0);
}

double PrandtlIshlinskii::update(double voltage_v, double nonlinear_scale) {
  const double u = voltage_v - v_mid_;
  double nonlinear = 0.0;
  const std::size_t n = state_.size();
  state_[0] = u;  // r_0 = 0: the linear operator
  for (std::size_t i = 1; i < n; ++i) {
    const double r = thresholds_v_[i];
    const double f = std::max(u - r, std::min(u + r, state_[i]));
    state_[i] = f;
    nonlinear += weights_[i] * f;
  }
  output_nm_ = weights_[0] * u + nonlinear_scale * nonlinear;
  return output_nm_;
}

void PrandtlIshlinskii::reset() {
  std::fill(state_.begin(), state_.end(), 0.0);
  output_nm_ = 0.0;
}

CreepModes::CreepModes(const AxisConfig& axis) {
  const int m = axis.creep_mode_count;
  tau_s_.resize(m);
  gains_.resize(m);
  double sum = 0.0;
  for (int j = 0; j < m; ++j) {
    const double x = m == 1 ? 0.0 : static_cast<double>(j) / (m - 1);
    tau_s_[j] = axis.creep_tau_min_s * std::pow(axis.creep_tau_max_s / axis.creep_tau_min_s, x);
    gains_[j] = std::pow(tau_s_[j], -axis.creep_alpha);
    sum += gains_[j];
  }
  for (auto& g : gains_) g *= axis.creep_gain / sum;
  state_.assign(m, 0.0);
  decay_.assign(m, 0.0);
}

double CreepModes::update(double h_nm, double dt_s) {
  // Reuse the decay factors while dt stays the same (11 Hz data: every step).
  if (std::fabs(dt_s - decay_dt_s_) > 1e-9 * dt_s) {
    for (std::size_t j = 0; j < tau_s_.size(); ++j) decay_[j] = std::exp(-dt_s / tau_s_[j]);
    decay_dt_s_ = dt_s;
  }
  double c = 0.0;
  for (std::size_t j = 0; j < state_.size(); ++j) {
    state_[j] = h_nm + (state_[j] - h_nm) * decay_[j];
    c += gains_[j] * state_[j];
  }
  return c;
}

double CreepModes::output_nm() const {
  double c = 0.0;
  for (std::size_t j = 0; j < state_.size(); ++j) c += gains_[j] * state_[j];
  return c;
}

void CreepModes::reset() { std::fill(state_.begin(), state_.end(), 0.0); }

}  // namespace piezo::sim
