#include "piezo_compensation/analysis/model_selection.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "piezo_compensation/analysis/evaluation.h"
#include "piezo_compensation/analysis/noise_floor.h"
#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"
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

// ---- the slow part of the error (issue 26) ----

std::vector<VoltageHold> voltage_holds(const io::Dataset& d, const std::string& axis, std::size_t from,
                                       const SlowScoreOptions& o) {
  std::vector<VoltageHold> out;
  const auto& v = d.axis(axis).voltage_v;
  const double dt = d.size() > 1 ? d.sample_period_s() : 1.0;
  std::size_t i = from;
  while (i < v.size()) {
    std::size_t j = i + 1;
    while (j < v.size() && std::fabs(v[j] - v[i]) <= o.hold_tolerance_v && !d.starts_recording(j)) ++j;
    if (double(j - i) * dt >= o.hold_min_s) out.push_back({i, j});
    i = j;
  }
  return out;
}

namespace {
// |mean(prediction − reference)| over each block of rows [b, e) (partial last block kept when ≥ half a block).
void add_blocks(const std::vector<double>& p, const std::vector<double>& r, std::size_t b, std::size_t e,
                std::size_t block, std::vector<double>& out) {
  block = std::max<std::size_t>(block, 1);
  e = std::min({e, p.size(), r.size()});
  for (std::size_t s = b; s < e; s += block) {
    const std::size_t t = std::min(e, s + block);
    if (2 * (t - s) < block) break;
    double sum = 0;
    std::size_t n = 0;
    for (std::size_t k = s; k < t; ++k)
      if (std::isfinite(p[k]) && std::isfinite(r[k])) sum += p[k] - r[k], ++n;
    if (n) out.push_back(std::fabs(sum / double(n)));
  }
}

double mean_of(const std::vector<double>& v) {
  if (v.empty()) return NAN;
  double s = 0;
  for (double x : v) s += x;
  return s / double(v.size());
}
double max_of(const std::vector<double>& v) { return v.empty() ? NAN : *std::max_element(v.begin(), v.end()); }
}  // namespace

std::vector<double> block_errors(const std::vector<double>& p, const std::vector<double>& r, std::size_t block) {
  std::vector<double> out;
  add_blocks(p, r, 0, std::min(p.size(), r.size()), block, out);
  return out;
}

SlowErrors slow_errors(const std::vector<double>& p, const std::vector<double>& r,
                       const std::vector<VoltageHold>& holds, std::size_t from, std::size_t block,
                       std::size_t hold_end) {
  SlowErrors e;
  const std::size_t n = std::min(p.size(), r.size());
  std::size_t at = std::min(from, n);
  for (const auto& h : holds) {
    const std::size_t hb = std::max(h.begin, at), he = std::min(h.end, n);
    if (hb >= he) continue;
    add_blocks(p, r, at, hb, block, e.moves);
    add_blocks(p, r, hb, he, block, e.holds);
    // The last hold_end rows of the hold (within the scored rows), one figure per hold.
    std::vector<double> end;
    const std::size_t w = std::max<std::size_t>(hold_end, 1);
    add_blocks(p, r, he - std::min(w, he - hb), he, w, end);
    if (!end.empty()) e.hold_ends.push_back(end.back());
    at = he;
  }
  add_blocks(p, r, at, n, block, e.moves);
  return e;
}

SlowScore summarise_slow(const SlowErrors& b, const SlowScoreOptions& o) {
  SlowScore s;
  s.blocks = b;
  s.moves_nm = mean_of(b.moves);
  s.holds_nm = mean_of(b.holds);
  s.hold_ends_nm = mean_of(b.hold_ends);
  s.worst_hold_end_nm = max_of(b.hold_ends);
  s.cold_nm = mean_of(b.cold);
  s.carry_nm = mean_of(b.carry);
  // Weighted geometric mean of (column + noise), less the noise: a column counts by its ratio between
  // candidates, not by its scale (a cold fold of 500 nm next to moves of 0.3 nm does not drown the moves), and
  // differences below the noise of a block mean count little.
  const double eps = std::max(o.noise_nm, 1e-3);
  double sum = 0, w = 0;
  for (const auto& [x, wt] : {std::pair<double, double>{s.moves_nm, 1.0}, {s.holds_nm, 1.0},
                              {s.hold_ends_nm, o.hold_end_weight}, {s.cold_nm, o.cold_weight},
                              {s.carry_nm, o.carry_weight}})
    if (std::isfinite(x)) sum += wt * std::log(x + eps), w += wt;
  s.overall_nm = w > 0 ? std::exp(sum / w) - eps : NAN;
  return s;
}

