// Holds: the runs of a data set where the voltage rests, found one way for every tool (the fits' hold weights,
// evaluation's creep metrics, the residual loop's validation). The rule is a parameter: how long a run must last
// and how still the voltage must be; the protocol's phase markers define the holds where the data carry them.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace piezo::io {

// The phase code of a hold in Dataset::phase (protocols::Phase::kHold).
inline constexpr int kHoldPhase = 1;

// What counts as a hold.
struct HoldRule {
  // From the voltage (data without phase markers, or use_phase false): a run whose every voltage lies within the
  // tolerance of its first, lasting at least min_duration_s (rows × the data's sample period) and min_rows rows.
  double min_duration_s = 60.0;
  std::size_t min_rows = 1;
  double tolerance_v = 1e-6;        // the tolerance, or tolerance_of_span × the voltage's span over the data
  double tolerance_of_span = 0.0;   // if that is larger (a read-back with a few LSB of noise still counts)
  bool skip_first_row = false;      // the run's first row is the step onto the voltage: left out of the hold
  // From the phase markers, where the data have them: the runs of phase == kHoldPhase (a new run also starts where
  // the segment changes) lasting at least min_marked_s.
  bool use_phase = true;
  double min_marked_s = 0.0;
};

struct HoldRun {
  std::size_t begin = 0, end = 0;  // rows [begin, end)
  int segment = -1;                // the segment of a marked run (-1: none)
};

// The holds of `axis` in data[from, end) under `rule`, in row order; none spans the start of a recording.
// Throws DataError when the axis is missing or the time column has no sample period.
std::vector<HoldRun> find_holds(const Dataset& data, const std::string& axis, const HoldRule& rule = {},
                                std::size_t from = 0);

// A row mask of `rows` rows: 1 inside a hold.
std::vector<char> hold_rows(std::size_t rows, const std::vector<HoldRun>& holds);

}  // namespace piezo::io
