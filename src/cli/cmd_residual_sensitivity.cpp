// `piezo residual-sensitivity`: how often the residual loop names a planted effect of a given size on simulated
// stages, and how often it adds anything to a stage without one; prints a markdown table.
#include <iostream>
#include <sstream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/analysis/residual/residual_sensitivity.h"

namespace piezo::cli {
namespace {

std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string x;
  while (std::getline(ss, x, ','))
    if (!x.empty()) out.push_back(x);
  return out;
}

int run_compare(const Args& args) {
  analysis::ComparisonOptions o;
  for (const auto& e : split_list(args.str("compare")))
    if (e != "none") o.effects.push_back(e);
  o.stage_path = args.str("stage");
  o.size_sigma = args.num("size");
  o.gain_lag_s = args.num("gain-lag-s");
  o.temperature_wander_c = args.num("temperature-wander-c");
  o.encoder_step_a_nm = args.num("step-a-nm");
  o.fused_other_axis = !args.flag("no-fused");
  o.hours = args.num("hours");
  o.seed = static_cast<std::uint64_t>(args.integer("seed"));
  o.base_kind = args.str("base");
  o.permutations = static_cast<int>(args.integer("permutations"));
  if (o.permutations < 10) throw UsageError("residual-sensitivity: --permutations must be ≥ 10");
  if (args.flag("verbose")) o.loop_log = [](const std::string& s) { std::cerr << "  " << s << "\n"; };
  analysis::ComparisonResult r;
  try {
    r = analysis::run_comparison(o);
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("residual-sensitivity: ") + e.what());
  }
  std::cout << analysis::comparison_text(r, o);
  return 0;
}

int run(int argc, char** argv) {
  Args args("residual-sensitivity",
            "Detection rate of the residual loop against the size of a planted effect (periodic encoder error,\n"
            "cross-axis coupling, an auxiliary signal, a stroke gain on it), in units of the reading noise σ, and\n"
            "its false-positive rate on stages without an effect. Simulated stages (default simulator, axes a and c\n"
            "on a random walk, a temperature_c column on every stage); the loop runs blind on each. Prints a\n"
            "markdown table.");
  args.option("families", "LIST", "periodic, cross_axis, aux_signal, gain", "periodic,cross_axis,aux_signal,gain")
      .option("sizes", "LIST", "effect sizes, RMS over σ", "0.25,0.5,1,1.5,2")
      .option("trials", "N", "stages per family and size", "5")
      .option("clean-trials", "N", "stages without an effect", "20")
      .option("hours", "H", "length of each stage", "6")
      .option("seed", "N", "first seed (trial t uses seed + t)", "1000")
      .option("base", "KIND", "base model kind fitted on each stage (auto: chosen per stage as `piezo residual --model auto`)", "auto")
      .option("permutations", "N", "circular-shift draws per family", "20")
      .option("compare", "LIST", "instead of the table: one stage with these effects (cross_axis, gain, periodic, "
              "slips; 'none' for a clean stage) against the same stage without them, the loop run on both")
      .option("stage", "FILE", "with --compare: a stage file (config/stages) for axis c; a gets c's physics", "")
      .option("size", "SIGMA", "with --compare: each effect's RMS over σ", "1.5")
      .option("gain-lag-s", "S", "with --compare: the stroke gain's first-order temperature lag", "90")
      .option("temperature-wander-c", "C", "with --compare: SD of a 400-s Gauss-Markov wander added to the room's temperature", "0")
      .option("step-a-nm", "NM", "with --compare: axis a's encoder step", "250")
      .option("no-fused", "", "with --compare: axis a enters through its readings and voltage, not its fused position")
      .option("quiet", "", "no line per trial on stderr")
      .option("verbose", "", "the loop's own progress lines on stderr");
  if (!args.parse(argc, argv)) return 0;
  if (args.has("compare")) return run_compare(args);
  analysis::SensitivityOptions o;
  o.families.clear();
  for (const auto& f : split_list(args.str("families"))) {
    try {
      o.families.push_back(analysis::parse_sensitivity_family(f));
    } catch (const std::invalid_argument& e) {
      throw UsageError(std::string("residual-sensitivity: ") + e.what());
    }
  }
  o.sizes_sigma.clear();
  for (const auto& s : split_list(args.str("sizes"))) {
    char* end = nullptr;
    const double v = std::strtod(s.c_str(), &end);
    if (end == s.c_str() || *end != '\0' || !(v > 0)) throw UsageError("residual-sensitivity: --sizes expects positive numbers, got '" + s + "'");
    o.sizes_sigma.push_back(v);
  }
  o.trials = static_cast<int>(args.integer("trials"));
  o.clean_trials = static_cast<int>(args.integer("clean-trials"));
  o.hours = args.num("hours");
  o.seed = static_cast<std::uint64_t>(args.integer("seed"));
  o.base_kind = args.str("base");
  o.permutations = static_cast<int>(args.integer("permutations"));
  if (o.trials < 0 || o.clean_trials < 0) throw UsageError("residual-sensitivity: --trials and --clean-trials must be ≥ 0");
  if (o.permutations < 10) throw UsageError("residual-sensitivity: --permutations must be ≥ 10");
  if (!(o.hours >= 0.5)) throw UsageError("residual-sensitivity: --hours must be ≥ 0.5");
  if (!args.flag("quiet")) o.progress = [](const std::string& s) { std::cerr << "residual-sensitivity: " << s << std::endl; };
  if (args.flag("verbose")) o.loop_log = [](const std::string& s) { std::cerr << "  " << s << "\n"; };
  const analysis::SensitivityResult r = analysis::run_sensitivity(o);
  std::cout << analysis::sensitivity_table(r, o);
  return 0;
}

const Register reg("residual-sensitivity", "detection rate of the residual loop against effect size, false positives", run);
}  // namespace
}  // namespace piezo::cli