namespace {
// Rows per block: block_s at the data's rate, at most a 1/min_blocks share of the `scored` rows, at least one (the
// slow score's blocks, the carry-over fold's and the block noise select_model estimates).
std::size_t block_rows(const SlowScoreOptions& o, double rate_hz, std::size_t scored) {
  return std::max<std::size_t>(1, std::min<std::size_t>(static_cast<std::size_t>(std::lround(o.block_s * rate_hz)),
                                                        scored / std::max<std::size_t>(1, o.min_blocks)));
}

// How every column runs a model: free, a diverging prediction kept finite.
models::StreamOptions free_run() {
  models::StreamOptions so;
  so.mode = models::PredictionMode::kFreeRun;
  so.keep_diverging = true;
  return so;
}

// The held-out part as recordings of their own, as a model meets a new one: reset at rest at a start, scored
// after a window of cold_window_s (at most a fifth of the part), to the part's end; with cold_start_estimate the
// window also fixes the start estimate (models::StreamOptions::anchor_s). Several starts (cold_starts, spread
// over the part's first half): one start state is one draw, and on a 10-s part one lucky draw decided (the KAN
// on the 50-µm stages: docs/models.md).
std::vector<double> cold_fold(const models::Model& model, const io::Dataset& tail, const std::string& axis,
                              const SlowScoreOptions& o, std::size_t block) {
  models::StreamOptions so = free_run();
  const double span_s = tail.size() > 1 ? tail.time_s.back() - tail.time_s.front() : 0.0;
  const double window_s = std::min(o.cold_window_s, span_s / 5.0);
  if (o.cold_start_estimate) so.anchor_s = window_s;
  const std::size_t starts = static_cast<std::size_t>(std::max(1, o.cold_starts));
  std::vector<double> out;
  for (std::size_t k = 0; k < starts; ++k) {
    const io::Dataset part = tail.slice(tail.size() * k / (2 * starts), tail.size());
    auto m = model.clone();
    const models::StreamResult r = models::stream_model(*m, part, axis, so);
    const auto& y = part.axis(axis).position_nm;
    std::size_t from = r.first_scored;
    while (from < y.size() && part.time_s[from] - part.time_s[0] < window_s) ++from;
    const auto f = static_cast<std::ptrdiff_t>(from);
    const auto e = block_errors(std::vector<double>(r.prediction.begin() + f, r.prediction.end()),
                                std::vector<double>(y.begin() + f, y.end()), block);
    out.insert(out.end(), e.begin(), e.end());
  }
  return out;
}
}  // namespace

