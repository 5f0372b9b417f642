// `piezo residual`: close the loop on measured data — find what the model misses, add it, report before/after.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <sstream>

#include "args.h"
#include "command.h"
#include "training_rows.h"
#include "plot_script.h"
#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/analysis/residual/residual_report.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/training/fit_plan.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/ros/data_file.h"

namespace fs = std::filesystem;

namespace piezo::cli {
namespace {

void declare_options(Args& args) {
  args.files("train", "FILE", "training data (CSV or bag); several files are separate recordings", false)
      .files("test", "FILE", "test data (CSV or bag); several files are separate recordings", false)
      .option("data", "FILE", "one data file split by time instead of --train/--test")
      .option("split", "FRACTION", "with --data: the first FRACTION is TRAIN", "0.7")
      .option("axis", "NAME", "axis to model", "c")
      .required("model", "KIND|FILE", "model kind to fit on TRAIN, auto (the documented path: the\n"
                "physical kinds reading only this axis's voltage, chosen on TRAIN's validation part as `piezo fit --model\n"
                "auto` chooses), or a model file")
      .option("set", "KEY=VALUE", "hyperparameter of the fitted kind", "", true)
      .option("mode", "MODE", "free-run or one-step", "free-run")
      .option("families", "LIST", "comma-separated effect families to consider (default all)")
      .option("validation", "FRACTION", "last part of TRAIN held out to check an effect generalises", "0.25")
      .option("alpha", "P", "significance level", "0.01")
      .option("min-gain", "FRACTION", "share of the validation systematic error (MSE − σ²) an effect must remove", "0.10")
      .option("max-effects", "N", "at most this many effects", "5")
      .option("permutations", "N", "circular-shift null draws per family", "40")
      .option("seed", "N", "random seed", "1")
      .option("anchor-s", "S", "the first S seconds of TEST's measurement fix the offset; TEST is scored after them", "0")
      .option("refit-base", "", "with a model file: refit its kind (default options) while backfitting")
      .option("mid-history", "", "TRAIN starts on a stage already in use (a ~snapshot): fit the decay of the base's "
              "unknown initial creep state alongside the effects (not put in the model)")
      .option("other-model", "AXIS=FILE", "another axis' model file (with its estimator block): that axis enters the "
              "cross-axis families through its fused position, not its raw readings; other axes without one get a "
              "model fitted on TRAIN", "", true)
      .option("other-readings", "", "other axes without --other-model enter through their readings and voltage "
              "(no model fitted for them)")
      .option("no-plots", "", "skip the PNGs")
      .required("out", "DIR", "output directory");
  allow_training_rows_option(args);
}

// TRAIN and TEST: --train/--test, or --data split by time.
void read_train_test(const Args& args, io::Dataset& train, io::Dataset& test) {
  if (args.has("data")) {
    if (args.has("train") || args.has("test")) throw UsageError("residual: give either --data or --train/--test");
    const io::Dataset all = ros_io::read_data(args.str("data"));
    const double f = args.num("split");
    if (!(f > 0.1 && f < 0.95)) throw UsageError("residual: --split must be in (0.1, 0.95)");
    const std::size_t cut = static_cast<std::size_t>(static_cast<double>(all.size()) * f);
    train = all.slice(0, cut);
    test = all.slice(cut, all.size());
    train.source = args.str("data") + " (TRAIN part)";
    test.source = args.str("data") + " (TEST part)";
  } else {
    if (!args.has("train") || !args.has("test")) throw UsageError("residual: give --train and --test (or --data)");
    train = ros_io::read_recordings(args.list("train"));
    test = ros_io::read_recordings(args.list("test"));
  }
  train.axis(args.str("axis"));  // clear error if missing
  test.axis(args.str("axis"));
}

analysis::ResidualOptions residual_options(const Args& args) {
  analysis::ResidualOptions o;
  o.axis = args.str("axis");
  o.mode = analysis::parse_prediction_mode(args.str("mode"));
  o.validation_fraction = args.num("validation");
  o.acceptance.alpha = args.num("alpha");
  o.acceptance.min_removed_fraction = args.num("min-gain");
  o.max_effects = static_cast<int>(args.integer("max-effects"));
  o.permutations = static_cast<int>(args.integer("permutations"));
  o.seed = static_cast<std::uint64_t>(args.integer("seed"));
  o.anchor_s = args.num("anchor-s");
  o.start_transients = args.flag("mid-history");
  if (!(o.anchor_s >= 0)) throw UsageError("residual: --anchor-s must be ≥ 0");
  if (o.permutations < 10) throw UsageError("residual: --permutations must be ≥ 10");
  if (args.has("families")) {
    std::stringstream ss(args.str("families"));
    std::string f;
    while (std::getline(ss, f, ','))
      if (!f.empty()) o.families.push_back(f);
  }
  o.log = [](const std::string& s) { std::cerr << "residual: " << s << "\n"; };
  return o;
}

// --other-model AXIS=FILE, repeatable: each other axis' model, checked to be that axis'.
std::map<std::string, std::shared_ptr<const models::Model>> other_axis_models(const std::vector<std::string>& specs) {
  std::map<std::string, std::shared_ptr<const models::Model>> out;
  for (const auto& spec : specs) {
    const auto eq = spec.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == spec.size())
      throw UsageError("residual: --other-model expects AXIS=FILE, got '" + spec + "'");
    const std::string other_axis = spec.substr(0, eq), file = spec.substr(eq + 1);
    if (out.count(other_axis)) throw UsageError("residual: --other-model given twice for axis " + other_axis);
    models::ModelPtr m = models::load_model(file);
    models::check_model_axis(*m, other_axis, file);
    out[other_axis] = std::move(m);
  }
  return out;
}

// Every other axis with readings in TRAIN and TEST enters the cross-axis families through its fused position: its
// --other-model file, or a model of `kind` fitted on TRAIN's fit part with its error filter identified on the rest
// (analysis::fit_axis_model). With --other-readings, or when --families leaves both cross-axis families out, only the
// files given: the others enter through their readings.
void add_other_axes(const Args& args, io::Dataset& train, io::Dataset& test, const std::string& axis, std::size_t n_fit,
                    const std::string& kind, const analysis::ResidualOptions& o) {
  auto models = other_axis_models(args.list("other-model"));
  const auto searched = [&o](const char* f) {
    return o.families.empty() || std::find(o.families.begin(), o.families.end(), f) != o.families.end();
  };
  // Only the cross-axis families read another axis: without them no model is fitted for it.
  if (!args.flag("other-readings") && (searched("cross_axis") || searched("cross_axis_gain")))
    for (const auto& ax : train.axes) {
      if (ax.name == axis || models.count(ax.name) || !test.has_axis(ax.name)) continue;
      o.log("axis " + ax.name + ": fitting " + kind + " on TRAIN's first part and its error filter on the rest, for "
            "its fused position (--other-readings: its readings instead)");
      try {
        models[ax.name] = analysis::fit_axis_model(train, n_fit, ax.name, kind, o.seed, true);
      } catch (const std::exception& e) {  // an axis that did not move, or too few rows: it keeps its readings
        o.log("axis " + ax.name + ": no model (" + e.what() + "); it enters through its readings");
      }
    }
  analysis::add_fused_positions(train, test, models, axis, o.warm_start, o.log);
}

// The base model and how it came about.
struct Base {
  models::ModelPtr model;
  std::string fitted_kind;   // auto: the chosen kind (refitted while backfitting); a kind: itself
  std::string selection_md;  // auto: the choice's table
  std::string choice;        // for the report
};

// The base: a model file, or the plan's kind (or auto's choice) fitted on TRAIN's first part (the rest validates it),
// refused when the data do not support it.
Base base_model(const Args& args, training::FitPlan& plan, const io::Dataset& test, std::uint64_t seed) {
  Base b;
  b.fitted_kind = plan.kind;
  if (plan.kind == "auto") {
    analysis::ModelCandidate chosen;
    b.model = analysis::fit_auto(plan.all, plan.split_at, plan.axis, seed, &chosen, &b.selection_md);
    std::cerr << "residual: model choice\n" << b.selection_md;
    b.fitted_kind = chosen.kind;
    if (chosen.options) plan.options = chosen.options;
    b.choice = "auto: chose " + b.fitted_kind + " on TRAIN's first part (table in model_choice.md)";
  } else if (fs::exists(plan.kind)) {
    b.model = models::load_model(plan.kind);
    if (b.model->kind() == "augmented")
      throw UsageError("residual: " + plan.kind + " is already augmented; start from its base model");
    models::check_model_matches_data(*b.model, plan.all, args.has("data") ? args.str("data") : plan.all.source_or_data());
    check_training_rows(args, "residual", b.model->meta, test, plan.axis, plan.kind, "TEST ");
    b.choice = "model file " + plan.kind;
  } else {
    if (!training::fitter(plan.kind)) throw UsageError("residual: model kind '" + plan.kind + "' cannot be fitted on its own");
    training::FitRequest req = plan.request();
    req.seed = seed;
    std::cerr << "residual: fitting " << plan.kind << " on " << plan.train.size() << " TRAIN rows\n";
    b.model = training::fit_model(plan.kind, req);
    b.choice = "fitted " + plan.kind + " on TRAIN's first part";
  }
  const analysis::ValidationScore score = analysis::score_validation(*b.model, plan.all, plan.split_at, plan.axis);
  analysis::check_fit_sanity(*b.model, &score, analysis::data_scale(plan.train, plan.axis));
  return b;
}

// Backfitting: the base is refitted with the same kind and options after each added effect. A loaded model file
// keeps its weights unless --refit-base asks to refit its kind with default options.
void set_refit(const Args& args, const training::FitPlan& plan, const Base& base, analysis::ResidualOptions& o) {
  const bool file = fs::exists(plan.kind);
  const std::string kind = file ? (args.flag("refit-base") ? base.model->kind() : "") : base.fitted_kind;
  if (kind.empty()) return;
  if (!training::fitter(kind)) throw UsageError("residual: kind '" + kind + "' cannot be refitted");
  const YAML::Node options = file ? YAML::Node(YAML::NodeType::Map) : plan.options;
  const std::string axis = plan.axis;
  const std::uint64_t seed = o.seed;
  o.refit_base = [kind, options, axis, seed](const io::Dataset& fit_part, const io::Dataset& val_part,
                                             const models::Model& previous, bool same_structure) {
    training::FitRequest r;
    r.train = &fit_part;
    r.validation = &val_part;
    r.axis = axis;
    r.options = training::refit_options(previous, options, same_structure);
    r.seed = seed;
    return training::fit_model(kind, r);
  };
}

void write_outputs(const Args& args, const Base& base, const analysis::ResidualResult& res, const io::Dataset& train,
                   const io::Dataset& test, const analysis::ResidualOptions& o) {
  const fs::path out = args.str("out");
  fs::create_directories(out);
  training::stamp_origin(*res.model, train, "");  // a simulated stage's terms are the simulator's
  if (!base.selection_md.empty()) std::ofstream(out / "model_choice.md") << "# Base model choice\n\n" << base.selection_md;
  analysis::ResidualReportContext ctx;
  ctx.axis = o.axis;
  ctx.mode = args.str("mode");
  ctx.base_kind = base.model->kind();
  ctx.base_choice = base.choice;
  analysis::write_residual_report(out.string(), ctx, res, train, test, o.mode);
  std::cout << "residual: " << analysis::residual_summary(res) << "\n";
  if (!args.flag("no-plots")) run_plot_script("residual", "residual_plots.py", {out.string()});
  std::cout << "residual: wrote " << (out / "report.md").string() << "\n";
}

int run(int argc, char** argv) {
  Args args("residual",
            "Close the loop: fit (or load) a model on TRAIN, trace its residual to effect families (time_drift,\n"
            "cross_axis, position_periodic, rate_dependent, aux_signal, periodic_disturbance, missing_memory,\n"
            "voltage_nonlinearity) ranked by cross-validated explained variance with a significance test, add the\n"
            "best significant one, refit, repeat; report TEST error before/after. Gain families (time_gain,\n"
            "cross_axis_gain, aux_gain) scale the motion instead of adding to it. Writes report.md, report.json,\n"
            "predictions.csv, model.yaml (kind augmented) and PNGs to --out.");
  declare_options(args);
  if (!args.parse(argc, argv)) return 0;
  io::Dataset train, test;
  read_train_test(args, train, test);
  analysis::ResidualOptions o = residual_options(args);
  training::FitPlan plan;
  plan.axis = o.axis;
  plan.kind = args.str("model");
  try {
    plan.options = training::plan_options("", args.list("set"));
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("residual: --") + e.what());
  }
  const std::size_t n_fit = static_cast<std::size_t>(std::lround(static_cast<double>(train.size()) * (1.0 - o.validation_fraction)));
  const bool kind_given = plan.kind != "auto" && !fs::exists(plan.kind) && training::fitter(plan.kind);
  add_other_axes(args, train, test, o.axis, n_fit, kind_given ? plan.kind : "pi_creep_lti", o);
  training::split_at_row(plan, train, n_fit);
  const Base base = base_model(args, plan, test, o.seed);
  set_refit(args, plan, base, o);
  const analysis::ResidualResult res = analysis::trace_residual(*base.model, train, test, o);
  write_outputs(args, base, res, train, test, o);
  return 0;
}

const Register reg("residual", "trace the residual to effects the model lacks, add them, report before/after", run);
}  // namespace
}  // namespace piezo::cli
