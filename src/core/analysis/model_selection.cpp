#include "piezo_compensation/analysis/model_selection.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "piezo_compensation/analysis/evaluation.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/lasso.h"

namespace piezo::analysis {

namespace {

bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
}

std::string fmt(double x, int precision = 3) {
  std::ostringstream os;
  os << std::setprecision(precision) << x;
  return os.str();
}

// Walks the model's parameters; calls f(path, key, value) for every number.
template <class F>
void for_each_number(const YAML::Node& n, const std::string& path, const std::string& key, F&& f) {
  if (n.IsScalar()) {
    double v = 0.0;
    try {
      v = n.as<double>();
    } catch (const YAML::Exception&) {
      return;  // text (method names, feature types)
    }
    f(path, key, v);
  } else if (n.IsSequence()) {
    for (std::size_t i = 0; i < n.size(); ++i) for_each_number(n[i], path + "[" + std::to_string(i) + "]", key, f);
  } else if (n.IsMap()) {
    for (const auto& kv : n) {
      const std::string k = kv.first.as<std::string>();
      for_each_number(kv.second, path.empty() ? k : path + "." + k, k, f);
    }
  }
}

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return NAN;
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(p * static_cast<double>(v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

}  // namespace

DataScale data_scale(const io::Dataset& data, const std::string& axis) {
  const auto& ax = data.axis(axis);
  DataScale s;
  std::vector<double> y;
  y.reserve(ax.position_nm.size());
  for (double x : ax.position_nm)
    if (std::isfinite(x)) y.push_back(x), s.position_abs_max_nm = std::max(s.position_abs_max_nm, std::fabs(x));
  if (!y.empty()) s.position_range_nm = percentile(y, 0.999) - percentile(y, 0.001);
  if (data.size() > 1) {
    const io::DataSpan span = io::data_span(data, axis);
    s.voltage_span_v = span.voltage_span_v();
    s.duration_s = span.duration_s;
  }
  return s;
}

ValidationScore score_validation(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                                 const std::string& axis) {
  ValidationScore s;
  const auto& ax = data.axis(axis);
  std::vector<char> mask(data.size(), 1), hold = hold_mask(data);
  for (std::size_t i = 0; i < std::min(score_from, data.size()); ++i) mask[i] = hold[i] = 0;
  s.samples = data.size() > score_from ? data.size() - score_from : 0;
  SeriesPrediction p;
  try {
    p = predict_series(model, data, axis);
  } catch (const std::exception& e) {
    s.finite = false;
    s.failure = e.what();
    return s;
  }
  for (std::size_t i = score_from; i < p.free_run.size(); ++i)
    if (!std::isfinite(p.free_run[i]) || !std::isfinite(p.one_step[i])) {
      s.finite = false;
      s.failure = "prediction not finite at sample " + std::to_string(i);
      return s;
    }
  s.one_step = error_stats(p.one_step, ax.position_nm, mask);
  s.free_run = error_stats(p.free_run, ax.position_nm, mask);
  s.hold_free_run = error_stats(p.free_run, ax.position_nm, hold);
  if (ax.has_truth()) {
    s.one_step_truth = error_stats(p.one_step, ax.true_position_nm, mask);
    s.free_run_truth = error_stats(p.free_run, ax.true_position_nm, mask);
    s.hold_free_run_truth = error_stats(p.free_run, ax.true_position_nm, hold);
  }
  return s;
}

void store_validation(const ValidationScore& s, models::Model& model) {
  auto put = [&](const std::string& key, const ErrorStats& e) {
    if (e.valid()) model.meta.validation[key] = e.mae_nm;
  };
  put("one_step_mae_nm", s.one_step);
  put("free_run_mae_nm", s.free_run);
  put("one_step_mae_vs_truth_nm", s.one_step_truth);
  put("free_run_mae_vs_truth_nm", s.free_run_truth);
  put("hold_free_run_mae_vs_truth_nm", s.hold_free_run_truth);
  put("hold_free_run_mae_nm", s.hold_free_run);
  model.meta.validation["validation_samples"] = static_cast<double>(s.samples);
}

std::string sanity_problem(const models::Model& model, const ValidationScore* score, const DataScale& scale) {
  const std::string who = "kind " + model.kind() + " refused: ";
  const double range = scale.position_range_nm;
  if (score) {
    if (!score->finite || !score->free_run.valid() || !std::isfinite(score->free_run.mae_nm))
      return who + "free-run validation error is not finite (" +
             (score->failure.empty() ? std::string("no valid samples") : score->failure) +
             "); likely cause: a numerically unstable fit (positions or voltages in unexpected units, a column "
             "with NaN, too short a recording)";
    if (range > 0.0 && score->free_run.mae_nm > kMaxFreeRunErrorOfRange * range)
      return who + "free-run validation MAE " + fmt(score->free_run.mae_nm) + " nm is " +
             fmt(100.0 * score->free_run.mae_nm / range) + " % of the data's position range (" + fmt(range) +
             " nm; the gate is " + fmt(100.0 * kMaxFreeRunErrorOfRange) +
             " %); likely cause: wrong units or column (position not in nm, voltage not in V, another axis), a "
             "recording too short for this kind, or validation data from another stage";
  }
  std::string problem;
  const double size_nm = std::max(range, 1e-9) + scale.position_abs_max_nm;
  for_each_number(model.to_yaml(), "model", "", [&](const std::string& path, const std::string& key, double v) {
    if (!problem.empty()) return;
    if (path.rfind("model.training.", 0) == 0) return;  // figures of the training run, not parameters
    if (!std::isfinite(v)) {
      problem = who + "parameter " + path + " is not finite; likely cause: a numerically unstable fit";
    } else if (ends_with(key, "_nm") && !ends_with(key, "_per_nm") && std::fabs(v) > 10.0 * size_nm) {
      problem = who + "parameter " + path + " = " + fmt(v) + " nm is " + fmt(std::fabs(v) / std::max(range, 1e-9)) +
                " times the data's position range (" + fmt(range) +
                " nm): large cancelling terms; likely cause: positions in other units than nm, or too short a "
                "recording to separate the terms";
    } else if (ends_with(key, "_nm_per_v") && range > 0.0 && std::fabs(v) * scale.voltage_span_v > 10.0 * range) {
      problem = who + "parameter " + path + " = " + fmt(v) + " nm/V moves " +
                fmt(std::fabs(v) * scale.voltage_span_v) + " nm over the data's " + fmt(scale.voltage_span_v) +
                " V span, " + fmt(std::fabs(v) * scale.voltage_span_v / range) + " times the position range (" +
                fmt(range) + " nm): cancelling weights; likely cause: voltage or position in other units, or "
                "too few distinct voltages in the recording";
    } else if (key.find("tau") != std::string::npos && ends_with(key, "_s") && scale.duration_s > 0.0 &&
               v > 10.0 * scale.duration_s) {
      problem = who + "time constant " + path + " = " + fmt(v) + " s, but the training data lasts " +
                fmt(scale.duration_s) + " s: the data cannot identify it; likely cause: too short a recording "
                "for this creep model (use a longer one or a kind without slow creep)";
    }
  });
  return problem;
}

void check_fit_sanity(const models::Model& model, const ValidationScore* score, const DataScale& scale) {
  const std::string p = sanity_problem(model, score, scale);
  if (!p.empty()) throw FitRejected(p);
}

YAML::Node lasso_linear_options(const io::Dataset& train, const std::string& axis, const training::ProgressFn& progress,
                                std::string* report, std::size_t* kept) {
  const auto sel = training::run_lasso(features::candidate_features(), train, axis, {}, progress);
  features::FeatureSpec chosen = training::select_features(sel.spec, sel.path.coefs[sel.path.index_1se]);
  if (report) *report = training::lasso_report(sel.spec, sel.path);
  if (kept) *kept = chosen.size();
  chosen.mean.clear();
  chosen.scale.clear();
  YAML::Node o(YAML::NodeType::Map);
  o["features"] = chosen.to_yaml();
  return o;
}

std::vector<ModelCandidate> default_candidates(const std::vector<std::string>& extra_kinds) {
  std::vector<ModelCandidate> c;
  c.push_back({"linear (lasso features)", "linear", YAML::Node(), true});
  c.push_back({"pi", "pi", YAML::Node(), false});
  for (const auto& k : models::model_kind_names())
    if (k.rfind("pi_creep_", 0) == 0) c.push_back({k, k, YAML::Node(), false});
  for (const auto& k : models::model_kind_names())
    if (k.rfind("preisach", 0) == 0) c.push_back({k, k, YAML::Node(), false});
  // The KAN on its voltage-history features, on a fixed step budget (deterministic, bounded time): on short
  // fast recordings (lowvolt_pi_creep, docs/models.md) it beats every kind above by a third.
  c.push_back({"kan", "kan", YAML::Load("{steps: 800, patience: 0}"), false});
  for (const auto& k : extra_kinds) {
    models::model_kind(k);  // throws listing the known kinds
    const bool dup = std::any_of(c.begin(), c.end(), [&](const ModelCandidate& x) { return x.label == k; });
    if (!dup) c.push_back({k, k, YAML::Node(), false});
  }
  return c;
}

SelectionRequest selection_request(const io::Dataset& train, const io::Dataset* validation,
                                   const io::Dataset& score_data, std::size_t score_from, const std::string& axis) {
  SelectionRequest rq;
  rq.train = &train;
  rq.validation = validation;
  rq.score_data = &score_data;
  rq.score_from = score_from;
  rq.axis = axis;
  return rq;
}

Selection select_model(const SelectionRequest& rq) {
  if (!rq.train || !rq.score_data) throw std::invalid_argument("model selection: no training or validation data");
  if (rq.score_data->size() <= rq.score_from)
    throw std::invalid_argument("model selection needs validation samples (use --split < 1 or --validation)");
  Selection sel;
  sel.scale = data_scale(*rq.train, rq.axis);
  const std::vector<ModelCandidate> cands = rq.candidates.empty() ? default_candidates() : rq.candidates;
  double best_mae = INFINITY;
  for (std::size_t k = 0; k < cands.size(); ++k) {
    CandidateResult r;
    r.candidate = cands[k];
    if (rq.progress) rq.progress(double(k), double(cands.size()), "fitting " + r.candidate.label);
    const auto t0 = std::chrono::steady_clock::now();
    models::ModelPtr m;
    try {
      const training::FitFn& fit = training::fitter(r.candidate.kind);
      if (!fit) throw std::runtime_error("kind cannot be fitted on its own");
      if (r.candidate.lasso_features) r.candidate.options = lasso_linear_options(*rq.train, rq.axis, {});
      training::FitRequest fr;
      fr.train = rq.train;
      fr.validation = rq.validation;
      fr.axis = rq.axis;
      fr.options = r.candidate.options ? YAML::Clone(r.candidate.options) : YAML::Node(YAML::NodeType::Map);
      fr.time_budget_s = rq.time_budget_s;
      fr.seed = rq.seed;
      fr.threads = rq.threads;
      m = fit(fr);
      if (!m) throw std::runtime_error("the fit returned no model");
      m->meta.axis = rq.axis;
      m->meta.sample_rate_hz = rq.train->sample_rate_hz();
      r.parameters = m->num_parameters();
      r.score = score_validation(*m, *rq.score_data, rq.score_from, rq.axis);
      r.refused = sanity_problem(*m, &r.score, sel.scale);
    } catch (const std::exception& e) {
      r.refused = "kind " + r.candidate.kind + " refused: the fit failed: " + e.what();
    }
    r.fit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (r.refused.empty() && r.score.free_run.mae_nm < best_mae) {
      best_mae = r.score.free_run.mae_nm;
      sel.best = k;
      store_validation(r.score, *m);
      sel.model = std::move(m);
    }
    sel.table.push_back(std::move(r));
  }
  if (!sel.model) {
    std::string why = "model selection: every candidate was refused:";
    for (const auto& r : sel.table) why += "\n  " + r.refused;
    throw FitRejected(why);
  }
  sel.model->meta.selection = selection_yaml(sel);
  return sel;
}

std::string selection_table(const Selection& s) {
  std::ostringstream os;
  const double range = s.scale.position_range_nm;
  os << "Model choice (`--model auto`): each candidate fitted on the training part and run free on the validation\n"
        "part; the lowest free-run MAE against the measurement wins. Position range of the training data "
     << fmt(range, 4) << " nm.\n\n";
  os << "| candidate | free-run MAE [nm] | [% of range] | max [nm] | parameters | fit [s] | status |\n";
  os << "|---|---:|---:|---:|---:|---:|---|\n";
  for (std::size_t k = 0; k < s.table.size(); ++k) {
    const auto& r = s.table[k];
    const bool scored = r.score.finite && r.score.free_run.valid();
    os << "| " << r.candidate.label << " | " << (scored ? fmt(r.score.free_run.mae_nm, 4) : "–") << " | "
       << (scored && range > 0 ? fmt(100.0 * r.score.free_run.mae_nm / range, 3) : "–") << " | "
       << (scored ? fmt(r.score.free_run.max_nm, 4) : "–") << " | " << r.parameters << " | " << fmt(r.fit_s, 3)
       << " | " << (!r.refused.empty() ? r.refused : (s.model && k == s.best ? "**chosen**" : "")) << " |\n";
  }
  return os.str();
}

YAML::Node selection_yaml(const Selection& s) {
  YAML::Node n;
  n["criterion"] = "lowest free-run validation MAE vs the measurement among the candidates passing the gates";
  if (!s.table.empty()) {
    n["chosen"] = s.table[s.best].candidate.label;
    n["chosen_kind"] = s.table[s.best].candidate.kind;
  }
  n["position_range_nm"] = s.scale.position_range_nm;
  YAML::Node rows(YAML::NodeType::Sequence);
  for (const auto& r : s.table) {
    YAML::Node row;
    row["candidate"] = r.candidate.label;
    row["kind"] = r.candidate.kind;
    if (r.score.finite && r.score.free_run.valid()) {
      row["free_run_mae_nm"] = r.score.free_run.mae_nm;
      row["free_run_max_nm"] = r.score.free_run.max_nm;
    }
    row["parameters"] = static_cast<unsigned long>(r.parameters);
    row["fit_s"] = r.fit_s;
    if (!r.refused.empty()) row["refused"] = r.refused;
    rows.push_back(row);
  }
  n["candidates"] = rows;
  return n;
}

}  // namespace piezo::analysis