namespace {
// Several recordings: each one's zero is unknown to any model (an encoder reset per run), so it is taken out of
// `pred` (the mean of measured − predicted over its rows from `from` on) and the blocks score the rest.
void take_out_recording_zeros(const io::Dataset& data, const std::string& axis, std::size_t from, std::vector<double>& pred) {
  if (data.recording_count() < 2) return;
  const std::vector<double> d = models::recording_offsets(data, axis, pred, from);
  for (std::size_t k = 0; k < d.size(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    for (std::size_t i = rb; i < re; ++i) pred[i] += d[k];
  }
}

// Several recordings: each hold's rows shifted by the mean of measured − predicted over its first `window` rows.
void take_out_hold_zeros(const io::Dataset& data, const std::string& axis, const std::vector<VoltageHold>& holds,
                         double window, std::vector<double>& pred) {
  if (data.recording_count() < 2 || !(window >= 1.0)) return;
  const auto& y = data.axis(axis).position_nm;
  for (const auto& h : holds) {
    const std::size_t e = std::min(h.end, pred.size()), z = std::min(e, h.begin + static_cast<std::size_t>(window));
    if (z <= h.begin) continue;
    double d = 0;
    for (std::size_t i = h.begin; i < z; ++i) d += (y[i] - pred[i]) / static_cast<double>(z - h.begin);
    for (std::size_t i = h.begin; i < e; ++i) pred[i] += d;
  }
}
}  // namespace

SlowScore slow_score(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                     const std::string& axis, const SlowScoreOptions& o, const std::vector<double>* warm_free_run) {
  const auto& ax = data.axis(axis);
  const double rate = data.size() > 1 ? data.sample_rate_hz() : 1.0;
  const std::size_t scored = data.size() > score_from ? data.size() - score_from : 0;
  const std::size_t block = block_rows(o, rate, scored);
  const std::size_t hold_end = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(o.hold_end_s * rate)));
  std::vector<double> warm = warm_free_run ? *warm_free_run : models::free_run_prediction(model, data, axis);
  take_out_recording_zeros(data, axis, score_from, warm);
  const auto holds = voltage_holds(data, axis, score_from, o);
  take_out_hold_zeros(data, axis, holds, o.hold_zero_s * rate, warm);
  SlowErrors e = slow_errors(warm, ax.position_nm, holds, score_from, block, hold_end);
  if (score_from < data.size()) e.cold = cold_fold(model, data.slice(score_from, data.size()), axis, o, block);
  SlowScore s = summarise_slow(e, o);
  s.block_s = double(block) / rate;
  if (ax.has_truth()) {
    const SlowErrors t = slow_errors(warm, ax.true_position_nm, holds, score_from, block, hold_end);
    s.hold_ends_truth_nm = mean_of(t.hold_ends);
    s.worst_hold_end_truth_nm = max_of(t.hold_ends);
  }
  return s;
}

std::vector<double> carry_over_errors(const models::Model& half_fit, const io::Dataset& train, std::size_t half,
                                      const std::string& axis, const SlowScoreOptions& o) {
  if (half >= train.size()) return {};
  std::vector<double> p = models::free_run_prediction(half_fit, train, axis);
  take_out_recording_zeros(train, axis, half, p);
  const auto& y = train.axis(axis).position_nm;
  const std::size_t block = block_rows(o, train.size() > 1 ? train.sample_rate_hz() : 1.0, train.size() - half);
  const auto h = static_cast<std::ptrdiff_t>(half);
  return block_errors(std::vector<double>(p.begin() + h, p.end()), std::vector<double>(y.begin() + h, y.end()), block);
}

namespace {
struct Column {
  const char* name;
  const std::vector<double> SlowErrors::*v;
  double SlowScore::*mean;
};
const Column kColumns[] = {{"moves", &SlowErrors::moves, &SlowScore::moves_nm},
                           {"holds", &SlowErrors::holds, &SlowScore::holds_nm},
                           {"hold ends", &SlowErrors::hold_ends, &SlowScore::hold_ends_nm},
                           {"cold fold", &SlowErrors::cold, &SlowScore::cold_nm},
                           {"carry-over", &SlowErrors::carry, &SlowScore::carry_nm}};
}  // namespace

bool within_noise(const SlowScore& best, const SlowScore& other, std::vector<std::string>* worse) {
  bool within = true;
  for (const auto& c : kColumns) {
    const auto& a = best.blocks.*c.v;
    const auto& b = other.blocks.*c.v;
    if (a.empty() || b.empty()) continue;
    // Per block (block = 1 entry): the paired test over the columns' block errors; under four blocks the lower
    // mean decides, as the test does.
    if (training::validation_prefers(a, b, 1)) {
      within = false;
      if (worse) worse->push_back(c.name);
    }
  }
  return within;
}

