// The "ideal piezo" the operator thinks in: position proportional to voltage, no hysteresis, no creep.
// Defined from the model itself: the straight line through the model's positions after a long hold at the two
// voltage limits, each reached from rest at 0 V / 0 nm (see docs/predictor.md).
#pragma once

#include <string>

#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

struct IdealLine {
  double gain_nm_per_v = 0.0;
  double offset_nm = 0.0;        // ideal position at 0 V

  double position_nm(double voltage_v) const { return offset_nm + gain_nm_per_v * voltage_v; }
  double voltage_v(double position_nm) const { return (position_nm - offset_nm) / gain_nm_per_v; }
};

struct IdealLineOptions {
  double voltage_min_v = -80.0;
  double voltage_max_v = 80.0;
  double ramp_s = 10.0;          // linear ramp from 0 V to each limit
  double hold_s = 1800.0;        // hold at the limit before reading the position (creep settled)
  double sample_rate_hz = 11.0;
};

// Throws std::runtime_error (one line) when the model gives non-finite positions or a zero/negative-span line.
IdealLine ideal_line_from_model(const models::Model& model, const IdealLineOptions& options);

}  // namespace piezo::compensation
