// `piezo plot BAG --out DIR`: PNG time series of a bag (positions, voltages, predicted drift per axis) by
// scripts/plotting/bag_plots.py, since rqt_plot is not packaged in Debian.
#include <sys/wait.h>

#include <cstdlib>
#include <filesystem>
#include <iostream>

#include "args.h"
#include "command.h"

namespace piezo::cli {
namespace {

std::string quote(const std::string& s) {
  std::string q = "'";
  for (char c : s) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

int run(int argc, char** argv) {
  Args args("plot", "Write PNG time series of a bag: per axis the measured, true, predicted and intended positions,\n"
                    "the applied, commanded and corrected voltages and the predicted drift.");
  args.required("out", "DIR", "output directory for the PNG files");
  if (!args.parse(argc, argv)) return 0;
  if (args.positional().size() != 1) throw UsageError("plot: give exactly one bag");
  const std::string bag = args.positional()[0];
  if (!std::filesystem::exists(bag)) throw UsageError("plot: " + bag + ": no such file");
  const char* src = std::getenv("PIEZO_SOURCE_DIR");
  const std::filesystem::path script =
      std::filesystem::path(src ? src : PIEZO_SOURCE_DIR_FALLBACK) / "scripts" / "plotting" / "bag_plots.py";
  if (!std::filesystem::exists(script)) throw UsageError("plot: " + script.string() + " not found (set PIEZO_SOURCE_DIR)");
  const std::string cmd = "/usr/bin/python3 " + quote(script.string()) + " " + quote(bag) + " --out " + quote(args.str("out"));
  const int rc = std::system(cmd.c_str());
  return WIFEXITED(rc) ? WEXITSTATUS(rc) : 1;
}

const Register reg("plot", "PNG time series (positions, voltages, drift) from a bag", run);

}  // namespace
}  // namespace piezo::cli
