// `piezo fit`: fits any registered model kind on a data file and writes the model file.
#include <filesystem>
#include <fstream>
#include <iostream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/analysis/evaluation.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/lasso.h"
#include "piezo_compensation/util/progress_bar.h"

namespace piezo::cli {
namespace {

int run(int argc, char** argv) {
  std::string kinds;
  for (const auto& k : models::model_kind_names()) kinds += (kinds.empty() ? "" : ", ") + k;
  Args args("fit", "Fit a model of one axis on a data file (CSV or bag) and write the model file (YAML).\n"
                   "The validation part (--validation FILE or the last 1 − split of --data, held out by time) gives the\n"
                   "validation metrics stored in the file. Kinds: " + kinds);
  args.required("data", "FILE", "training data (CSV or bag)")
      .option("validation", "FILE", "separate validation data (else --split is used)")
      .option("split", "FRACTION", "training fraction of --data when no --validation is given", "0.8")
      .option("axis", "a|b|c", "axis to model", "c")
      .required("model", "KIND", "model kind")
      .option("features", "SET", "study | candidates | physics | lasso (lasso on the candidates, λ_1se survivors)")
      .option("tune", "N", "hyperparameter search with N trials (kinds that support it)", "0")
      .option("time-budget-s", "T", "stop tuning/training after T (seconds, or 90min, 2h; 0 = none)", "0")
      .option("set", "KEY=VALUE", "kind option (YAML value, e.g. method=lasso, thresholds_v=[0,10,20])", "", true)
      .option("options", "FILE.yaml", "kind options from a YAML mapping (--set overrides)")
      .option("seed", "N", "random seed", "1")
      .option("threads", "N", "threads", "2")
      .option("lasso-report", "FILE.md", "write the lasso selection report here (with --features lasso)")
      .option("quiet", "", "no progress bar")
      .required("out", "FILE.yaml", "model file to write");
  if (!args.parse(argc, argv)) return 0;
  const std::string axis = args.str("axis");
  const std::string kind = args.str("model");
  const training::FitFn& fit = training::fitter(kind);
  if (!fit) throw UsageError("fit: kind '" + kind + "' cannot be fitted on its own");

  io::Dataset all = ros_io::read_data(args.str("data"));
  all.axis(axis);  // clear error if the axis is missing
  io::Dataset train, val;
  std::size_t split_at = 0;  // > 0: validation is the tail of `all`, scored after running through the training part
  if (args.has("validation")) {
    train = all;
    val = ros_io::read_data(args.str("validation"));
  } else {
    const double split = args.num("split");
    if (!(split > 0 && split <= 1)) throw UsageError("fit: --split must be in (0, 1]");
    const std::size_t n = static_cast<std::size_t>(split * all.size());
    if (n < 20) throw UsageError("fit: too few training samples after --split");
    train = all.slice(0, n);
    if (n < all.size()) val = all.slice(n, all.size()), split_at = n;
    train.source = val.source = all.source;
  }

  YAML::Node options(YAML::NodeType::Map);
  if (args.has("options")) {
    try {
      options = YAML::LoadFile(args.str("options"));
    } catch (const YAML::Exception& e) {
      throw UsageError("fit: --options " + args.str("options") + ": " + e.what());
    }
    if (!options.IsMap()) throw UsageError("fit: --options " + args.str("options") + ": expected a mapping");
  }
  for (const auto& kv : args.list("set")) {
    const auto eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) throw UsageError("fit: --set expects KEY=VALUE, got '" + kv + "'");
    try {
      options[kv.substr(0, eq)] = YAML::Load(kv.substr(eq + 1));
    } catch (const YAML::Exception& e) {
      throw UsageError("fit: --set " + kv + ": " + e.what());
    }
  }