std::vector<std::string> cold_start_exclusions(const std::vector<const SlowScore*>& scores, double position_range_nm) {
  std::vector<std::string> out(scores.size());
  const double limit = kMaxColdFoldFraction * position_range_nm;
  if (!(limit > 0)) return out;
  const bool any_within = std::any_of(scores.begin(), scores.end(), [&](const SlowScore* s) {
    return s && std::isfinite(s->cold_nm) && s->cold_nm <= limit;
  });
  if (!any_within) return out;
  for (std::size_t k = 0; k < scores.size(); ++k)
    if (scores[k] && std::isfinite(scores[k]->cold_nm) && scores[k]->cold_nm > limit)
      out[k] = "cold start off: cold fold " + std::to_string(std::lround(scores[k]->cold_nm)) + " nm > " +
               fmt(100 * kMaxColdFoldFraction, 2) + " % of the position range (" +
               std::to_string(std::lround(position_range_nm)) + " nm)";
  return out;
}

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
  auto nm = [](double x) { return std::isfinite(x) ? fmt(x, 3) + " nm" : std::string("–"); };
  std::ostringstream r;
  if (ch.chosen != ch.best_overall) {
    r << c.label << ": within the noise of " << b.label << " on every column (overall " << nm(c.score->overall_nm)
      << " vs " << nm(b.score->overall_nm) << ") with " << c.parameters << " instead of " << b.parameters
      << " parameters";
  } else {
    const bool ends = std::isfinite(c.score->hold_ends_nm);
    r << c.label << ": lowest overall slow error " << nm(c.score->overall_nm);
    if (ends) r << ", hold ends " << nm(c.score->hold_ends_nm);
    // The best simpler candidate, and where it falls short.
    std::size_t s = SIZE_MAX;
    for (std::size_t k = 0; k < en.size(); ++k)
      if (en[k].score && en[k].score->valid() && en[k].parameters < c.parameters &&
          (s == SIZE_MAX || en[k].score->overall_nm < en[s].score->overall_nm))
        s = k;
    if (s != SIZE_MAX) {
      std::vector<std::string> worse;
      within_noise(*c.score, *en[s].score, &worse);
      std::vector<std::string> ok;
      for (const auto& col : kColumns)
        if (!(c.score->blocks.*col.v).empty() && !(en[s].score->blocks.*col.v).empty() &&
            std::find(worse.begin(), worse.end(), col.name) == worse.end())
          ok.push_back(col.name);
      r << "; " << en[s].label << " (" << en[s].parameters << " parameters)";
      if (!ok.empty()) {
        r << " within noise on ";
        for (std::size_t i = 0; i < ok.size(); ++i) r << (i ? (i + 1 == ok.size() ? " and " : ", ") : "") << ok[i];
        r << " but";
      } else {
        r << ":";
      }
      for (std::size_t i = 0; i < worse.size(); ++i) {
        double v = NAN;
        for (const auto& col : kColumns)
          if (worse[i] == col.name) v = (*en[s].score).*col.mean;
        r << (i ? "," : "") << " " << nm(v) << " on " << worse[i];
      }
    } else {
      r << "; no candidate has fewer parameters";
    }
  }
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
  c.push_back({"linear (lasso features)", "linear", YAML::Node(), true});
  c.push_back({"pi", "pi", YAML::Node(), false});
  // pi_creep_play is opt-in (--auto-extra pi_creep_play): on the simulated stages its choice does not carry over
  // to a separate recording (docs/validation/pi_creep_play.md).
  for (const auto& k : models::model_kind_names())
    if (k.rfind("pi_creep_", 0) == 0 && k != "pi_creep_play") c.push_back({k, k, YAML::Node(), false});
  for (const auto& k : models::model_kind_names())
    if (k.rfind("preisach", 0) == 0) c.push_back({k, k, YAML::Node(), false});
  // The KAN on its default features, on a fixed step budget (deterministic, bounded time); why it is a candidate:
  // docs/models.md, "The stage matrix".
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

