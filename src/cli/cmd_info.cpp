// `piezo info FILE`: what a data file holds (columns, rate, duration) — also a quick validity check.
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/ros/data_file.h"

namespace piezo::cli {
namespace {
int run(int argc, char** argv) {
  Args args("info", "Print the columns, sample rate and duration of a data file (CSV or bag); fails with one\n"
                    "clear line naming file, row and column if the file is malformed.");
  if (!args.parse(argc, argv)) return 0;
  if (args.positional().empty()) throw UsageError("info: give a data file");
  for (const auto& path : args.positional()) {
    const io::Dataset d = ros_io::read_data(path);
    std::cout << path << ": " << d.size() << " samples, " << d.sample_rate_hz() << " Hz, "
              << (d.time_s.back() - d.time_s.front()) << " s\n  axes:";
    for (const auto& a : d.axes) std::cout << " " << a.name << (a.has_truth() ? " (with truth)" : "");
    std::cout << "\n  aux:";
    for (const auto& x : d.aux) std::cout << " " << x.name;
    if (d.aux.empty()) std::cout << " none";
    std::cout << "\n";
  }
  return 0;
}
const Register reg("info", "columns, sample rate and duration of a data file", run);
}  // namespace
}  // namespace piezo::cli