  util::ProgressBar bar(std::cerr, "steps", !args.flag("quiet"));
  training::FitRequest req;
  req.train = &train;
  req.validation = val.empty() ? nullptr : &val;
  req.axis = axis;
  req.tune_trials = static_cast<int>(args.integer("tune"));
  req.time_budget_s = args.seconds("time-budget-s");
  req.seed = static_cast<std::uint64_t>(args.integer("seed"));
  req.threads = static_cast<int>(args.integer("threads"));
  req.progress = [&](double done, double total, const std::string& what) { bar.update(done, total, what); };

  if (args.has("features")) {
    const std::string set = args.str("features");
    if (set == "lasso") {
      const auto sel = training::run_lasso(features::candidate_features(), train, axis, {}, req.progress);
      const features::FeatureSpec chosen = training::select_features(sel.spec, sel.path.coefs[sel.path.index_1se]);
      const std::string report = training::lasso_report(sel.spec, sel.path);
      if (args.has("lasso-report")) {
        std::ofstream f(args.str("lasso-report"));
        if (!f) throw std::runtime_error(args.str("lasso-report") + ": cannot open for writing");
        f << report;
      }
      std::cerr << "\nlasso kept " << chosen.size() << " of " << sel.spec.size() << " candidate features (λ_1se)\n";
      features::FeatureSpec raw = chosen;
      raw.mean.clear();
      raw.scale.clear();
      options["features"] = raw.to_yaml();
    } else {
      features::named_features(set);  // validates the name
      options["features"] = set;
    }
  }
  req.options = options;

  models::ModelPtr model = fit(req);
  if (!model) throw std::runtime_error("fit: kind '" + kind + "' returned no model");
  model->meta.axis = axis;
  model->meta.sample_rate_hz = train.sample_rate_hz();
  if (model->meta.training_source.empty()) model->meta.training_source = args.str("data");
  model->meta.time_clock = train.time_clock;  // the predictor feeds time_s only on the clock the data used
  bar.finish();

  if (req.validation) {
    // Held out by time. With --split the model runs through the training part first, so the validation part
    // starts with the real history (as live); a separate --validation file starts from rest.
    const io::Dataset& vd = split_at ? all : val;
    std::vector<char> mask(vd.size(), 1), hold = analysis::hold_mask(vd);
    for (std::size_t i = 0; i < split_at; ++i) mask[i] = hold[i] = 0;
    const auto p = analysis::predict_series(*model, vd, axis);
    const auto& ax = vd.axis(axis);
    auto put = [&](const std::string& key, const analysis::ErrorStats& s) {
      if (s.valid()) model->meta.validation[key] = s.mae_nm;
    };
    put("one_step_mae_nm", analysis::error_stats(p.one_step, ax.position_nm, mask));
    put("free_run_mae_nm", analysis::error_stats(p.free_run, ax.position_nm, mask));
    if (ax.has_truth()) {
      put("one_step_mae_vs_truth_nm", analysis::error_stats(p.one_step, ax.true_position_nm, mask));
      put("free_run_mae_vs_truth_nm", analysis::error_stats(p.free_run, ax.true_position_nm, mask));
      put("hold_free_run_mae_vs_truth_nm", analysis::error_stats(p.free_run, ax.true_position_nm, hold));
    }
    put("hold_free_run_mae_nm", analysis::error_stats(p.free_run, ax.position_nm, hold));
    model->meta.validation["validation_samples"] = static_cast<double>(val.size());
  }
  models::save_model(args.str("out"), *model);
  std::cout << "wrote " << args.str("out") << ": kind " << model->kind() << ", " << model->num_parameters()
            << " parameters, trained on " << train.size() << " samples";
  for (const auto& [k, v] : model->meta.validation) std::cout << "\n  " << k << " = " << v;
  std::cout << "\n";
  return 0;
}

const Register reg("fit", "fit a model kind (linear, pi, pi_creep_*, dense, lstm, kan, ...) and write the model file", run);

}  // namespace
}  // namespace piezo::cli