namespace {
// `s` summarised again from `blocks` (its block length and truth figures kept).
void rescore(SlowScore& s, const SlowErrors& blocks, const SlowScoreOptions& o) {
  SlowScore t = summarise_slow(blocks, o);
  t.block_s = s.block_s;
  t.hold_ends_truth_nm = s.hold_ends_truth_nm;
  t.worst_hold_end_truth_nm = s.worst_hold_end_truth_nm;
  s = t;
}

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

// The carry-over fold of one candidate (SlowScoreOptions::carry_fold): the kind fitted again on rows [0, half) of
// the training part alone (their last fifth the fit's validation when the selection has one; the lasso candidate's
// features chosen again on them), scored on the second half. A fit that fails or returns nothing there leaves the
// column empty (align_carry_over then drops it for every candidate).
void add_carry_over(const SelectionRequest& rq, const ModelCandidate& c, const SlowScoreOptions& o, SlowScore& s,
                    training::LassoFeatureCache* lasso_cache) {
  const io::Dataset& train = *rq.train;
  std::size_t half = train.size() / 2;
  if (train.recording_count() > 1) {  // whole recordings on either side: the recording starting nearest the middle
    std::size_t best = 0;
    for (std::size_t k = 1; k < train.recording_count(); ++k) {
      const std::size_t b = train.recording_rows(k).first;
      if (best == 0 || (b > half ? b - half : half - b) < (best > half ? best - half : half - best)) best = b;
    }
    half = best;
  }
  if (!o.carry_fold || half < 2 * static_cast<std::size_t>(std::max(1, o.min_blocks))) return;
  const io::Dataset first = train.slice(0, half);
  const std::size_t fit_rows = rq.validation ? half * 4 / 5 : half;
  const io::Dataset fit_part = first.slice(0, fit_rows), val_part = first.slice(fit_rows, half);
  SlowErrors b = s.blocks;
  try {
    ModelCandidate half_c = c;
    if (c.lasso_features) {  // the features chosen again on the half; the candidate's other options kept
      half_c.options = c.options && c.options.IsMap() ? YAML::Clone(c.options) : YAML::Node(YAML::NodeType::Map);
      half_c.options["features"] = lasso_linear_options(fit_part, rq.axis, {})["features"];
    }
    const models::ModelPtr m =
        training::fit_model(c.kind, fit_request(rq, half_c, fit_part, rq.validation ? &val_part : nullptr, lasso_cache));
    if (!m) return;
    b.carry = carry_over_errors(*m, train, half, rq.axis, o);
  } catch (const std::exception&) {
    return;
  }
  rescore(s, b, o);
}

}  // namespace

double estimate_block_noise(const SelectionRequest& rq) {
  if (rq.slow.noise_nm > 0.0) return rq.slow.noise_nm;
  if (!rq.score_data || rq.score_data->size() <= rq.score_from) return NAN;
  // The noise of a block mean, from the validation part's readings (σ/√samples per block).
  try {
    const io::Dataset tail = rq.score_data->slice(rq.score_from, rq.score_data->size());
    const NoiseFloor nf = estimate_noise_floor(tail, rq.axis);
    const double rate = tail.size() > 1 ? tail.sample_rate_hz() : 1.0;
    const double rows = static_cast<double>(block_rows(rq.slow, rate, tail.size()));
    return std::max(nf.sigma_nm, nf.quantisation_nm / std::sqrt(12.0)) / std::sqrt(rows);
  } catch (const std::exception&) {
    return NAN;  // too few samples for a noise figure
  }
}

Identification identification(const SlowScore& s, double block_noise_nm) {
  Identification id;
  if (s.blocks.carry.empty()) {
    id.unchecked = "no carry-over figure (a training part too short for the fold, or a half fit that failed)";
    return id;
  }
  id.carry_nm = s.carry_nm;
  id.moves_nm = s.moves_nm;
  id.noise_nm = std::isfinite(block_noise_nm) && block_noise_nm > 0.0 ? block_noise_nm : 0.0;
  if (!id.checked()) id.unchecked = "no moves in the validation part to compare with";
  return id;
}

