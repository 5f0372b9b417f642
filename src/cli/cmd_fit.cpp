// `piezo fit`: fits any registered model kind on a data file and writes the model file.
#include <fstream>
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fit_plan.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/util/progress_bar.h"

namespace piezo::cli {
namespace {

void declare_options(Args& args) {
  args.files("data", "FILE", "training data (CSV or bag); several files are separate recordings, each with its own\n"
             "history and zero (docs/data_formats.md, \"Several recordings\")", true)
      .files("validation", "FILE", "separate validation data (else --split is used)", false)
      .option("split", "FRACTION", "training fraction of --data when no --validation is given (several recordings:\n"
              "the fraction of the recordings, the last ones held out whole)", "0.8")
      .option("axis", "a|b|c", "axis to model", "c")
      .required("model", "KIND", "model kind, or auto: every invertible physical kind (PI and Preisach, with and\n"
                "without creep, each as fitted and with the output map), run free on the held-out part and scored on\n"
                "the errors of the predicted 10-s and 60-s changes of the moves and of the creep in each hold from its\n"
                "start; the fewest parameters within the noise of the best; the table and the reason are printed and stored")
      .option("auto-extra", "KIND", "with --model auto: also try this kind (linear on lasso features, dense, lstm, kan;\n"
              "they may read other columns: not for a residual loop's base)", "", true)
      .option("features", "SET", "study | candidates | physics | voltage_history | lasso (lasso on the candidates, λ_1se survivors) | voltage_lasso (the same among the candidates that read no position; the neural kinds' default)")
      .option("tune", "N", "hyperparameter search with N trials (kinds that support it)", "0")
      .option("time-budget-s", "T", "stop tuning/training after T (seconds, or 90min, 2h; 0 = none)", "0")
      .option("set", "KEY=VALUE", "kind option (YAML value, e.g. method=lasso, thresholds_v=[0,10,20])", "", true)
      .option("options", "FILE.yaml", "kind options from a YAML mapping (--set overrides)")
      .option("seed", "N", "random seed", "1")
      .option("threads", "N", "threads", "2")
      .option("lasso-report", "FILE.md", "write the lasso selection report here (with --features lasso)")
      .option("no-identification", "", "skip the identification check of a single kind (with validation data: the kind\n"
              "fitted again on the training part's first half, its error on the second half against the validation's;\n"
              "over 2x the recording does not identify it)")
      .option("quiet", "", "no progress bar")
      .required("out", "FILE.yaml", "model file to write");
}

// The plan of the command line: the data read and split, the kind and its options.
training::FitPlan read_plan(const Args& args) {
  training::FitPlan plan;
  plan.axis = args.str("axis");
  plan.kind = args.str("model");
  const bool auto_kind = plan.kind == "auto";
  if (!auto_kind && !training::fitter(plan.kind)) throw UsageError("fit: kind '" + plan.kind + "' cannot be fitted on its own");
  if (auto_kind && args.has("features")) throw UsageError("fit: --features does not apply to --model auto");
  std::vector<std::string> notes;
  io::Dataset all = ros_io::read_recordings(args.list("data"), &notes);
  all.axis(plan.axis);  // clear error if the axis is missing
  try {
    if (args.has("validation")) {
      plan.train = all;
      plan.validation = ros_io::read_recordings(args.list("validation"), &notes);
      plan.all = std::move(all);
    } else {
      split_by_fraction(plan, std::move(all), args.num("split"));
    }
    plan.options = training::plan_options(args.has("options") ? args.str("options") : "", args.list("set"));
  } catch (const std::invalid_argument& e) {  // "split …", "options FILE: …", "set KEY=VALUE: …"
    throw UsageError(std::string("fit: --") + e.what());
  }
  for (const auto& n : notes) std::cerr << "note: " << n << "\n";
  for (const auto& f : args.list("data")) plan.source += (plan.source.empty() ? "" : " ") + f;
  return plan;
}

// --features: a named set, or lasso (chosen on the training part; its report written with --lasso-report).
YAML::Node feature_option(const Args& args, const training::FitRequest& req) {
  const std::string set = args.str("features");
  if (set == "voltage_lasso") return YAML::Node(set);  // chosen on the training part by the fit (training/fit_common.h)
  if (set != "lasso") {
    features::check_feature_set_name(set);  // validates the name
    return YAML::Node(set);
  }
  std::string report;
  std::size_t kept = 0;
  const YAML::Node o = analysis::lasso_linear_options(*req.train, req.axis, req.progress, &report, &kept);
  if (args.has("lasso-report")) {
    std::ofstream f(args.str("lasso-report"));
    if (!f) throw std::runtime_error(args.str("lasso-report") + ": cannot open for writing");
    f << report;
  }
  const features::DataSpan span = io::data_span(*req.train, req.axis);
  std::cerr << "\nlasso kept " << kept << " of " << features::candidate_features(&span).size()
            << " candidate features the data can identify (λ_1se)\n";
  return o["features"];
}

// The selection request of `req` (auto's and the identification check's): its data, budget, seed and threads.
analysis::SelectionRequest selection_request_of(const training::FitRequest& req, const training::FitPlan& plan) {
  analysis::SelectionRequest sr =
      analysis::selection_request(*req.train, req.validation, plan.score_data(), plan.split_at, req.axis);
  sr.time_budget_s = req.time_budget_s;
  sr.seed = req.seed;
  sr.threads = req.threads;
  return sr;
}

// The identification check of a single kind (`--model auto` has it from select_model): printed, and its ratio stored
// as validation carry_over_ratio. A tuned fit is not checked: the half fit would run the kind's defaults.
void identify(const analysis::ModelCandidate& c, const training::FitRequest& req, const training::FitPlan& plan,
              models::Model& model) {
  analysis::Identification id;
  if (req.tune_trials > 0) {
    id.unchecked = "a tuned fit (--tune): the half fit would not be tuned alike";
  } else {
    id = analysis::check_identification(selection_request_of(req, plan), c, model);
  }
  if (id.checked()) model.meta.validation["carry_over_ratio"] = id.ratio();
  std::cout << id.describe(c.label, io::data_span(*req.train, req.axis).duration_s) << "\n";
}

models::ModelPtr fit_auto(const Args& args, const training::FitRequest& req, const training::FitPlan& plan,
                          util::ProgressBar& bar) {
  if (!req.validation) throw UsageError("fit: --model auto needs validation data (--split < 1 or --validation)");
  analysis::SelectionRequest sr = selection_request_of(req, plan);
  try {
    sr.candidates = analysis::default_candidates(args.list("auto-extra"));
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("fit: ") + e.what());
  }
  sr.progress = req.progress;
  analysis::Selection sel = analysis::select_model(sr);
  bar.finish();
  std::cout << analysis::selection_table(sel) << "\n";
  std::cout << sel.identification.describe(sel.table[sel.best].candidate.label,
                                           io::data_span(plan.train, plan.axis).duration_s) << "\n";
  return std::move(sel.model);
}

// One kind: fitted, refused by the sanity gate if the data do not support it, its validation stored and its
// identification checked.
models::ModelPtr fit_kind(const Args& args, training::FitRequest& req, const training::FitPlan& plan,
                          util::ProgressBar& bar) {
  if (args.has("features")) req.options["features"] = feature_option(args, req);
  models::ModelPtr model = training::fit_model(plan.kind, req);
  if (!model) throw std::runtime_error("fit: kind '" + plan.kind + "' returned no model");
  model->meta.axis = plan.axis;
  model->meta.sample_rate_hz = plan.train.sample_rate_hz();
  bar.finish();
  const analysis::DataScale scale = analysis::data_scale(plan.train, plan.axis);
  if (!req.validation) {
    analysis::check_fit_sanity(*model, nullptr, scale);
    return model;
  }
  const analysis::ValidationScore score =
      analysis::score_validation(*model, plan.score_data(), plan.split_at, plan.axis);
  analysis::check_fit_sanity(*model, &score, scale);
  analysis::store_validation(score, *model);
  if (!args.flag("no-identification")) {
    const bool lasso = args.has("features") && args.str("features") == "lasso";
    identify(analysis::ModelCandidate{plan.kind, plan.kind, req.options, lasso}, req, plan, *model);
  }
  return model;
}

// The estimator's noise model on the part the model was not fitted on, run from a cold start as on the next
// recording: the warm continuation of the fit's own history shows smaller model errors than a new recording has,
// and a filter identified there is over-confident on one (docs/predictor.md, "Estimator").
void identify_estimator(const training::FitPlan& plan, models::Model& model) {
  if (!plan.has_validation()) return;
  const estimation::NoiseModel noise = analysis::identify_estimator(model, plan.validation, plan.axis);
  model.meta.estimator = noise.to_yaml();
  std::cout << "estimator: " << noise.describe() << "\n";
}

void write_model(const std::string& path, const models::Model& model, std::size_t rows) {
  models::save_model(path, model);
  std::cout << "wrote " << path << ": kind " << model.kind() << ", " << model.num_parameters()
            << " parameters, trained on " << rows << " samples";
  for (const auto& [k, v] : model.meta.validation) std::cout << "\n  " << k << " = " << v;
  std::cout << "\n";
}

int run(int argc, char** argv) {
  std::string kinds;
  for (const auto& k : models::model_kind_names()) kinds += (kinds.empty() ? "" : ", ") + k;
  Args args("fit", "Fit a model of one axis on a data file (CSV or bag) and write the model file (YAML).\n"
                   "The validation part (--validation FILE or the last 1 − split of --data, held out by time) gives the\n"
                   "validation metrics stored in the file. A fit that fails a sanity gate (free-run validation error\n"
                   "not finite or above 25 % of the position range, parameters far outside what the data supports)\n"
                   "is refused with one error. Kinds: auto (fit the candidates, choose by the errors of moves and hold creep), " + kinds);
  declare_options(args);
  if (!args.parse(argc, argv)) return 0;
  const training::FitPlan plan = read_plan(args);
  if (plan.all.recording_count() > 1)
    std::cout << "recordings: " << plan.train.recording_count() << " for training, "
              << (plan.has_validation() ? plan.validation.recording_count() : 0)
              << " for validation, each its own history and zero\n";
  util::ProgressBar bar(std::cerr, "steps", !args.flag("quiet"));
  training::FitRequest req = plan.request();
  req.tune_trials = static_cast<int>(args.integer("tune"));
  req.time_budget_s = args.seconds("time-budget-s");
  req.seed = static_cast<std::uint64_t>(args.integer("seed"));
  req.threads = static_cast<int>(args.integer("threads"));
  req.progress = [&](double done, double total, const std::string& what) { bar.update(done, total, what); };
  models::ModelPtr model = plan.kind == "auto" ? fit_auto(args, req, plan, bar) : fit_kind(args, req, plan, bar);
  identify_estimator(plan, *model);
  training::stamp_origin(*model, plan.train, plan.source);
  write_model(args.str("out"), *model, plan.train.size());
  return 0;
}

const Register reg("fit", "fit a model kind (linear, pi, pi_creep_*, dense, lstm, kan, ...) and write the model file", run);

}  // namespace
}  // namespace piezo::cli
