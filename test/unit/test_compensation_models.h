// Small models for the compensation tests, written here so the tests do not depend on the fitted kinds:
// a classical Prandtl-Ishlinskii hysteresis plus single-mode creep (not affine in voltage), a linear
// gain-plus-creep model (affine), and a model that turns NaN on demand.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <vector>

#include "piezo_compensation/models/model.h"

namespace piezo::test {

// y = Σ w_j play_rj(V) + g_c · z,  z ← z + α (V − z): single-mode creep, α = 1 − exp(−dt/τ).
class PiCreepModel : public models::Model {
 public:
  PiCreepModel(std::vector<double> thresholds_v, std::vector<double> weights_nm_per_v, double creep_gain_nm_per_v,
               double creep_tau_s, double rate_hz)
      : r_(std::move(thresholds_v)), w_(std::move(weights_nm_per_v)), g_(creep_gain_nm_per_v),
        alpha_(1.0 - std::exp(-1.0 / (creep_tau_s * rate_hz))), play_(r_.size(), 0.0) {}
  std::string kind() const override { return "test_pi_creep"; }
  void reset(double v, double) override {
    for (auto& p : play_) p = v;
    z_ = v;
  }
  double predict(const models::ModelInput& in) const override {
    double y = 0.0;
    for (std::size_t j = 0; j < r_.size(); ++j) y += w_[j] * play(j, in.voltage_v);
    return y + g_ * (z_ + alpha_ * (in.voltage_v - z_));
  }
  void commit(const models::ModelInput& in, double) override {
    for (std::size_t j = 0; j < r_.size(); ++j) play_[j] = play(j, in.voltage_v);
    z_ += alpha_ * (in.voltage_v - z_);
  }
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<PiCreepModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return w_.size() + 2; }

 private:
  double play(std::size_t j, double v) const { return std::max(v - r_[j], std::min(v + r_[j], play_[j])); }
  std::vector<double> r_, w_;
  double g_, alpha_;
  std::vector<double> play_;
  double z_ = 0.0;
};

// A default PI + creep plant: ~14 nm/V static gain, ~12 % hysteresis, creep τ = 300 s.
inline std::unique_ptr<PiCreepModel> make_pi_creep(double rate_hz = 11.0) {
  return std::make_unique<PiCreepModel>(std::vector<double>{0.0, 5.0, 10.0, 20.0, 40.0},
                                        std::vector<double>{8.0, 1.5, 1.2, 1.0, 0.8}, 1.5, 300.0, rate_hz);
}

// The reload hand-over tests' stage: a seeded random walk in ±60 V (steps up to ±2 V) driving make_pi_creep
// from rest at the walk's first voltage; its position is the plant's plus offset_nm.
struct PiCreepWalk {
  std::vector<double> voltage_v, position_nm;
};
inline PiCreepWalk pi_creep_walk(std::size_t n, double rate_hz, double offset_nm, std::uint64_t seed = 7) {
  PiCreepWalk w{std::vector<double>(n), std::vector<double>(n)};
  double x = 0.0;
  for (auto& v : w.voltage_v) {
    seed = seed * 6364136223846793005ULL + 1442695040888963407ULL;
    x = std::clamp(x + ((seed >> 33) % 2001 / 1000.0 - 1.0) * 2.0, -60.0, 60.0);
    v = x;
  }
  auto plant = make_pi_creep(rate_hz);
  plant->reset(w.voltage_v[0], 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    const models::ModelInput in{w.voltage_v[i], nullptr};
    const double y = plant->predict(in);
    plant->commit(in, y);
    w.position_nm[i] = y + offset_nm;
  }
  return w;
}

// y = a V + b z with the same single-mode creep state z: affine in V at every state.
class LinearCreepModel : public models::Model {
 public:
  LinearCreepModel(double gain_nm_per_v, double creep_gain_nm_per_v, double creep_tau_s, double rate_hz)
      : a_(gain_nm_per_v), b_(creep_gain_nm_per_v), alpha_(1.0 - std::exp(-1.0 / (creep_tau_s * rate_hz))) {}
  std::string kind() const override { return "test_linear_creep"; }
  void reset(double v, double) override { z_ = v; }
  double predict(const models::ModelInput& in) const override {
    return a_ * in.voltage_v + b_ * (z_ + alpha_ * (in.voltage_v - z_));
  }
  void commit(const models::ModelInput& in, double) override { z_ += alpha_ * (in.voltage_v - z_); }
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<LinearCreepModel>(*this); }
  bool uses_position_history() const override { return false; }
  bool is_affine_in_voltage() const override { return true; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return 3; }
  double alpha() const { return alpha_; }

 private:
  double a_, b_, alpha_;
  double z_ = 0.0;
};

// Wraps a model and returns NaN once `fail_after` samples have been committed.
class FailingModel : public models::Model {
 public:
  FailingModel(std::unique_ptr<models::Model> inner, std::size_t fail_after)
      : inner_(std::move(inner)), fail_after_(fail_after) {}
  FailingModel(const FailingModel& o) : inner_(o.inner_->clone()), fail_after_(o.fail_after_), n_(o.n_) {}
  std::string kind() const override { return "test_failing"; }
  void reset(double v, double x) override { inner_->reset(v, x); }
  double predict(const models::ModelInput& in) const override {
    return n_ >= fail_after_ ? std::numeric_limits<double>::quiet_NaN() : inner_->predict(in);
  }
  void commit(const models::ModelInput& in, double x) override {
    inner_->commit(in, x);
    ++n_;
  }
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<FailingModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return 0; }

 private:
  std::unique_ptr<models::Model> inner_;
  std::size_t fail_after_, n_ = 0;
};

}  // namespace piezo::test
