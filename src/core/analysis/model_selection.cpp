#include "piezo_compensation/analysis/model_selection.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/training/fit_common.h"
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

namespace {
// score_validation, keeping the predicted series (`p`) for the slow scores.
ValidationScore score_validation_series(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                                        const std::string& axis, SeriesPrediction& p) {
  ValidationScore s;
  const auto& ax = data.axis(axis);
  std::vector<char> mask(data.size(), 1), hold = hold_mask(data);
  for (std::size_t i = 0; i < std::min(score_from, data.size()); ++i) mask[i] = hold[i] = 0;
  s.samples = data.size() > score_from ? data.size() - score_from : 0;
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
}  // namespace

ValidationScore score_validation(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                                 const std::string& axis) {
  SeriesPrediction p;
  return score_validation_series(model, data, score_from, axis, p);
}

// ---- the errors the use cares about ----

std::vector<io::HoldRun> voltage_holds(const io::Dataset& d, const std::string& axis, std::size_t from,
                                       const SlowScoreOptions& o) {
  io::HoldRule rule;
  rule.min_duration_s = o.hold_min_s;
  rule.tolerance_v = o.hold_tolerance_v;
  rule.use_phase = false;
  return io::find_holds(d, axis, rule, from);
}

namespace {
double mean_of(const std::vector<double>& v) {
  if (v.empty()) return NAN;
  double s = 0;
  for (double x : v) s += x;
  return s / double(v.size());
}
double max_of(const std::vector<double>& v) { return v.empty() ? NAN : *std::max_element(v.begin(), v.end()); }

// Means over consecutive windows of mean_s of one recording's rows [b, e), from the time of row b. A window with
// fewer than half its expected rows (a gap in the host clock) has NaN means. hold: the hold every row of the window
// lies in (-1: none, or rows of several); walk: no row of the window in a hold.
struct Windows {
  std::vector<double> p, y;
  std::vector<long> hold;
  std::vector<char> walk;
};
Windows window_means(const std::vector<double>& p, const std::vector<double>& y, const std::vector<double>& t,
                     std::size_t b, std::size_t e, const std::vector<io::HoldRun>& holds, double mean_s, double rate) {
  Windows w;
  const double min_rows = 0.5 * mean_s * rate;
  std::size_t h = 0;
  for (std::size_t i = b; i < e;) {
    const auto k = static_cast<std::size_t>(std::max(0.0, (t[i] - t[b]) / mean_s));
    while (w.p.size() < k) w.p.push_back(NAN), w.y.push_back(NAN), w.hold.push_back(-1), w.walk.push_back(0);
    const double end_t = t[b] + double(k + 1) * mean_s;
    double sp = 0, sy = 0;
    std::size_t n = 0, j = i;
    long hold = -2;
    bool walk = true;
    for (; j < e && (j == i || t[j] < end_t); ++j) {
      while (h < holds.size() && holds[h].end <= j) ++h;
      const long hj = h < holds.size() && holds[h].begin <= j ? static_cast<long>(h) : -1;
      if (hj >= 0) walk = false;
      hold = hold == -2 || hold == hj ? hj : -1;
      if (std::isfinite(p[j]) && std::isfinite(y[j])) sp += p[j], sy += y[j], ++n;
    }
    const bool ok = double(n) >= min_rows && n > 0;
    w.p.push_back(ok ? sp / double(n) : NAN);
    w.y.push_back(ok ? sy / double(n) : NAN);
    w.hold.push_back(hold < 0 ? -1 : hold);
    w.walk.push_back(walk ? 1 : 0);
    i = j;
  }
  return w;
}

// The moves and hold creep entries of one recording's windows.
void add_entries(const Windows& w, std::size_t short_lag, std::size_t long_lag, SlowErrors& e) {
  const std::size_t n = w.p.size();
  auto change_error = [&](std::size_t a, std::size_t b) { return (w.p[b] - w.p[a]) - (w.y[b] - w.y[a]); };
  for (std::size_t i = 0; i < n; ++i) {
    if (!w.walk[i] || !std::isfinite(w.p[i])) continue;
    for (const auto& [lag, out] : {std::pair<std::size_t, std::vector<double>*>{short_lag, &e.move_short},
                                   {long_lag, &e.move_long}})
      if (i + lag < n && w.walk[i + lag] && std::isfinite(w.p[i + lag])) out->push_back(std::fabs(change_error(i, i + lag)));
  }
  for (std::size_t i = 0; i < n;) {
    if (w.hold[i] < 0 || !std::isfinite(w.p[i])) {
      ++i;
      continue;
    }
    const std::size_t first = i;
    double last = NAN;
    for (++i; i < n && w.hold[i] == w.hold[first]; ++i)
      if (std::isfinite(w.p[i])) {
        last = change_error(first, i);
        e.hold_creep.push_back(std::fabs(last));
      }
    if (std::isfinite(last)) e.hold_end_creep.push_back(last);
  }
}

// Rows per window and entries per block of the paired test.
std::size_t entries_per_block(const SlowScoreOptions& o) {
  return std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(o.block_s / o.mean_s)));
}
}  // namespace

