// Shared pieces of the residual tests: a small base model the tests fit themselves, and synthetic data with
// one planted effect, so the statistics are tested without depending on the simulator.
#pragma once

#include <Eigen/Dense>
#include <cmath>
#include <cstdlib>
#include <memory>
#include <random>
#include <string>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::test {

// position = w0 + w1·V + w2·lowpass(V, 20 s): the shape of the synthetic plant without its extra effect.
class LowpassLinearModel : public models::Model {
 public:
  LowpassLinearModel(double w0, double w1, double w2, double fs) : w_{w0, w1, w2}, fs_(fs) {
    alpha_ = std::exp(-1.0 / (20.0 * fs));
  }
  std::string kind() const override { return "residual_test_lowpass_linear"; }
  void reset(double v, double) override { lp_ = v; }
  double predict(const models::ModelInput& in) const override {
    const double lp = alpha_ * lp_ + (1 - alpha_) * in.voltage_v;
    return w_[0] + w_[1] * in.voltage_v + w_[2] * lp;
  }
  void commit(const models::ModelInput& in, double) override { lp_ = alpha_ * lp_ + (1 - alpha_) * in.voltage_v; }
  std::unique_ptr<models::Model> clone() const override { return std::make_unique<LowpassLinearModel>(*this); }
  bool uses_position_history() const override { return false; }
  bool is_affine_in_voltage() const override { return true; }
  YAML::Node to_yaml() const override {
    YAML::Node n;
    n["w0"] = w_[0];
    n["w1"] = w_[1];
    n["w2"] = w_[2];
    n["fs"] = fs_;
    return n;
  }
  std::size_t num_parameters() const override { return 3; }

  static std::unique_ptr<LowpassLinearModel> fit(const io::Dataset& d, const std::string& axis, std::size_t rows) {
    const auto& ax = d.axis(axis);
    const double fs = d.sample_rate_hz();
    LowpassLinearModel probe(0, 0, 0, fs);
    Eigen::Matrix3d G = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    double lp = ax.voltage_v[0];
    for (std::size_t i = 0; i < rows; ++i) {
      lp = probe.alpha_ * lp + (1 - probe.alpha_) * ax.voltage_v[i];
      const Eigen::Vector3d x(1.0, ax.voltage_v[i], lp);
      G += x * x.transpose();
      b += x * ax.position_nm[i];
    }
    const Eigen::Vector3d w = G.ldlt().solve(b);
    return std::make_unique<LowpassLinearModel>(w[0], w[1], w[2], fs);
  }

 private:
  double w_[3];
  double fs_;
  double alpha_ = 0.0;
  double lp_ = 0.0;
};

// A physics base for the simulator tests (by default the fast PI hysteresis + LTI creep) on axis c;
// PIEZO_RESIDUAL_BASE=<kind> tries another by hand.
inline std::string physics_base_kind(const std::string& default_kind = "pi_creep_lti") {
  const char* kind = std::getenv("PIEZO_RESIDUAL_BASE");
  return kind ? kind : default_kind;
}
// `previous` (optional): the base a backfitting round replaces; the refit starts from its creep law.
inline models::ModelPtr fit_physics_base(const io::Dataset& fit, const io::Dataset& val,
                                         const std::string& default_kind = "pi_creep_lti",
                                         const models::Model* previous = nullptr, bool same_structure = false) {
  training::FitRequest req;
  req.train = &fit;
  req.validation = &val;
  req.axis = "c";
  if (previous) req.options = training::refit_options(*previous, req.options, same_structure);
  return training::fit_model(physics_base_kind(default_kind), req);
}

inline void register_test_kind() {
  static const bool done = [] {
    models::register_model_kind(models::ModelKind{
        "residual_test_lowpass_linear", "test only",
        [](const YAML::Node& n) -> models::ModelPtr {
          return std::make_unique<LowpassLinearModel>(n["w0"].as<double>(), n["w1"].as<double>(), n["w2"].as<double>(),
                                                       n["fs"].as<double>());
        },
        nullptr});
    return true;
  }();
  (void)done;
}

enum class Planted { kNone, kPositionPeriodic, kAuxTemperature, kCrossAxis, kPeriodicDisturbance };

// Synthetic c-axis data at 11 Hz: a random-walk voltage with holds, plant 12·V + 4·lowpass(V, 20 s) nm,
// encoder noise σ 20.8 nm quantised to 20 nm, plus at most one planted effect. An `a` axis (own random walk)
// and a `temperature_c` column are always present, whether or not they matter.
inline io::Dataset synthetic(Planted effect, double hours, std::uint64_t seed, bool with_temperature = true) {
  const double fs = 11.0;
  const std::size_t n = static_cast<std::size_t>(hours * 3600 * fs);
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  io::Dataset d;
  d.time_s.resize(n);
  d.add_axis("a");
  d.add_axis("c");  // may reallocate: take references after both exist
  auto& a = d.axis("a");
  auto& c = d.axis("c");
  a.voltage_v.resize(n);
  a.position_nm.resize(n);
  c.voltage_v.resize(n);
  c.position_nm.resize(n);
  c.true_position_nm.resize(n);
  io::AuxSignal temp{"temperature_c", std::vector<double>(n)};
  const double alpha = std::exp(-1.0 / (20.0 * fs));
  const double alpha_t = std::exp(-1.0 / (300.0 * fs));
  double vc = 0, va = 0, lp = 0, tw = 0, tlp = 22.0;
  int hold = 0;
  std::vector<double> va_hist;
  for (std::size_t i = 0; i < n; ++i) {
    const double t = static_cast<double>(i) / fs;
    d.time_s[i] = t;
    if (hold > 0) {
      --hold;
    } else {
      vc = std::clamp(vc + 2.0 * g(rng), -80.0, 80.0);
      if (u(rng) < 0.002) hold = static_cast<int>(60 * fs * u(rng));
    }
    va = std::clamp(va + 1.5 * g(rng), -80.0, 80.0);
    va_hist.push_back(va);
    lp = alpha * lp + (1 - alpha) * vc;
    tw += 0.0005 * g(rng);
    const double temperature = 22.0 + 0.6 * std::sin(6.283185307179586 * t / 5400.0) + tw;
    tlp = alpha_t * tlp + (1 - alpha_t) * temperature;
    double x = 12.0 * vc + 4.0 * lp;
    switch (effect) {
      case Planted::kNone: break;
      case Planted::kPositionPeriodic: x += 30.0 * std::sin(6.283185307179586 * x / 400.0); break;
      case Planted::kAuxTemperature: x += 150.0 * (tlp - 22.0); break;
      case Planted::kCrossAxis: x += 1.5 * va_hist[i >= 11 ? i - 11 : 0]; break;
      case Planted::kPeriodicDisturbance: x += 35.0 * std::sin(6.283185307179586 * 0.0123 * t + 0.4); break;
    }
    c.voltage_v[i] = vc;
    c.true_position_nm[i] = x;
    c.position_nm[i] = 20.0 * std::round((x + 20.8 * g(rng)) / 20.0);
    a.voltage_v[i] = va;
    a.position_nm[i] = 250.0 * std::round((va * 12.0 + 20.8 * g(rng)) / 250.0);
    temp.values[i] = temperature;
  }
  if (with_temperature) d.aux.push_back(temp);
  return d;
}

}  // namespace piezo::test
