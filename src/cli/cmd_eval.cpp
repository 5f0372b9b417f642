// `piezo eval`: several model files on test (and creep) data → report.md, report.json and PNG plots.
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <set>

#include "args.h"
#include "command.h"
#include "training_rows.h"
#include "plot_script.h"
#include "piezo_compensation/analysis/evaluation/eval_report.h"
#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/util/progress_bar.h"

namespace piezo::cli {
namespace {
namespace fs = std::filesystem;

// The scoring options, in the report's context and the evaluation's alike.
void read_options(const Args& args, analysis::EvalContext& ctx, analysis::EvalOptions& eo) {
  for (const auto& f : args.list("data")) ctx.test_path += (ctx.test_path.empty() ? "" : " ") + f;
  for (const auto& f : args.list("creep")) ctx.creep_path += (ctx.creep_path.empty() ? "" : " ") + f;
  ctx.warmup_s = args.seconds("warmup-s");
  ctx.anchor_s = args.seconds("anchor-s");
  if (!(ctx.anchor_s >= 0)) throw UsageError("eval: --anchor-s must be ≥ 0");
  eo.warmup_s = ctx.warmup_s;
  eo.anchor_s = ctx.anchor_s;
  ctx.anchor_history = eo.anchor_history = !args.flag("anchor-offset-only");
  try {
    if (args.has("test-segments")) eo.test_segments = analysis::parse_segments(args.str("test-segments"));
    if (args.has("creep-segments")) eo.creep_segments = analysis::parse_segments(args.str("creep-segments"));
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("eval: ") + e.what());
  }
  ctx.test_segments = eo.test_segments;
  ctx.zero_window_s = eo.zero_window_s = args.seconds("zero-before-hold-s");
  ctx.walk_end_s = eo.walk_end_s = args.seconds("walk-end-s");
  if (!(eo.zero_window_s >= 0) || !(eo.walk_end_s > 0)) throw UsageError("eval: --zero-before-hold-s must be >= 0, --walk-end-s > 0");
  ctx.creep_segments = eo.creep_segments;
}

int run(int argc, char** argv) {
  Args args("eval", "Evaluate model files on test data (hysteresis: samples outside holds) and creep data (samples in\n"
                    "holds), one-step and free-run, against the measurement and (simulated data) the true position.\n"
                    "usage: piezo eval --models m1.yaml m2.yaml ... --data TEST [--creep CREEP] --out DIR");
  args.option("models", "FILE.yaml", "model files (more may follow as plain arguments)", "", true)
      .files("data", "FILE", "test data (CSV or bag); several files are separate recordings, each from its own start", true)
      .files("creep", "FILE", "creep data with holds (else the holds in --data; without a phase column a hold is the\n"
             "voltage unchanged for at least 60 s)", false)
      .option("axis", "a|b|c", "axis (default: the models' axis)")
      .option("noise-sigma-nm", "NM", "encoder noise σ for the floor and the Fig. 14 band (default: estimated from the\n"
              "test data's holds, analysis/evaluation/noise_floor.h)")
      .option("warmup-s", "T", "do not score the first T of the test data (seconds, or 30s, 10min)", "0")
      .option("anchor-s", "T", "the first T of measured position fix each model's start state and offset (docs/models.md,\n"
              "\"Start-up state estimate\"); scored after them", "0")
      .option("anchor-offset-only", "", "with --anchor-s: fix the offset only, the model starting at rest")
      .option("test-segments", "LIST", "score only these segments for hysteresis (e.g. 2); the model still runs over all")
      .option("creep-segments", "LIST", "score only the holds of these segments for creep (e.g. 3-17)")
      .option("zero-before-hold-s", "T", "score each test recording's first hold from a zero taken over the T before it\n"
              "(its walk's MAE over --walk-end-s before the hold, and the hold's creep); 0 = off", "0")
      .option("walk-end-s", "T", "with --zero-before-hold-s: the walk scored over this long before the hold", "900")
      .option("no-plots", "", "skip the PNG plots")
      .required("out", "DIR", "output directory");
  allow_training_rows_option(args);
  if (!args.parse(argc, argv)) return 0;
  std::vector<std::string> paths = args.list("models");
  for (const auto& p : args.positional()) paths.push_back(p);
  if (paths.empty()) throw UsageError("eval: give at least one model file (--models m1.yaml ...)");

  std::vector<std::string> notes;
  const io::Dataset test = ros_io::read_recordings(args.list("data"), &notes);
  io::Dataset creep;
  if (args.has("creep")) creep = ros_io::read_recordings(args.list("creep"), &notes);
  for (const auto& n : notes) std::cerr << "note: " << n << "\n";
  const fs::path out = args.str("out");
  fs::create_directories(out);

  analysis::EvalContext ctx;
  analysis::EvalOptions eo;
  read_options(args, ctx, eo);

  std::vector<models::ModelPtr> ms;
  for (const auto& p : paths) {
    ms.push_back(models::load_model(p));
    const std::string axis = args.has("axis") ? args.str("axis") : ms.back()->meta.axis;
    if (ms.size() == 1) ctx.axis = axis;
    if (axis != ctx.axis) throw UsageError("eval: models are for different axes; pass --axis");
    analysis::check_model_for_eval(*ms.back(), p, axis, test, creep.empty() ? nullptr : &creep);
    check_training_rows(args, "eval", ms.back()->meta, test, axis, p);
    check_training_rows(args, "eval", ms.back()->meta, creep, axis, p);
  }
  eo.axis = ctx.axis;
  const io::AxisSeries& ax = test.axis(ctx.axis);
  const analysis::NoiseFloor noise = args.has("noise-sigma-nm")
                                         ? analysis::noise_floor_from_sigma(args.num("noise-sigma-nm"))
                                         : analysis::estimate_noise_floor(test, ctx.axis);
  ctx.noise_sigma_nm = noise.sigma_nm;
  std::cout << "noise floor: " << noise.describe() << "\n";
  if (ax.has_truth()) ctx.measured_sigma_nm = analysis::noise_sigma_nm(ax.position_nm, ax.true_position_nm);

  util::ProgressBar bar(std::cerr, "models");
  std::vector<analysis::ModelEvaluation> evals;
  std::set<std::string> names;
  for (std::size_t k = 0; k < ms.size(); ++k) {
    std::string name = fs::path(paths[k]).stem().string();
    while (names.count(name)) name += "_";
    names.insert(name);
    bar.update(double(k), double(ms.size()), "evaluating");
    evals.push_back(analysis::evaluate_model(*ms[k], name, test, creep.empty() ? nullptr : &creep, eo));
  }
  bar.update(double(ms.size()), double(ms.size()), "evaluating");
  bar.finish();
  analysis::write_eval_report(out.string(), ctx, evals, test, creep.empty() ? nullptr : &creep);
  std::cout << analysis::eval_markdown(ctx, evals).substr(0, std::string::npos);
  // The errors `piezo fit --model auto` chooses by, on the test recordings (each run free from its own rest).
  std::vector<std::pair<std::string, const models::Model*>> named;
  for (std::size_t k = 0; k < ms.size(); ++k) named.emplace_back(fs::path(paths[k]).stem().string(), ms[k].get());
  const std::string use = analysis::use_error_table(named, test, ctx.axis);
  std::cout << "\n## Moves and hold creep (free run from each recording's rest, 5-s means, no zero needed)\n\n" << use;
  std::ofstream((out / "use_errors.md").string()) << use;
  if (!args.flag("no-plots")) run_plot_script("eval", "eval_plots.py", {out.string()});
  std::cout << "\nwrote " << (out / "report.md").string() << ", report.json and plots\n";
  return 0;
}

const Register reg("eval", "evaluate model files: Table 3, final positions, traces (report.md/json + PNG)", run);

}  // namespace
}  // namespace piezo::cli