Identification check_identification(const SelectionRequest& rq, const ModelCandidate& c, const models::Model& fitted) {
  Identification id;
  if (!rq.train || !rq.score_data || rq.score_data->size() <= rq.score_from) {
    id.unchecked = "no validation part";
    return id;
  }
  try {
    SlowScoreOptions o = rq.slow;
    o.carry_fold = true;
    const double noise = estimate_block_noise(rq);
    if (std::isfinite(noise) && noise > 0.0) o.noise_nm = noise;
    SlowScore s = slow_score(fitted, *rq.score_data, rq.score_from, rq.axis, o);
    add_carry_over(rq, c, o, s, nullptr);
    return identification(s, noise);
  } catch (const std::exception& e) {
    id.unchecked = std::string("the check failed: ") + e.what();
    return id;
  }
}

std::string Identification::describe(const std::string& label, double train_s) const {
  if (!checked()) return "identification of " + label + ": not checked: " + (unchecked.empty() ? "no ratio" : unchecked);
  std::ostringstream os;
  os << "identification of " << label << ": fitted on the training part's first half it is " << fmt(carry_nm, 3)
     << " nm off (block means) on the second half, the whole fit " << fmt(moves_nm, 3)
     << " nm on the validation part's moves (block noise " << fmt(noise_nm, 2) << " nm): " << fmt(ratio(), 3) << "x";
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

void align_carry_over(std::vector<CandidateResult>& table, const SlowScoreOptions& o) {
  bool all = true;
  for (const auto& r : table)
    if (r.refused.empty() && r.slow.valid() && r.slow.blocks.carry.empty()) all = false;
  if (all) return;
  for (auto& r : table)
    if (!r.slow.blocks.carry.empty()) {
      SlowErrors b = r.slow.blocks;
      b.carry.clear();
      rescore(r.slow, b, o);
    }
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
    if (r.refused.empty()) {
      r.slow = slow_score(*m, *rq.score_data, rq.score_from, rq.axis, sel.slow_options, &p.free_run);
      add_carry_over(rq, r.candidate, sel.slow_options, r.slow, &lasso_cache);
    }
  } catch (const std::exception& e) {
    r.refused = "kind " + r.candidate.kind + " refused: the fit failed: " + e.what();
  }
  r.fit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (r.refused.empty()) r.model = std::move(m);
  return r;
}

// The choice over the table as it stands: carry-over aligned, cold starts far off excluded (recorded per row).
Choice choose_from(Selection& sel) {
  align_carry_over(sel.table, sel.slow_options);
  std::vector<const SlowScore*> scored;
  for (const auto& r : sel.table) scored.push_back(r.refused.empty() && r.slow.valid() ? &r.slow : nullptr);
  const std::vector<std::string> cold_off = cold_start_exclusions(scored, sel.scale.position_range_nm);
  std::vector<ChoiceEntry> entries;
  for (std::size_t k = 0; k < sel.table.size(); ++k) {
    sel.table[k].cold_start_off = cold_off[k];
    entries.push_back({sel.table[k].candidate.label, sel.table[k].parameters, cold_off[k].empty() ? scored[k] : nullptr});
  }
  return choose_candidate(entries);
}

// The chosen PI or Preisach kind with its output map (the loop's static bend, models/pi_model.h), when it was fitted
// without one: a further candidate, chosen by the same rule (its two more parameters lose to the plain kind within
// the noise).
bool output_map_candidate(const CandidateResult& chosen, ModelCandidate& out) {
  if (!chosen.model || !dynamic_cast<const models::PiCreepModel*>(chosen.model.get())) return false;
  const auto it = chosen.model->meta.validation.find("fit_output_map");
  if (it != chosen.model->meta.validation.end() && it->second > 0) return false;
  if (chosen.candidate.options && chosen.candidate.options.IsMap() && chosen.candidate.options["output_map"]) return false;
  out = chosen.candidate;
  out.label += " + output map";
  out.options = chosen.candidate.options && chosen.candidate.options.IsMap() ? YAML::Clone(chosen.candidate.options)
                                                                            : YAML::Node(YAML::NodeType::Map);
  out.options["output_map"] = "on";
  return true;
}
}  // namespace

