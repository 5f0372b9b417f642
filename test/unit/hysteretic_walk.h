// Synthetic hysteretic data shared by the neural model tests and bench_models_neural: a random-walk voltage
// with holds through a play operator plus a first-order creep term and Gaussian noise (axis "c", 11 Hz), so
// every feature family carries signal. Deterministic for a seed.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <random>

#include "piezo_compensation/io/dataset.h"

namespace test_data {

struct HystereticWalk {
  std::size_t period_samples = 40;  // the voltage walks for the first walk_samples of every period, then holds
  std::size_t walk_samples = 30;
  double step_v = 3.0;              // standard deviation of one walk step
  double play_half_width_v = 5.0;
  double creep_rate = 0.01;         // per sample, towards the play output
  double play_gain_nm_per_v = 12.0;
  double creep_gain_nm_per_v = 2.0;
  double noise_nm = 2.0;
};

inline piezo::io::Dataset hysteretic_walk(std::size_t n, std::uint64_t seed, const HystereticWalk& w) {
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
    if (t % w.period_samples < w.walk_samples) v = std::clamp(v + w.step_v * n01(rng), -80.0, 80.0);
    play = std::clamp(play, v - w.play_half_width_v, v + w.play_half_width_v);
    creep += (play - creep) * w.creep_rate;
    ax.voltage_v[t] = v;
    ax.position_nm[t] = w.play_gain_nm_per_v * play + w.creep_gain_nm_per_v * creep + w.noise_nm * n01(rng);
  }
  return d;
}

}  // namespace test_data
