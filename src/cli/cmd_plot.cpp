// `piezo plot BAG --out DIR`: PNG time series of a bag (positions, voltages, predicted drift per axis) by
// scripts/plotting/bag_plots.py, since rqt_plot is not packaged in Debian.
#include <cstdlib>
#include <filesystem>
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/util/child_process.h"
#include "plot_script.h"

namespace piezo::cli {
namespace {

int run(int argc, char** argv) {
  Args args("plot", "Write PNG time series of a bag: per axis the measured, true, predicted and intended positions,\n"
                    "the applied, commanded and corrected voltages and the predicted drift.");
  args.required("out", "DIR", "output directory for the PNG files");
  if (!args.parse(argc, argv)) return 0;
  if (args.positional().size() != 1) throw UsageError("plot: give exactly one bag");
  const std::string bag = args.positional()[0];
  if (!std::filesystem::exists(bag)) throw UsageError("plot: " + bag + ": no such file");
  std::filesystem::path script;
  try {
    script = find_plot_script("bag_plots.py");
  } catch (const std::exception& e) {
    throw UsageError(std::string("plot: ") + e.what());
  }
  const util::ChildResult r = util::run_process({"/usr/bin/python3", script.string(), bag, "--out", args.str("out")});
  if (!r.ok()) std::cerr << "plot: " << r.error << "\n";
  return r.ok() ? 0 : (r.exit_code > 0 ? r.exit_code : 1);
}

const Register reg("plot", "PNG time series (positions, voltages, drift) from a bag", run);

}  // namespace
}  // namespace piezo::cli
