// `piezo bench [NAME...]`: runs the benchmark and measurement programs built into <devel>/lib/piezo_compensation/bench
// and prints their figures. Speed targets are shown here, never asserted in timed tests.
#include <algorithm>
#include <unistd.h>  // access(), X_OK

#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "args.h"
#include "command.h"
#include "piezo_compensation/util/child_process.h"

namespace fs = std::filesystem;

namespace piezo::cli {
namespace {

fs::path bench_dir() {
  // The CLI lives in <devel>/lib/piezo_compensation/; benchmarks in its bench/ subfolder.
  std::error_code ec;
  fs::path self = fs::read_symlink("/proc/self/exe", ec);
  return self.parent_path() / "bench";
}

int run(int argc, char** argv) {
  Args args("bench", "Run the Google Benchmark targets and measurement tools and print their figures.\n"
                     "NAME selects programs whose name contains it (e.g. `piezo bench simulator`).");
  args.option("list", "", "list the available programs and exit");
  args.option("min-time", "S", "minimum time per benchmark [s] (Google Benchmark --benchmark_min_time)", "0.5");
  args.option("soak", "MINUTES",
              "run only the soak test for MINUTES: 3 simulated manipulators through driver + predictor at 1 kHz per "
              "axis (docs/driver.md)", "");
  args.option("soak-window", "MINUTES", "soak: report window", "10");
  if (!args.parse(argc, argv)) return 0;
  const fs::path dir = bench_dir();
  std::vector<fs::path> programs;
  if (fs::is_directory(dir))
    for (const auto& e : fs::directory_iterator(dir))
      if (e.is_regular_file() && access(e.path().c_str(), X_OK) == 0) programs.push_back(e.path());
  std::sort(programs.begin(), programs.end());
  if (programs.empty()) {
    std::cerr << "bench: no benchmark programs in " << dir << " (build first: scripts/build)\n";
    return 1;
  }
  if (args.flag("list")) {
    for (const auto& p : programs) std::cout << p.filename().string() << "\n";
    return 0;
  }
  if (!args.str("soak").empty()) {
    const fs::path soak = dir / "can_soak";
    const util::ChildResult r =
        util::run_process({soak.string(), "--minutes", args.str("soak"), "--window-minutes", args.str("soak-window")});
    if (!r.ok()) std::cerr << "bench: can_soak failed (" << r.error << ")\n";
    return r.ok() ? 0 : 1;
  }
  int failures = 0;
  for (const auto& p : programs) {
    const std::string name = p.filename().string();
    bool selected = args.positional().empty() && name != "can_soak";  // the soak runs for minutes: --soak
    for (const auto& want : args.positional()) selected |= name.find(want) != std::string::npos;
    if (!selected) continue;
    std::cout << "=== " << name << " ===" << std::endl;
    std::vector<std::string> argv{p.string()};
    if (name.rfind("bench_", 0) == 0) argv.push_back("--benchmark_min_time=" + args.str("min-time"));
    const util::ChildResult r = util::run_process(argv);
    if (!r.ok()) {
      std::cerr << "bench: " << name << " failed (" << r.error << ")\n";
      ++failures;
    }
  }
  return failures == 0 ? 0 : 1;
}

const Register reg("bench", "run the benchmarks and measurement tools, print their figures", run);
}  // namespace
}  // namespace piezo::cli
