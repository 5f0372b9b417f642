// Shared by the creep-model tests: time slices of a recording and the free-run error inside the holds against the
// true position (MAE, and the worst end-of-hold error); model-file text round trips in test_model_text.h.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/model_file.h"
#include "test_model_text.h"

#include <string>
#include <gtest/gtest.h>

namespace piezo {

namespace {

io::Dataset slice(const io::Dataset& d, std::size_t b, std::size_t e) {
  io::Dataset s;
  s.time_s.assign(d.time_s.begin() + b, d.time_s.begin() + e);
  io::AxisSeries& ax = s.add_axis("c");
  const io::AxisSeries& src = d.axis("c");
  ax.voltage_v.assign(src.voltage_v.begin() + b, src.voltage_v.begin() + e);
  ax.position_nm.assign(src.position_nm.begin() + b, src.position_nm.begin() + e);
  ax.true_position_nm.assign(src.true_position_nm.begin() + b, src.true_position_nm.begin() + e);
  if (!d.phase.empty()) s.phase.assign(d.phase.begin() + b, d.phase.begin() + e);
  if (!d.segment.empty()) s.segment.assign(d.segment.begin() + b, d.segment.begin() + e);
  return s;
}

struct HoldScore {
  double mae_nm = 0, worst_end_nm = 0, walk_mae_nm = 0;  // walk: samples ≥ from outside holds
  int holds = 0;
  std::vector<double> start_nm, end_nm, voltage_v;  // per hold: signed mean error of its first and last 5 s, voltage
};

// Free-run over all of `d` from rest at its first voltage; scored against the true position inside the holds of
// samples ≥ from: MAE, and per hold the mean error of its last 5 s (and the MAE outside the holds).
HoldScore score_holds(const models::Model& fitted, const io::Dataset& d, std::size_t from, double rate_hz) {
  auto m = fitted.clone();
  const io::AxisSeries& ax = d.axis("c");
  m->reset(ax.voltage_v[0], ax.position_nm[0]);
  HoldScore s;
  double sum = 0, walk = 0;
  std::size_t n = 0, n_walk = 0;
  std::vector<double> err(ax.voltage_v.size(), 0.0);
  for (std::size_t t = 0; t < ax.voltage_v.size(); ++t) {
    models::ModelInput in{ax.voltage_v[t], nullptr};
    const double y = m->predict(in);
    m->commit(in, y);
    err[t] = y - ax.true_position_nm[t];
    if (t >= from && d.phase[t] == 1) sum += std::abs(err[t]), ++n;
    if (t >= from && d.phase[t] != 1) walk += std::abs(err[t]), ++n_walk;
  }
  s.mae_nm = n ? sum / n : INFINITY;
  s.walk_mae_nm = n_walk ? walk / n_walk : INFINITY;
  const std::size_t last = static_cast<std::size_t>(5 * rate_hz);
  for (std::size_t t = from; t < err.size(); ++t) {
    const bool end_of_hold = d.phase[t] == 1 && (t + 1 == err.size() || d.phase[t + 1] != 1);
    if (!end_of_hold) continue;
    double e = 0, e0 = 0;
    for (std::size_t k = t + 1 - last; k <= t; ++k) e += err[k];
    std::size_t b = t;
    while (b > from && d.phase[b - 1] == 1) --b;
    for (std::size_t k = b; k < b + last; ++k) e0 += err[k];
    s.worst_end_nm = std::max(s.worst_end_nm, std::abs(e / last));
    s.start_nm.push_back(e0 / last);
    s.voltage_v.push_back(ax.voltage_v[t]);
    s.end_nm.push_back(e / last);
    ++s.holds;
  }
  return s;
}

}  // namespace

}  // namespace piezo
