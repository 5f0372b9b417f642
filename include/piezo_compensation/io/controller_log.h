// A controller log: what a host program polling the MM3E's controller writes, one row per set point, in the layout
// of the reference study's recordings (docs/data_formats.md, "Controller logs"):
//   finestep   the DAC set point in steps (fine mode: ±32768 steps ↔ ±80 V)
//   time       the host clock [s] when the set point was sent
//   <axis>_0…  the encoder reads after the set point, in counts (the counter may fall as the voltage rises)
//   temp       a thermocouple [°C] (optional; NaN cells and readout glitches happen)
//   <axis>_mean  the mean of the reads (optional; recomputed, never trusted)
// import_controller_log turns it into the package's Dataset: one reading per set point (the reads' mean), the
// temperature as the aux column temperature_c with every bad cell repaired and counted, and a report of it all.
#pragma once

#include <cstddef>
#include <string>

#include "piezo_compensation/io/dataset.h"

namespace piezo::io {

struct ControllerLogOptions {
  std::string axis = "c";
  double volts_per_step = 0.0;       // [V/step], e.g. 80/32768 for the MM3E's fine mode
  double nm_per_count = 0.0;         // [nm/count], signed: negative when the counter falls as the position rises
  double temperature_min_c = 0.0;    // a reading outside [min, max] is a readout glitch
  double temperature_max_c = 50.0;
  double temperature_max_step_c = 1.0;  // a jump from the last good reading larger than this is a glitch
  // With fewer good temperature cells than this fraction, the column is left out rather than mostly held.
  double temperature_min_good_fraction = 0.5;
};

struct ControllerLogReport {
  std::size_t rows_in = 0, rows_out = 0;
  std::size_t reads_per_row = 0;           // read columns <axis>_0…
  std::size_t read_cells_bad = 0;          // non-finite read cells, left out of their row's mean
  std::size_t rows_without_reading = 0;    // rows with no finite read: left out (the model steps over them)
  double read_sigma_nm = 0.0;              // pooled spread of the reads within a set point
  double mean_sigma_independent_nm = 0.0;  // read_sigma_nm / √(reads): a row's reading σ if the reads were independent
  // The rows' own scatter where the set point holds: RMS of successive differences / √2 (correlated reads show here).
  double mean_sigma_holds_nm = 0.0;
  std::size_t hold_pairs = 0;              // successive rows with the same set point, behind mean_sigma_holds_nm
  bool mean_column_checked = false;        // <axis>_mean was present and agreed with the reads (else an error)
  bool has_temperature = false;            // temp column present
  bool temperature_kept = false;           // written as temperature_c
  std::size_t temperature_nan = 0, temperature_out_of_range = 0, temperature_jumps = 0;
  std::size_t temperature_held = 0;        // bad cells replaced by the last good reading (the first good one at the start)
  double voltage_min_v = 0.0, voltage_max_v = 0.0;
};

// Throws DataError with file, row and column on: no such file, a missing column (finestep, time, <axis>_0), an
// unknown column, a non-numeric cell where a number is needed (a read cell may be NaN), a time that does not
// increase, a <axis>_mean that disagrees with the reads, options that are not finite or zero.
Dataset import_controller_log(const std::string& path, const ControllerLogOptions& options,
                              ControllerLogReport* report = nullptr);

}  // namespace piezo::io
