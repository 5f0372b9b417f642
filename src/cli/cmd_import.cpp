// `piezo import LOG… --volts-per-step V --nm-per-count NM --out OUT.csv`: controller logs (one row per set point,
// several encoder reads, a host clock, a glitching thermocouple) into the package's CSV (io/controller_log.h).
#include <filesystem>
#include <iostream>
#include <sstream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/io/controller_log.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/util/format.h"

namespace piezo::cli {
namespace {
namespace fs = std::filesystem;

// Lines for the user: the reads, each repair with its count, what was left out.
std::string describe(const io::ControllerLogReport& r) {
  std::ostringstream os;
  os << r.rows_in << " rows, " << r.reads_per_row << " reads each: one reading per set point, their mean ("
     << r.rows_out << " rows written)\n";
  os << "reads: σ " << util::fmt(r.read_sigma_nm, 3) << " nm within a held set point -> "
     << util::fmt(r.mean_sigma_independent_nm, 3) << " nm for their mean if independent; the means' own scatter where the "
     << "set point holds: " << util::fmt(r.mean_sigma_holds_nm, 3) << " nm (" << r.hold_pairs << " pairs)\n";
  if (r.read_cells_bad) os << "read cells: " << r.read_cells_bad << " not a number, left out of their row's mean\n";
  if (r.rows_without_reading)
    os << "rows: " << r.rows_without_reading << " without a finite read, left out (a model steps over them)\n";
  os << "voltage: " << util::fmt(r.voltage_min_v, 5) << " .. " << util::fmt(r.voltage_max_v, 5) << " V\n";
  if (!r.has_temperature) {
    os << "temperature: no temp column\n";
    return os.str();
  }
  os << "temperature: " << r.temperature_nan << " NaN cells, " << r.temperature_out_of_range << " outside the range, "
     << r.temperature_jumps << " jumps no thermal mass allows; ";
  if (r.temperature_kept)
    os << r.temperature_held << " cells hold the last good reading; written as temperature_c\n";
  else
    os << "too few good cells: the column is left out\n";
  return os.str();
}


int run(int argc, char** argv) {
  Args args("import",
            "Convert controller logs (columns finestep, time, <axis>_0…, optional temp and <axis>_mean: one row per set\n"
            "point) into the package's data format. The reads of a set point become one reading, their mean; temp becomes\n"
            "the aux column temperature_c with NaN cells and readout glitches replaced by the last good reading and\n"
            "counted (left out when fewer than half are good). The host clock's timestamps are kept as they are: every\n"
            "tool steps a model once per row (docs/data_formats.md, \"Time\").");
  args.option("axis", "NAME", "the axis whose reads the log holds", "c")
      .required("volts-per-step", "V", "volts per DAC step (MM3E fine mode: 80/32768 = 0.00244140625)")
      .required("nm-per-count", "NM", "nanometres per encoder count, signed: negative when the counter falls as the\n"
                                      "position rises (the study's MM3E axis c: -20)")
      .option("out", "FILE", "output file (.csv or .bag) for one log")
      .option("out-dir", "DIR", "output directory for several logs: DIR/<log name>.csv")
      .option("temperature-min-c", "C", "a temperature below this is a readout glitch", "0")
      .option("temperature-max-c", "C", "a temperature above this is a readout glitch", "50")
      .option("temperature-max-step-c", "C", "a jump larger than this from the last good reading is a glitch", "1");
  if (!args.parse(argc, argv)) return 0;
  const auto& logs = args.positional();
  if (logs.empty()) throw UsageError("import: give a controller log");
  if (args.has("out") == args.has("out-dir")) throw UsageError("import: give --out FILE (one log) or --out-dir DIR");
  if (args.has("out") && logs.size() != 1) throw UsageError("import: --out takes one log; use --out-dir DIR for several");
  io::ControllerLogOptions o;
  o.axis = args.str("axis");
  o.volts_per_step = args.num("volts-per-step");
  o.nm_per_count = args.num("nm-per-count");
  o.temperature_min_c = args.num("temperature-min-c");
  o.temperature_max_c = args.num("temperature-max-c");
  o.temperature_max_step_c = args.num("temperature-max-step-c");
  if (!(o.temperature_min_c < o.temperature_max_c))
    throw UsageError("import: --temperature-min-c must be below --temperature-max-c");
  if (!(o.temperature_max_step_c > 0)) throw UsageError("import: --temperature-max-step-c must be > 0");
  if (args.has("out-dir")) fs::create_directories(args.str("out-dir"));
  for (const auto& log : logs) {
    io::ControllerLogReport report;
    const io::Dataset d = io::import_controller_log(log, o, &report);
    const std::string out =
        args.has("out") ? args.str("out") : (fs::path(args.str("out-dir")) / fs::path(log).stem()).string() + ".csv";
    ros_io::write_data(out, d);
    std::cout << log << " -> " << out << "\n";
    std::string text = describe(report);
    for (std::size_t p = 0, e; p < text.size(); p = e + 1) {
      e = text.find('\n', p);
      std::cout << "  " << text.substr(p, e - p) << "\n";
      if (e == std::string::npos) break;
    }
  }
  return 0;
}
const Register reg("import", "controller logs (set points, reads, host clock) into the package's data format", run);
}  // namespace
}  // namespace piezo::cli
