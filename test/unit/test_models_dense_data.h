// Small synthetic data for the neural model tests: a random-walk voltage through a play operator with a
// first-order creep term and a little noise, so every feature family carries signal.
#pragma once

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace test_data {

inline piezo::io::Dataset hysteretic_dataset(std::size_t n, std::uint64_t seed, double noise_nm = 2.0) {
  piezo::io::Dataset d;
  d.time_s.resize(n);
  auto& ax = d.add_axis("c");
  ax.voltage_v.resize(n);
  ax.position_nm.resize(n);
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n01;
  double v = 0.0, play = 0.0, creep = 0.0;
  for (std::size_t t = 0; t < n; ++t) {
    d.time_s[t] = static_cast<double>(t) / 11.0;
    if (t % 40 < 30) v = std::clamp(v + 3.0 * n01(rng), -80.0, 80.0);  // walk, then hold
    play = std::clamp(play, v - 5.0, v + 5.0);
    creep += (play - creep) * 0.01;
    ax.voltage_v[t] = v;
    ax.position_nm[t] = 12.0 * play + 2.0 * creep + noise_nm * n01(rng);
  }
  return d;
}

// One-step MAE of a model on the data (measured positions committed).
inline double one_step_mae(const piezo::models::Model& model, const piezo::io::Dataset& d, const std::string& axis) {
  auto m = model.clone();
  const auto& ax = d.axis(axis);
  m->reset(ax.voltage_v[0], ax.position_nm[0]);
  double sum = 0.0;
  for (std::size_t t = 0; t < d.size(); ++t) {
    const piezo::models::ModelInput in{ax.voltage_v[t], nullptr};
    sum += std::abs(m->predict(in) - ax.position_nm[t]);
    m->commit(in, ax.position_nm[t]);
  }
  return sum / static_cast<double>(d.size());
}

inline double mean_abs_deviation(const std::vector<double>& x) {
  double mean = 0.0;
  for (double v : x) mean += v;
  mean /= static_cast<double>(x.size());
  double s = 0.0;
  for (double v : x) s += std::abs(v - mean);
  return s / static_cast<double>(x.size());
}

}  // namespace test_data
