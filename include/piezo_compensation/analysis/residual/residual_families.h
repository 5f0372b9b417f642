// The effect families of the residual loop as one table: an enum, each family's traits (what kind of term it
// adds, what the acceptance policy must know about it) and its candidate generator. Every place that needs to
// know "is this a gain", "does this extrapolate in time" reads this table instead of comparing names.
#pragma once

#include <cstddef>
#include <optional>
#include <string>
#include <vector>

namespace piezo::analysis {

enum class Family {
  kTimeDrift,
  kCrossAxis,
  kPositionPeriodic,
  kRateDependent,
  kAuxSignal,
  kPeriodicDisturbance,
  kMissingMemory,
  kVoltageNonlinearity,
  kTimeGain,
  kCrossAxisGain,
  kAuxGain,
};

struct FamilyTraits {
  Family id;
  const char* name;
  // Scales the base output (or the voltage) by 1 + f(signal) instead of adding to it.
  bool gain = false;
  // For a gain: the additive family on the same signal, which it must beat (AcceptanceRule::kGainVsAdditive).
  std::optional<Family> additive;
  // A line in time: extrapolates without bound past TRAIN, so it must remove more of the slow error and may not
  // lose either validation half (see AcceptanceThresholds).
  bool line_in_time = false;
  // Regressors are functions of the operating point (voltage, position), not of a physical signal: flexible
  // enough to soak up any misfit that correlates with the motion, so they must win clearly over a physical one.
  bool operating_point = false;
  // Significance from the periodogram against a red-noise background, not from circular-shift draws.
  bool spectral = false;
  // Regressors are compared on the same signal as the additive counterpart (time_drift/time_gain have none).
  bool compares_signal = true;
  // A sensor effect: in the readings, not in the stage's motion. An error periodic in the position at a few
  // hundred nm is the encoder's interpolation error (a piezo stage's motion has no such period): it belongs to
  // the model of what the encoder reads, and the stage position (what the feedforward positions) leaves it out.
  bool in_readings = false;
};

// All families, in report order.
const std::vector<FamilyTraits>& family_table();
const FamilyTraits& traits(Family f);
// nullptr for an unknown name.
const FamilyTraits* find_family(const std::string& name);
// Throws std::invalid_argument("unknown effect family '…'") for an unknown name.
const FamilyTraits& traits_of(const std::string& name);

}  // namespace piezo::analysis
