// `piezo info FILE…`: what a data file holds (columns, rate, duration, how its rows sit in time) — also a quick
// validity check.
#include <iostream>
#include <sstream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/util/format.h"

namespace piezo::cli {
namespace {
// One line on the time column: a sample clock, or a host clock's jitter, late rows and the time a model steps over.
std::string describe_time(const io::Dataset& d) {
  const io::TimeBase tb = io::time_base(d.time_s);
  std::ostringstream os;
  if (tb.constant) {
    os << "a sample clock (every step within 1 % of " << util::fmt(tb.period_s, 6) << " s)";
    return os.str();
  }
  const double span_s = d.time_s.back() - d.time_s.front();
  os << "a host clock: median step " << util::fmt(tb.period_s, 4) << " s (the model's step), mean "
     << util::fmt(tb.mean_step_s, 4) << " s, jitter " << util::fmt(1e3 * tb.jitter_s, 2) << " ms RMS; " << tb.late_steps
     << " late step(s) over " << io::kLateStepFactor << " × the median, the longest " << util::fmt(tb.longest_step_s, 3)
     << " s after t = " << util::fmt(d.time_s[tb.longest_row - 1], 6) << " s (row " << tb.longest_row + 2
     << "); a model stepping once per row at the median step falls " << util::fmt(tb.clock_lag_s, 3) << " s behind ("
     << util::fmt(100.0 * tb.clock_lag_s / span_s, 2) << " % of the recording), " << util::fmt(tb.late_s, 3)
     << " s of it in the late steps";
  return os.str();
}

int run(int argc, char** argv) {
  Args args("info", "Print the columns, sample rate, duration and time base of a data file (CSV or bag); fails with\n"
                    "one clear line naming file, row and column if the file is malformed.");
  if (!args.parse(argc, argv)) return 0;
  if (args.positional().empty()) throw UsageError("info: give a data file");
  for (const auto& path : args.positional()) {
    std::vector<std::string> notes;
    const io::Dataset d = ros_io::read_data(path, &notes);
    std::cout << path << ": " << d.size() << " samples, " << d.sample_rate_hz() << " Hz, "
              << (d.time_s.back() - d.time_s.front()) << " s\n  time: " << describe_time(d) << "\n  axes:";
    for (const auto& a : d.axes) std::cout << " " << a.name << (a.has_truth() ? " (with truth)" : "");
    std::cout << "\n  aux:";
    for (const auto& x : d.aux) std::cout << " " << x.name;
    if (d.aux.empty()) std::cout << " none";
    std::cout << "\n";
    for (const auto& n : notes) std::cout << "  " << n << "\n";
  }
  return 0;
}
const Register reg("info", "columns, sample rate, duration and time base of a data file", run);
}  // namespace
}  // namespace piezo::cli