Selection select_model(const SelectionRequest& rq) {
  if (!rq.train || !rq.score_data) throw std::invalid_argument("model selection: no training or validation data");
  if (rq.score_data->size() <= rq.score_from)
    throw std::invalid_argument("model selection needs validation samples (use --split < 1 or --validation)");
  Selection sel;
  sel.scale = data_scale(*rq.train, rq.axis);
  sel.slow_options = rq.slow;
  sel.block_noise_nm = estimate_block_noise(rq);
  if (std::isfinite(sel.block_noise_nm) && sel.block_noise_nm > 0.0) sel.slow_options.noise_nm = sel.block_noise_nm;
  const std::vector<ModelCandidate> cands = rq.candidates.empty() ? default_candidates() : rq.candidates;
  // The neural candidates' voltage_lasso is resolved once on the training part and once on its half (the fold's own).
  training::LassoFeatureCache lasso_cache;
  for (std::size_t k = 0; k < cands.size(); ++k) {
    if (rq.progress) rq.progress(double(k), double(cands.size()), "fitting " + cands[k].label);
    sel.table.push_back(fit_candidate(rq, cands[k], sel, lasso_cache));
  }
  Choice ch = choose_from(sel);
  ModelCandidate mapped;
  if (ch.chosen != SIZE_MAX && output_map_candidate(sel.table[ch.chosen], mapped)) {
    if (rq.progress) rq.progress(double(cands.size()), double(cands.size()), "fitting " + mapped.label);
    sel.table.push_back(fit_candidate(rq, mapped, sel, lasso_cache));
    ch = choose_from(sel);
  }
  if (ch.chosen == SIZE_MAX) {
    std::string why = "model selection: every candidate was refused:";
    for (const auto& r : sel.table)
      why += "\n  " + (r.refused.empty() ? r.candidate.label + ": no slow-error score (too few validation samples)"
                                          : r.refused);
    throw FitRejected(why);
  }
  sel.best = ch.chosen;
  sel.best_overall = ch.best_overall;
  sel.reason = ch.reason;
  sel.model = sel.table[sel.best].model->clone();
  store_validation(sel.table[sel.best].score, *sel.model);
  sel.identification = identification(sel.table[sel.best].slow, sel.block_noise_nm);
  if (sel.identification.checked()) sel.model->meta.validation["carry_over_ratio"] = sel.identification.ratio();
  sel.model->meta.selection = selection_yaml(sel);
  return sel;
}

namespace {
std::string cell(double x) { return std::isfinite(x) ? fmt(x, 3) : std::string("–"); }

// Whether the carry-over fold scored the candidates (off, a short training part, or a half fit that failed: not).
bool carry_ran(const Selection& s) {
  return std::any_of(s.table.begin(), s.table.end(), [](const CandidateResult& r) { return !r.slow.blocks.carry.empty(); });
}
}  // namespace