SlowErrors use_errors(const std::vector<double>& p, const std::vector<double>& r, const io::Dataset& data,
                      const std::string& axis, std::size_t from, const SlowScoreOptions& o) {
  if (!(o.mean_s > 0) || !(o.move_short_s >= o.mean_s) || !(o.move_long_s >= o.mean_s))
    throw std::invalid_argument("use errors: the window (mean_s) must be positive and no longer than the moves");
  SlowErrors e;
  const auto holds = voltage_holds(data, axis, from, o);
  const double rate = data.size() > 1 ? data.sample_rate_hz() : 1.0;
  const auto lag = [&](double s) { return static_cast<std::size_t>(std::lround(s / o.mean_s)); };
  const std::size_t n = std::min({p.size(), r.size(), data.size()});
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    const std::size_t b = std::max(rb, from), end = std::min(re, n);
    if (b >= end) continue;
    add_entries(window_means(p, r, data.time_s, b, end, holds, o.mean_s, rate), lag(o.move_short_s),
                lag(o.move_long_s), e);
  }
  return e;
}

SlowScore summarise_slow(const SlowErrors& b, const SlowScoreOptions& o) {
  SlowScore s;
  s.blocks = b;
  s.block = entries_per_block(o);
  s.noise_nm = o.noise_nm;
  s.move_short_nm = mean_of(b.move_short);
  s.move_long_nm = mean_of(b.move_long);
  s.hold_creep_nm = mean_of(b.hold_creep);
  std::vector<double> ends;
  for (double x : b.hold_end_creep) ends.push_back(std::fabs(x));
  s.worst_hold_creep_nm = max_of(ends);
  const double eps = std::max(o.noise_nm, 1e-3);
  double sum = 0;
  int n = 0;
  for (double x : {s.move_short_nm, s.move_long_nm, s.hold_creep_nm})
    if (std::isfinite(x)) sum += std::log(x + eps), ++n;
  s.overall_nm = n > 0 ? std::exp(sum / n) - eps : NAN;
  return s;
}

SlowScore slow_score(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                     const std::string& axis, const SlowScoreOptions& o, const std::vector<double>* warm_free_run) {
  const auto& ax = data.axis(axis);
  const std::vector<double> p = warm_free_run ? *warm_free_run : models::free_run_prediction(model, data, axis);
  SlowScore s = summarise_slow(use_errors(p, ax.position_nm, data, axis, score_from, o), o);
  if (ax.has_truth()) s.hold_creep_truth_nm = mean_of(use_errors(p, ax.true_position_nm, data, axis, score_from, o).hold_creep);
  return s;
}

std::string use_error_table(const std::vector<std::pair<std::string, const models::Model*>>& ms,
                            const io::Dataset& test, const std::string& axis, const SlowScoreOptions& o) {
  std::ostringstream os;
  os << "| model | 10-s moves [nm] | 60-s moves [nm] | hold creep [nm] | creep error per hold, first to last " << fmt(o.mean_s)
     << " s [nm] |\n|---|---:|---:|---:|---|\n";
  for (const auto& [name, m] : ms) {
    const SlowScore s = slow_score(*m, test, 0, axis, o);
    std::string holds;
    for (double x : s.blocks.hold_end_creep) holds += (holds.empty() ? "" : ", ") + fmt(x, 3);
    os << "| " << name << " | " << fmt(s.move_short_nm, 3) << " | " << fmt(s.move_long_nm, 3) << " | "
       << fmt(s.hold_creep_nm, 3) << " | " << (holds.empty() ? "no hold" : holds) << " |\n";
  }
  return os.str();
}

