// Synthetic study-like data for the model tests: a trending random walk in [-80, 80] V with holds, positions
// from a given model (the kinds' own forward models are ideal generators), optional Gaussian encoder noise.
#pragma once

#include <cmath>
#include <random>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace piezo::testdata {

inline std::vector<double> random_walk_v(std::size_t n, std::uint64_t seed, double hold_prob = 0.002,
                                         std::vector<int>* phase = nullptr) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> step(0.0, 0.6);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<double> v(n);
  double x = 0, trend = 0;
  std::size_t hold = 0;
  for (std::size_t i = 0; i < n; ++i) {
    if (hold > 0) {
      --hold;
      if (phase) phase->push_back(1);
    } else {
      if (u(rng) < 0.01) trend = 0.3 * (u(rng) - 0.5);
      x += trend + step(rng);
      if (x > 80) x = 80, trend = -std::abs(trend);
      if (x < -80) x = -80, trend = std::abs(trend);
      if (u(rng) < hold_prob) hold = static_cast<std::size_t>(200 + 3000 * u(rng));
      if (phase) phase->push_back(0);
    }
    v[i] = x;
  }
  return v;
}

// Runs `truth_model` over the voltages (free-run: it uses no measured positions) and adds noise.
inline io::Dataset make_dataset(models::Model& truth_model, const std::vector<double>& v, double rate_hz,
                                double noise_nm, std::uint64_t seed, const std::vector<int>* phase = nullptr) {
  io::Dataset d;
  d.time_s.resize(v.size());
  for (std::size_t i = 0; i < v.size(); ++i) d.time_s[i] = i / rate_hz;
  io::AxisSeries& c = d.add_axis("c");
  c.voltage_v = v;
  c.true_position_nm.resize(v.size());
  c.position_nm.resize(v.size());
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, noise_nm);
  truth_model.reset(v[0], 0.0);
  for (std::size_t i = 0; i < v.size(); ++i) {
    models::ModelInput in{v[i], nullptr};
    const double y = truth_model.predict(in);
    truth_model.commit(in, y);
    c.true_position_nm[i] = y;
    c.position_nm[i] = y + (noise_nm > 0 ? noise(rng) : 0.0);
  }
  if (phase) {
    d.phase = *phase;
    d.segment.assign(v.size(), 0);
  }
  return d;
}

}  // namespace piezo::testdata