std::string selection_table(const Selection& s) {
  std::ostringstream os;
  const auto& o = s.slow_options;
  const double block_s = s.table.empty() || !std::isfinite(s.table[s.best].slow.block_s) ? o.block_s
                                                                                         : s.table[s.best].slow.block_s;
  os << "Model choice (`--model auto`): each candidate fitted on the training part and run free over the validation\n"
        "part; scored on the slow part of the error, |mean(predicted - measured)| of " << fmt(block_s) << "-s blocks";
  if (std::isfinite(s.block_noise_nm)) os << " (reading noise of a block mean ~" << fmt(s.block_noise_nm, 2) << " nm)";
  os << ":\nmoves, holds (voltage unchanged >= " << fmt(o.hold_min_s) << " s), hold ends (last " << fmt(o.hold_end_s)
     << " s of each hold), cold fold\n(the validation part alone, " << o.cold_starts << " starts from rest, scored after "
     << fmt(o.cold_window_s) << " s at most" << (o.cold_start_estimate ? " with the start estimate there" : "")
     << ")" << (carry_ran(s) ? ", carry-over\n(fitted again on the training part's first half, scored on its second half)" : "")
     << "; overall = weighted geometric mean of (column + block noise), less the\n"
        "noise (hold ends x" << fmt(o.hold_end_weight) << ", cold fold x" << fmt(o.cold_weight)
     << (carry_ran(s) ? ", carry-over x" + fmt(o.carry_weight) : std::string()) << "). Lowest overall, then the fewest parameters\namong the candidates within the noise "
        "of it (paired block test on every column). Position range "
     << fmt(s.scale.position_range_nm, 4) << " nm.\n\n";
  os << "| kind | parameters | moves [nm] | holds [nm] | hold ends [nm] | cold fold [nm] | carry-over [nm] | overall [nm] | status |\n";
  os << "|---|---:|---:|---:|---:|---:|---:|---:|---|\n";
  for (std::size_t k = 0; k < s.table.size(); ++k) {
    const auto& r = s.table[k];
    const auto& w = r.slow;
    std::string status = r.refused.empty() ? r.cold_start_off : r.refused;
    if (status.empty()) {
      if (s.model && k == s.best) status = "**chosen**";
      else if (k == s.best_overall) status = "lowest overall";
    }
    os << "| " << r.candidate.label << " | " << r.parameters << " | " << cell(w.moves_nm) << " | " << cell(w.holds_nm)
       << " | " << cell(w.hold_ends_nm) << " | " << cell(w.cold_nm) << " | " << cell(w.carry_nm) << " | "
       << cell(w.overall_nm) << " | " << status
       << " |\n";
  }
  if (!s.reason.empty()) os << "\nChoice: " << s.reason << "\n";
  return os.str();
}

YAML::Node selection_yaml(const Selection& s) {
  YAML::Node n;
  const auto& o = s.slow_options;
  n["criterion"] = "slow part of the error: |mean(predicted - measured)| of " + fmt(o.block_s) +
                   "-s blocks on moves, holds, hold ends (x" + fmt(o.hold_end_weight) +
                   ") and a cold fold (x" + fmt(o.cold_weight) + ", " + std::to_string(o.cold_starts) + " starts from rest, scored after at most " +
                   fmt(o.cold_window_s) + " s" + (o.cold_start_estimate ? " with the start estimate there" : "") + ")" +
                   (carry_ran(s) ? " and a carry-over fold (x" + fmt(o.carry_weight) + ", the kind fitted again on the training part's first half, scored on its second half)" : std::string()) +
                   "; overall = weighted geometric mean of (column + block noise) less the noise; "
                   "lowest overall, then the fewest parameters within the noise of it "
                   "(paired block test on every column), among the candidates passing the gates";
  if (!s.table.empty()) {
    n["chosen"] = s.table[s.best].candidate.label;
    n["chosen_kind"] = s.table[s.best].candidate.kind;
    n["lowest_overall"] = s.table[s.best_overall].candidate.label;
  }
  n["reason"] = s.reason;
  n["block_s"] = s.table.empty() || !std::isfinite(s.table[s.best].slow.block_s) ? o.block_s
                                                                                : s.table[s.best].slow.block_s;
  n["hold_min_s"] = o.hold_min_s;
  n["hold_end_s"] = o.hold_end_s;
  n["hold_end_weight"] = o.hold_end_weight;
  if (std::isfinite(s.block_noise_nm)) n["block_noise_nm"] = s.block_noise_nm;
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
    put("moves_nm", w.moves_nm);
    put("holds_nm", w.holds_nm);
    put("hold_ends_nm", w.hold_ends_nm);
    put("worst_hold_end_nm", w.worst_hold_end_nm);
    put("cold_fold_nm", w.cold_nm);
    put("carry_over_nm", w.carry_nm);
    put("overall_nm", w.overall_nm);
    put("hold_ends_vs_truth_nm", w.hold_ends_truth_nm);
    put("worst_hold_end_vs_truth_nm", w.worst_hold_end_truth_nm);
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