namespace {
struct Column {
  const char* name;
  const std::vector<double> SlowErrors::*v;
  double SlowScore::*mean;
};
const Column kColumns[] = {{"10-s moves", &SlowErrors::move_short, &SlowScore::move_short_nm},
                           {"60-s moves", &SlowErrors::move_long, &SlowScore::move_long_nm},
                           {"hold creep", &SlowErrors::hold_creep, &SlowScore::hold_creep_nm}};
}  // namespace

bool within_noise(const SlowScore& best, const SlowScore& other, std::vector<std::string>* worse) {
  bool within = true;
  for (const auto& c : kColumns) {
    const auto& a = best.blocks.*c.v;
    const auto& b = other.blocks.*c.v;
    if (a.empty() || b.empty()) continue;
    const std::size_t block = std::max(best.block, std::size_t{1});
    if ((other.*c.mean) - (best.*c.mean) > best.noise_nm && training::validation_prefers(a, b, block)) {
      within = false;
      if (worse) worse->push_back(c.name);
    }
  }
  return within;
}

namespace {
std::string nm(double x) { return std::isfinite(x) ? fmt(x, 3) + " nm" : std::string("–"); }

// Why the chosen candidate (the lowest overall) is not one with fewer parameters: the best of those, and the columns
// on which it is clearly worse.
std::string why_not_simpler(const std::vector<ChoiceEntry>& en, std::size_t chosen) {
  const ChoiceEntry& c = en[chosen];
  std::size_t s = SIZE_MAX;
  for (std::size_t k = 0; k < en.size(); ++k)
    if (en[k].score && en[k].score->valid() && en[k].parameters < c.parameters &&
        (s == SIZE_MAX || en[k].score->overall_nm < en[s].score->overall_nm))
      s = k;
  if (s == SIZE_MAX) return "; no candidate has fewer parameters";
  std::vector<std::string> worse;
  within_noise(*c.score, *en[s].score, &worse);
  std::ostringstream r;
  r << "; " << en[s].label << " (" << en[s].parameters << " parameters) is clearly worse on";
  for (std::size_t i = 0; i < worse.size(); ++i) {
    double v = NAN, mine = NAN;
    for (const auto& col : kColumns)
      if (worse[i] == col.name) v = (*en[s].score).*col.mean, mine = (*c.score).*col.mean;
    r << (i ? "," : "") << " " << worse[i] << " (" << nm(v) << " vs " << nm(mine) << ")";
  }
  return r.str();
}
}  // namespace

Choice choose_candidate(const std::vector<ChoiceEntry>& en) {
  Choice ch;
  for (std::size_t k = 0; k < en.size(); ++k)
    if (en[k].score && en[k].score->valid() &&
        (ch.best_overall == SIZE_MAX || en[k].score->overall_nm < en[ch.best_overall].score->overall_nm))
      ch.best_overall = k;
  if (ch.best_overall == SIZE_MAX) return ch;
  const ChoiceEntry& b = en[ch.best_overall];
  ch.chosen = ch.best_overall;
  for (std::size_t k = 0; k < en.size(); ++k) {
    if (k == ch.best_overall || !en[k].score || !en[k].score->valid()) continue;
    const ChoiceEntry& c = en[k];
    const ChoiceEntry& cur = en[ch.chosen];
    const bool simpler = c.parameters < cur.parameters ||
                         (c.parameters == cur.parameters && c.score->overall_nm < cur.score->overall_nm);
    if (simpler && within_noise(*b.score, *c.score)) ch.chosen = k;
  }
  const ChoiceEntry& c = en[ch.chosen];
  std::ostringstream r;
  if (ch.chosen != ch.best_overall)
    r << c.label << ": within the noise of " << b.label << " (lowest overall " << nm(b.score->overall_nm)
      << ") on every column, overall " << nm(c.score->overall_nm) << ", with " << c.parameters << " instead of "
      << b.parameters << " parameters";
  else
    r << c.label << ": lowest overall " << nm(c.score->overall_nm) << why_not_simpler(en, ch.chosen);
  ch.reason = r.str();
  return ch;
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
  if (!checked()) return "identification of " + label + ": not checked: " + (unchecked.empty() ? "no ratio" : unchecked);
  std::ostringstream os;
  os << "identification of " << label << ": fitted on the training part's first half it is " << fmt(carry_nm, 3)
     << " nm off (overall use error) on the second half, the whole fit " << fmt(validation_nm, 3)
     << " nm on the validation part (noise " << fmt(noise_nm, 2) << " nm): " << fmt(ratio(), 3) << "x";
  if (!flagged()) {
    os << " (<= " << fmt(kCarryOverAdvised) << ": the recording identifies it)";
  } else {
    os << ". Over " << fmt(kCarryOverAdvised) << "x the " << fmt(train_s, 3)
       << "-s training recording does not identify it: a separate recording is likely to be worse than the validation "
          "says. Record longer, sweeping the range the stage will be used over";
  }
  return os.str();
}

