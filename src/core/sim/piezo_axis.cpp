#include "piezo_compensation/sim/piezo_axis.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>

#include "piezo_compensation/util/splitmix64.h"

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

Preisach::Preisach(const AxisConfig& axis) {
  const int n = axis.preisach_grid_count;
  const double half_range_v = 0.5 * (axis.voltage_max_v - axis.voltage_min_v);
  v_mid_ = 0.5 * (axis.voltage_max_v + axis.voltage_min_v);
  // Switching voltages at the centres of n equal bins over [−R, R]; α ≥ β (α = β: a relay without memory).
  std::vector<double> grid(n);
  for (int k = 0; k < n; ++k) grid[k] = half_range_v * (-1.0 + (2.0 * k + 1.0) / n);
  double sum = 0.0, straddle = 0.0;  // Σμ and Σμ over relays with β < 0 < α (they make the width at mid)
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j <= i; ++j) {
      const double a = grid[i], b = grid[j];
      const double c = 0.5 * (a + b) / half_range_v, w = 0.5 * (a - b) / half_range_v;
      const double dc = c - axis.preisach_centre_offset;
      const double mu = std::exp(-dc * dc / (2.0 * axis.preisach_centre_spread * axis.preisach_centre_spread) -
                                 w / axis.preisach_width_decay);
      double ja = 0.0, jb = 0.0;  // inside the cell; a relay without memory (α = β) keeps α = β
      if (axis.preisach_threshold_jitter) {
        const double cell = 2.0 * half_range_v / n;
        std::uint64_t h = static_cast<std::uint64_t>(i) * 1000003ULL + static_cast<std::uint64_t>(j);
        const auto unit = [&h] { return static_cast<double>(util::splitmix64(h) >> 11) * 0x1.0p-53; };
        ja = cell * (unit() - 0.5);
        jb = i == j ? ja : cell * (unit() - 0.5);
      }
      alpha_v_.push_back(a + ja);
      beta_v_.push_back(b + jb);
      weight_nm_.push_back(mu);
      start_state_.push_back(a + b < 0.0 ? 1 : -1);
      sum += mu;
      if (b < 0.0 && a > 0.0) straddle += mu;
    }
  }
  // Full-range loop: relays span 2·Σμ·s, the width at mid is 2·straddle·s; the linear part spans 2R·w_0.
  const double f = axis.loop_width_fraction;
  double s = 0.0;
  if (f > 0.0 && straddle > 0.0) {
    s = f * axis.stroke_nm / (2.0 * straddle);
    w0_ = (axis.stroke_nm - 2.0 * sum * s) / (2.0 * half_range_v);
    if (w0_ < 0.0)
      throw std::invalid_argument("simulator parameter axes." + axis.name +
                                  ".loop_width_fraction: too wide for this Preisach density (raise "
                                  "preisach_width_decay or lower the fraction)");
  } else {
    w0_ = axis.stroke_nm / (2.0 * half_range_v);
  }
  start_sum_ = 0.0;
  for (std::size_t k = 0; k < weight_nm_.size(); ++k) {
    weight_nm_[k] *= s;
    start_sum_ += weight_nm_[k] * start_state_[k];
  }
  state_ = start_state_;
  sort_thresholds();
}

double Preisach::update(double voltage_v, double nonlinear_scale) {
  const double u = voltage_v - v_mid_;
  if (!synced_) {
    // Every relay by the rule: the first step after construction or reset (their start states are not the
    // result of any one input), and the order the incremental steps keep.
    relay_sum_ = 0.0;
    for (std::size_t k = 0; k < state_.size(); ++k) {
      if (u >= alpha_v_[k])
        state_[k] = 1;
      else if (u <= beta_v_[k])
        state_[k] = -1;
      relay_sum_ += weight_nm_[k] * state_[k];
    }
    synced_ = true;
  } else if (u > u_prev_) {
    // Rising from u_prev: the relays with α ≤ u_prev are up already and those with β ≥ u were down; only the
    // ones with α in (u_prev, u] switch up.
    auto lo = std::upper_bound(alpha_sorted_.begin(), alpha_sorted_.end(), u_prev_);
    const auto hi = std::upper_bound(lo, alpha_sorted_.end(), u);
    for (; lo != hi; ++lo) switch_to(by_alpha_[static_cast<std::size_t>(lo - alpha_sorted_.begin())], 1);
  } else if (u < u_prev_) {
    // Falling: the relays with β in [u, u_prev] switch down unless α ≤ u (a memoryless relay at u stays up; one at
    // u_prev was up there and goes down now).
    auto lo = std::lower_bound(beta_sorted_.begin(), beta_sorted_.end(), u);
    const auto hi = std::upper_bound(lo, beta_sorted_.end(), u_prev_);
    for (; lo != hi; ++lo) {
      const std::size_t k = by_beta_[static_cast<std::size_t>(lo - beta_sorted_.begin())];
      if (!(u >= alpha_v_[k])) switch_to(k, -1);
    }
  }
  u_prev_ = u;
  output_nm_ = w0_ * u + nonlinear_scale * (relay_sum_ - start_sum_);
  return output_nm_;
}

void Preisach::switch_to(std::size_t k, signed char s) {
  if (state_[k] == s) return;
  state_[k] = s;
  relay_sum_ += 2.0 * s * weight_nm_[k];
}

void Preisach::sort_thresholds() {
  const std::size_t n = alpha_v_.size();
  by_alpha_.resize(n);
  by_beta_.resize(n);
  for (std::size_t k = 0; k < n; ++k) by_alpha_[k] = by_beta_[k] = k;
  std::stable_sort(by_alpha_.begin(), by_alpha_.end(), [&](std::size_t a, std::size_t b) { return alpha_v_[a] < alpha_v_[b]; });
  std::stable_sort(by_beta_.begin(), by_beta_.end(), [&](std::size_t a, std::size_t b) { return beta_v_[a] < beta_v_[b]; });
  alpha_sorted_.resize(n);
  beta_sorted_.resize(n);
  for (std::size_t k = 0; k < n; ++k) alpha_sorted_[k] = alpha_v_[by_alpha_[k]], beta_sorted_[k] = beta_v_[by_beta_[k]];
}

void Preisach::reset() {
  state_ = start_state_;
  output_nm_ = 0.0;
  synced_ = false;
}

CreepModes::CreepModes(const AxisConfig& axis) {
  if (!axis.creep_spectrum_tau_s.empty()) {
    tau_s_ = axis.creep_spectrum_tau_s;
    gains_ = axis.creep_spectrum_weights;
    state_.assign(tau_s_.size(), 0.0);
    decay_.assign(tau_s_.size(), 0.0);
    return;
  }
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
