// `--model auto` itself: the candidates, the identification check, select_model and fit_auto, the selection's table
// and model-file block. Each candidate is scored in candidate_scoring.cpp and chosen by choice_rule.cpp.
#include "piezo_compensation/analysis/selection/model_selection.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/training/lasso.h"
#include "piezo_compensation/util/format.h"

namespace piezo::analysis {

YAML::Node lasso_linear_options(const io::Dataset& train, const std::string& axis, const training::ProgressFn& progress,
                                std::string* report, std::size_t* kept) {
  const features::DataSpan span = io::data_span(train, axis);
  const features::FeatureSpec chosen = training::lasso_survivors(features::candidate_features(&span), train, axis,
                                                                  progress, report);
  if (kept) *kept = chosen.size();
  YAML::Node o(YAML::NodeType::Map);
  o["features"] = chosen.to_yaml();
  return o;
}

std::vector<ModelCandidate> default_candidates(const std::vector<std::string>& extra_kinds) {
  std::vector<ModelCandidate> c;
  for (const auto& k : models::model_kind_names())
    if (models::model_kind(k).auto_candidacy == models::AutoCandidacy::kDefault) {
      c.push_back({k, k, YAML::Node(), false});
      c.push_back({k + " + output map", k, YAML::Load("{output_map: on}"), false});
    }
  for (const auto& k : extra_kinds) {
    if (models::model_kind(k).auto_candidacy == models::AutoCandidacy::kNever)  // model_kind throws for unknown kinds
      throw std::invalid_argument("--auto-extra " + k + ": not a kind --model auto can fit on its own");
    const bool dup = std::any_of(c.begin(), c.end(), [&](const ModelCandidate& x) { return x.kind == k; });
    if (dup) continue;
    if (k == "linear") c.push_back({"linear (lasso features)", "linear", YAML::Node(), true});
    else if (k == "kan") c.push_back({"kan", "kan", YAML::Load("{steps: 800, patience: 0}"), false});
    else c.push_back({k, k, YAML::Node(), false});
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

namespace {
training::FitRequest fit_request(const SelectionRequest& rq, const ModelCandidate& c, const io::Dataset& train,
                                 const io::Dataset* validation, training::LassoFeatureCache* lasso_cache) {
  training::FitRequest fr;
  fr.lasso_cache = lasso_cache;
  fr.train = &train;
  fr.validation = validation;
  fr.axis = rq.axis;
  fr.options = c.options ? YAML::Clone(c.options) : YAML::Node(YAML::NodeType::Map);
  fr.time_budget_s = rq.time_budget_s;
  fr.seed = rq.seed;
  fr.threads = rq.threads;
  return fr;
}

// The row where the training part's second half starts: its middle, or with several recordings the start of the
// recording nearest it (whole recordings on either side).
std::size_t half_row(const io::Dataset& train) {
  std::size_t half = train.size() / 2;
  if (train.recording_count() < 2) return half;
  std::size_t best = 0;
  for (std::size_t k = 1; k < train.recording_count(); ++k) {
    const std::size_t b = train.recording_rows(k).first;
    if (best == 0 || (b > half ? b - half : half - b) < (best > half ? best - half : half - best)) best = b;
  }
  return best;
}
}  // namespace

double estimate_block_noise(const SelectionRequest& rq) {
  if (rq.slow.noise_nm > 0.0) return rq.slow.noise_nm;
  if (!rq.score_data || rq.score_data->size() <= rq.score_from) return NAN;
  try {
    const io::Dataset tail = rq.score_data->slice(rq.score_from, rq.score_data->size());
    const NoiseFloor nf = estimate_noise_floor(tail, rq.axis);
    const double rate = tail.size() > 1 ? tail.sample_rate_hz() : 1.0;
    const double rows = std::max(1.0, rq.slow.mean_s * rate);
    return std::sqrt(2.0) * std::max(nf.sigma_nm, nf.quantisation_nm / std::sqrt(12.0)) / std::sqrt(rows);
  } catch (const std::exception&) {
    return NAN;  // too few samples for a noise figure
  }
}

Identification identification(double carry_nm, double validation_nm, double noise_nm) {
  Identification id;
  id.carry_nm = carry_nm;
  id.validation_nm = validation_nm;
  id.noise_nm = std::isfinite(noise_nm) && noise_nm > 0.0 ? noise_nm : 0.0;
  if (!std::isfinite(carry_nm)) id.unchecked = "no carry-over figure (a training part too short for the fold)";
  else if (!std::isfinite(validation_nm)) id.unchecked = "no use error on the validation part to compare with";
  return id;
}

Identification check_identification(const SelectionRequest& rq, const ModelCandidate& c, const models::Model& fitted,
                                    const SlowScore* validation) {
  Identification id;
  if (!rq.train || !rq.score_data || rq.score_data->size() <= rq.score_from) {
    id.unchecked = "no validation part";
    return id;
  }
  try {
    SelectionRequest scaled = rq;
    scaled.slow = fitted_to_part(rq.slow, *rq.score_data, rq.score_from);
    const double noise = estimate_block_noise(scaled);
    SlowScoreOptions o = scaled.slow;
    if (std::isfinite(noise) && noise > 0.0) o.noise_nm = noise;
    const SlowScore v = validation ? *validation : slow_score(fitted, *rq.score_data, rq.score_from, rq.axis, o);
    const io::Dataset& train = *rq.train;
    const std::size_t half = half_row(train);
    if (half < 4 || double(train.size() - half) < 2.0 * o.move_long_s * train.sample_rate_hz())
      return identification(NAN, v.overall_nm, noise);
    const io::Dataset first = train.slice(0, half);
    const std::size_t fit_rows = rq.validation ? half * 4 / 5 : half;
    const io::Dataset fit_part = first.slice(0, fit_rows), val_part = first.slice(fit_rows, half);
    ModelCandidate half_c = c;
    if (c.lasso_features) {  // the features chosen again on the half; the candidate's other options kept
      half_c.options = c.options && c.options.IsMap() ? YAML::Clone(c.options) : YAML::Node(YAML::NodeType::Map);
      half_c.options["features"] = lasso_linear_options(fit_part, rq.axis, {})["features"];
    }
    const models::ModelPtr m =
        training::fit_model(c.kind, fit_request(rq, half_c, fit_part, rq.validation ? &val_part : nullptr, nullptr));
    if (!m) throw std::runtime_error("the half fit returned no model");
    const SlowScore carry = slow_score(*m, train, half, rq.axis, o);
    return identification(carry.overall_nm, v.overall_nm, noise);
  } catch (const std::exception& e) {
    id.unchecked = std::string("the check failed: ") + e.what();
    return id;
  }
}

std::string Identification::describe(const std::string& label, double train_s) const {
  if (!checked())
    return "identification of " + label + ": not checked: " + (unchecked.empty() ? "no ratio" : unchecked);
  std::ostringstream os;
  os << "identification of " << label << ": fitted on the training part's first half it is " << util::fmt(carry_nm, 3)
     << " nm off (overall use error) on the second half, the whole fit " << util::fmt(validation_nm, 3)
     << " nm on the validation part (noise " << util::fmt(noise_nm, 2) << " nm): " << util::fmt(ratio(), 3) << "x";
  if (!flagged()) {
    os << " (<= " << util::fmt(kCarryOverAdvised, 3) << ": the recording identifies it)";
  } else {
    os << ". Over " << util::fmt(kCarryOverAdvised, 3) << "x the " << util::fmt(train_s, 3)
       << "-s training recording does not identify it: a separate recording is likely to be worse than the validation "
          "says. Record longer, sweeping the range the stage will be used over";
  }
  return os.str();
}

std::string unidentified_model_warning(const models::Model& model, const std::string& path) {
  const auto c = model.meta.validation.find("carry_over_ratio");
  if (c == model.meta.validation.end() || !(c->second > kCarryOverAdvised)) return {};
  return "model file " + path + ": its training recording did not identify it (fitted on the first half, " +
         util::fmt(c->second, 3) +
         "x worse on the second than on validation): expect larger errors than its validation "
         "figures; refit on a longer recording";
}

namespace {
// The plain fit an output-map variant starts from: the row before it when that is the same kind fitted
// without options (default_candidates lists each kind, then its variant) and was kept; else null (the variant
// fits it).
const models::Model* plain_fit_of(const Selection& sel, const ModelCandidate& cand) {
  const YAML::Node& o = cand.options;
  if (sel.table.empty() || !o || !o.IsMap() || o.size() != 1 || !o["output_map"]) return nullptr;
  const CandidateResult& prev = sel.table.back();
  const YAML::Node& po = prev.candidate.options;
  const bool plain = !po || po.IsNull() || (po.IsMap() && po.size() == 0);
  if (prev.candidate.kind != cand.kind || !plain || prev.candidate.lasso_features || !prev.model)
    return nullptr;
  return prev.model.get();
}

// One candidate fitted on the training part and scored on the validation part (refused with the reason otherwise).
CandidateResult fit_candidate(const SelectionRequest& rq, const ModelCandidate& cand, const Selection& sel,
                              training::LassoFeatureCache& lasso_cache) {
  CandidateResult r;
  r.candidate = cand;
  const auto t0 = std::chrono::steady_clock::now();
  models::ModelPtr m;
  try {
    if (!training::fitter(r.candidate.kind)) throw std::runtime_error("kind cannot be fitted on its own");
    if (r.candidate.lasso_features) r.candidate.options = lasso_linear_options(*rq.train, rq.axis, {});
    training::FitRequest fr = fit_request(rq, r.candidate, *rq.train, rq.validation, &lasso_cache);
    fr.plain_fit = plain_fit_of(sel, r.candidate);
    m = training::fit_model(r.candidate.kind, fr);
    if (!m) throw std::runtime_error("the fit returned no model");
    m->meta.axis = rq.axis;
    m->meta.sample_rate_hz = rq.train->sample_rate_hz();
    r.parameters = m->num_parameters();
    SeriesPrediction p;
    r.score = score_validation(*m, *rq.score_data, rq.score_from, rq.axis, &p);
    r.refused = sanity_problem(*m, &r.score, sel.scale);
    if (r.refused.empty())
      r.slow = slow_score(*m, *rq.score_data, rq.score_from, rq.axis, sel.slow_options, &p.free_run);
  } catch (const std::exception& e) {
    r.refused = "kind " + r.candidate.kind + " refused: the fit failed: " + e.what();
  }
  r.fit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (r.refused.empty()) r.model = std::move(m);
  return r;
}
}  // namespace


Selection select_model(const SelectionRequest& rq) {
  if (!rq.train || !rq.score_data) throw std::invalid_argument("model selection: no training or validation data");
  if (rq.score_data->size() <= rq.score_from)
    throw std::invalid_argument("model selection needs validation samples (use --split < 1 or --validation)");
  Selection sel;
  sel.scale = data_scale(*rq.train, rq.axis);
  SelectionRequest scaled = rq;
  scaled.slow = fitted_to_part(rq.slow, *rq.score_data, rq.score_from);
  sel.slow_options = scaled.slow;
  sel.block_noise_nm = estimate_block_noise(scaled);
  if (std::isfinite(sel.block_noise_nm) && sel.block_noise_nm > 0.0) sel.slow_options.noise_nm = sel.block_noise_nm;
  const std::vector<ModelCandidate> cands = rq.candidates.empty() ? default_candidates() : rq.candidates;
  training::LassoFeatureCache lasso_cache;  // the neural candidates' voltage_lasso, resolved once
  for (std::size_t k = 0; k < cands.size(); ++k) {
    if (rq.progress) rq.progress(double(k), double(cands.size()), "fitting " + cands[k].label);
    sel.table.push_back(fit_candidate(rq, cands[k], sel, lasso_cache));
  }
  std::vector<ChoiceEntry> entries;
  for (const auto& r : sel.table)
    entries.push_back({r.candidate.label, r.parameters, r.refused.empty() && r.slow.valid() ? &r.slow : nullptr});
  const Choice ch = choose_candidate(entries);
  if (ch.chosen == SIZE_MAX) {
    std::string why = "model selection: every candidate was refused:";
    for (const auto& r : sel.table)
      why += "\n  " + (r.refused.empty() ? r.candidate.label + ": no use-error score (too few validation samples)"
                                          : r.refused);
    throw FitRejected(why);
  }
  sel.best = ch.chosen;
  sel.best_overall = ch.best_overall;
  sel.reason = ch.reason;
  const CandidateResult& chosen = sel.table[sel.best];
  sel.model = chosen.model->clone();
  store_validation(chosen.score, *sel.model);
  if (rq.identify) {
    SelectionRequest id_rq = rq;
    id_rq.slow = sel.slow_options;
    sel.identification = check_identification(id_rq, chosen.candidate, *chosen.model, &chosen.slow);
  } else {
    sel.identification.unchecked = "not asked for";
  }
  if (sel.identification.checked()) sel.model->meta.validation["carry_over_ratio"] = sel.identification.ratio();
  sel.model->meta.selection = selection_yaml(sel);
  return sel;
}

models::ModelPtr fit_auto(const io::Dataset& train, std::size_t n_fit, const std::string& axis, std::uint64_t seed,
                          ModelCandidate* chosen, std::string* table) {
  if (n_fit == 0 || n_fit >= train.size()) throw std::invalid_argument("--model auto: no fit or no validation rows");
  const io::Dataset fit_part = train.slice(0, n_fit), val_part = train.slice(n_fit, train.size());
  SelectionRequest rq = selection_request(fit_part, &val_part, train, n_fit, axis);
  rq.seed = seed;
  Selection sel = select_model(rq);
  if (chosen) *chosen = sel.table[sel.best].candidate;
  if (table) *table = selection_table(sel);
  return std::move(sel.model);
}

namespace {
std::string cell(double x) { return std::isfinite(x) ? util::fmt(x, 3) : std::string("–"); }

std::string rule_text(const SlowScoreOptions& o) {
  return "each candidate fitted on the training part and run free over the held-out part, scored on the errors of "
         "the predicted change over " +
         util::fmt(o.move_short_s, 3) + " s and " + util::fmt(o.move_long_s, 3) +
         " s of the moves "
         "and of the creep in each hold from its start (" +
         util::fmt(o.mean_s, 3) +
         "-s means, no zero needed); the fewest "
         "parameters among the candidates no column of which is clearly worse (paired test over " +
         util::fmt(o.block_s, 3) + "-s blocks) than the lowest overall (geometric mean of the columns)";
}
}  // namespace

std::string selection_table(const Selection& s) {
  std::ostringstream os;
  const auto& o = s.slow_options;
  os << "Model choice (`--model auto`): " << rule_text(o)
     << ". Holds: the voltage unchanged >= " << util::fmt(o.hold_min_s, 3) << " s";
  if (o.time_scale < 1.0)
    os << "; the held-out part is short: windows, moves and blocks scaled by " << util::fmt(o.time_scale, 3);
  if (std::isfinite(s.block_noise_nm))
    os << "; noise of a change of " << util::fmt(o.mean_s, 3) << "-s means ~" << util::fmt(s.block_noise_nm, 2)
       << " nm";
  os << ".\n\n| kind | parameters | 10-s moves [nm] | 60-s moves [nm] | hold creep [nm] | worst hold creep end [nm] | "
        "overall [nm] | free-run MAE [nm] | status |\n|---|---:|---:|---:|---:|---:|---:|---:|---|\n";
  for (std::size_t k = 0; k < s.table.size(); ++k) {
    const auto& r = s.table[k];
    const auto& w = r.slow;
    std::string status = r.refused;
    if (status.empty()) {
      if (s.model && k == s.best) status = "**chosen**";
      else if (k == s.best_overall) status = "lowest overall";
    }
    os << "| " << r.candidate.label << " | " << r.parameters << " | " << cell(w.move_short_nm) << " | "
       << cell(w.move_long_nm) << " | " << cell(w.hold_creep_nm) << " | " << cell(w.worst_hold_creep_nm) << " | "
       << cell(w.overall_nm) << " | "
       << cell(r.score.finite && r.score.free_run.valid() ? r.score.free_run.mae_nm : NAN) << " | " << status << " |\n";
  }
  if (!s.reason.empty()) os << "\nChoice: " << s.reason << "\n";
  return os.str();
}

YAML::Node selection_yaml(const Selection& s) {
  YAML::Node n;
  const auto& o = s.slow_options;
  n["criterion"] = rule_text(o) + ", among the candidates passing the gates";
  if (!s.table.empty()) {
    n["chosen"] = s.table[s.best].candidate.label;
    n["chosen_kind"] = s.table[s.best].candidate.kind;
    n["lowest_overall"] = s.table[s.best_overall].candidate.label;
  }
  n["reason"] = s.reason;
  n["mean_s"] = o.mean_s;
  n["move_short_s"] = o.move_short_s;
  n["move_long_s"] = o.move_long_s;
  n["hold_min_s"] = o.hold_min_s;
  n["block_s"] = o.block_s;
  if (o.time_scale < 1.0) n["time_scale"] = o.time_scale;
  if (std::isfinite(s.block_noise_nm)) n["noise_nm"] = s.block_noise_nm;
  n["position_range_nm"] = s.scale.position_range_nm;
  YAML::Node rows(YAML::NodeType::Sequence);
  for (const auto& r : s.table) {
    YAML::Node row;
    row["candidate"] = r.candidate.label;
    row["kind"] = r.candidate.kind;
    row["parameters"] = static_cast<unsigned long>(r.parameters);
    const auto& w = r.slow;
    auto put = [&](const char* key, double x) {
      if (std::isfinite(x)) row[key] = x;
    };
    put("move_10s_nm", w.move_short_nm);
    put("move_60s_nm", w.move_long_nm);
    put("hold_creep_nm", w.hold_creep_nm);
    put("worst_hold_creep_end_nm", w.worst_hold_creep_nm);
    put("overall_nm", w.overall_nm);
    put("hold_creep_vs_truth_nm", w.hold_creep_truth_nm);
    if (r.score.finite && r.score.free_run.valid()) {
      row["free_run_mae_nm"] = r.score.free_run.mae_nm;
      row["free_run_max_nm"] = r.score.free_run.max_nm;
    }
    row["fit_s"] = r.fit_s;
    if (!r.refused.empty()) row["refused"] = r.refused;
    rows.push_back(row);
  }
  n["candidates"] = rows;
  return n;
}

}  // namespace piezo::analysis