std::string unidentified_model_warning(const models::Model& model, const std::string& path) {
  const auto c = model.meta.validation.find("carry_over_ratio");
  if (c == model.meta.validation.end() || !(c->second > kCarryOverAdvised)) return {};
  return "model file " + path + ": its training recording did not identify it (fitted on the first half, " +
         fmt(c->second, 3) + "x worse on the second than on validation): expect larger errors than its validation "
         "figures; refit on a longer recording";
}

namespace {
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
    m = training::fit_model(r.candidate.kind, fit_request(rq, r.candidate, *rq.train, rq.validation, &lasso_cache));
    if (!m) throw std::runtime_error("the fit returned no model");
    m->meta.axis = rq.axis;
    m->meta.sample_rate_hz = rq.train->sample_rate_hz();
    r.parameters = m->num_parameters();
    SeriesPrediction p;
    r.score = score_validation_series(*m, *rq.score_data, rq.score_from, rq.axis, p);
    r.refused = sanity_problem(*m, &r.score, sel.scale);
    if (r.refused.empty()) r.slow = slow_score(*m, *rq.score_data, rq.score_from, rq.axis, sel.slow_options, &p.free_run);
  } catch (const std::exception& e) {
    r.refused = "kind " + r.candidate.kind + " refused: the fit failed: " + e.what();
  }
  r.fit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (r.refused.empty()) r.model = std::move(m);
  return r;
}
}  // namespace

SlowScoreOptions fitted_to_part(const SlowScoreOptions& o, const io::Dataset& data, std::size_t from) {
  double span = INFINITY;  // the shortest held-out recording
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    const std::size_t b = std::max(rb, from);
    if (b + 1 < re) span = std::min(span, data.time_s[re - 1] - data.time_s[b]);
  }
  const double f = std::isfinite(span) ? span / (kMovesPerPart * o.move_long_s) : 1.0;
  if (!(f < 1.0 - 1e-9) || !(f > 0.0)) return o;  // a part already scaled to keeps its options
  SlowScoreOptions s = o;
  s.mean_s *= f, s.move_short_s *= f, s.move_long_s *= f, s.block_s *= f;
  s.time_scale = o.time_scale * f;
  return s;
}

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
std::string cell(double x) { return std::isfinite(x) ? fmt(x, 3) : std::string("–"); }

std::string rule_text(const SlowScoreOptions& o) {
  return "each candidate fitted on the training part and run free over the held-out part, scored on the errors of "
         "the predicted change over " + fmt(o.move_short_s) + " s and " + fmt(o.move_long_s) + " s of the moves "
         "and of the creep in each hold from its start (" + fmt(o.mean_s) + "-s means, no zero needed); the fewest "
         "parameters among the candidates no column of which is clearly worse (paired test over " + fmt(o.block_s) +
         "-s blocks) than the lowest overall (geometric mean of the columns)";
}
}  // namespace

std::string selection_table(const Selection& s) {
  std::ostringstream os;
  const auto& o = s.slow_options;
  os << "Model choice (`--model auto`): " << rule_text(o) << ". Holds: the voltage unchanged >= " << fmt(o.hold_min_s)
     << " s";
  if (o.time_scale < 1.0)
    os << "; the held-out part is short: windows, moves and blocks scaled by " << fmt(o.time_scale, 3);
  if (std::isfinite(s.block_noise_nm)) os << "; noise of a change of " << fmt(o.mean_s) << "-s means ~" << fmt(s.block_noise_nm, 2) << " nm";
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
       << cell(w.overall_nm) << " | " << cell(r.score.finite && r.score.free_run.valid() ? r.score.free_run.mae_nm : NAN)
       << " | " << status << " |\n";
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
