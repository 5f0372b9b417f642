// Simulated data written as a controller log (io/controller_log.h): what a host program polling the MM3E's
// controller records, with the faults real logs carry — a host clock's jitter, late rows and a gap, a counter reset
// at an unknown position, several independent reads per set point, NaN read cells, a row without a read, and a
// thermocouple with NaN cells and readout glitches. The tests and `piezo simulate --controller-log` use it; no real
// log is ever copied into the package.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "piezo_compensation/io/dataset.h"

namespace piezo::sim {

struct ControllerLogSpec {
  std::string axis = "c";
  double volts_per_step = 80.0 / 32768.0;  // [V/step]
  double nm_per_count = -20.0;             // [nm/count]; negative: the counter falls as the position rises
  int reads = 5;                           // encoder reads per set point
  double read_noise_nm = 21.0;             // σ of each read before the counter's quantisation
  double zero_nm = 0.0;                    // the true position at which the counter was reset
  double jitter_s = 0.007;                 // σ of the host clock's step jitter
  double late_fraction = 0.002;            // share of steps one host cycle late
  double gap_at_s = -1.0;                  // one gap in the timestamps after this time (< 0: none)
  double gap_s = 1.78;
  double temperature_c = 22.3;             // used when the data carry no temperature_c
  double temperature_nan_fraction = 0.02;  // share of NaN temperature cells
  double temperature_glitch_fraction = 0.01;  // share of readout glitches (−1 °C, or 75–81 °C)
  double read_nan_fraction = 0.001;        // share of NaN read cells
  std::size_t row_without_reads = 0;       // a row whose reads are all NaN (0: none)
};

// What was written, to check an import against.
struct ControllerLogFaults {
  std::size_t rows = 0, late_steps = 0, read_cells_nan = 0, temperature_nan = 0, temperature_glitches = 0;
  bool gap = false;
};

// `data` must have the axis with its true position (simulated data). Throws io::DataError on a missing axis or
// truth, std::runtime_error when the file cannot be written.
ControllerLogFaults write_controller_log(const std::string& path, const io::Dataset& data, const ControllerLogSpec& spec,
                                         std::uint64_t seed);

}  // namespace piezo::sim
