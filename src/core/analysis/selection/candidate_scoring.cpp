// Scoring one fitted candidate: its free-run validation score, the sanity gates on its parameters, and the errors
// the use cares about (moves and hold creep) that `--model auto` chooses by (analysis/selection/model_selection.h).
#include "piezo_compensation/analysis/selection/model_selection.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/util/format.h"

namespace piezo::analysis {

namespace {

bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
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
                                 const std::string& axis, SeriesPrediction* prediction) {
  SeriesPrediction local;
  SeriesPrediction& p = prediction ? *prediction : local;
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
      return who + "free-run validation MAE " + util::fmt(score->free_run.mae_nm, 3) + " nm is " +
             util::fmt(100.0 * score->free_run.mae_nm / range, 3) + " % of the data's position range (" +
             util::fmt(range, 3) + " nm; the gate is " + util::fmt(100.0 * kMaxFreeRunErrorOfRange, 3) +
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
      problem = who + "parameter " + path + " = " + util::fmt(v, 3) + " nm is " +
                util::fmt(std::fabs(v) / std::max(range, 1e-9), 3) + " times the data's position range (" +
                util::fmt(range, 3) +
                " nm): large cancelling terms; likely cause: positions in other units than nm, or too short a "
                "recording to separate the terms";
    } else if (ends_with(key, "_nm_per_v") && range > 0.0 && std::fabs(v) * scale.voltage_span_v > 10.0 * range) {
      problem = who + "parameter " + path + " = " + util::fmt(v, 3) + " nm/V moves " +
                util::fmt(std::fabs(v) * scale.voltage_span_v, 3) + " nm over the data's " +
                util::fmt(scale.voltage_span_v, 3) + " V span, " +
                util::fmt(std::fabs(v) * scale.voltage_span_v / range, 3) + " times the position range (" +
                util::fmt(range, 3) +
                " nm): cancelling weights; likely cause: voltage or position in other units, or "
                "too few distinct voltages in the recording";
    } else if (key.find("tau") != std::string::npos && ends_with(key, "_s") && scale.duration_s > 0.0 &&
               v > 10.0 * scale.duration_s) {
      problem = who + "time constant " + path + " = " + util::fmt(v, 3) + " s, but the training data lasts " +
                util::fmt(scale.duration_s, 3) + " s: the data cannot identify it; likely cause: too short a recording "
                "for this creep model (use a longer one or a kind without slow creep)";
    }
  });
  return problem;
}

void check_fit_sanity(const models::Model& model, const ValidationScore* score, const DataScale& scale) {
  const std::string p = sanity_problem(model, score, scale);
  if (!p.empty()) throw FitRejected(p);
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
      if (i + lag < n && w.walk[i + lag] && std::isfinite(w.p[i + lag]))
        out->push_back(std::fabs(change_error(i, i + lag)));
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
  if (ax.has_truth())
    s.hold_creep_truth_nm = mean_of(use_errors(p, ax.true_position_nm, data, axis, score_from, o).hold_creep);
  return s;
}

std::string use_error_table(const std::vector<std::pair<std::string, const models::Model*>>& ms,
                            const io::Dataset& test, const std::string& axis, const SlowScoreOptions& o) {
  std::ostringstream os;
  os << "| model | 10-s moves [nm] | 60-s moves [nm] | hold creep [nm] | creep error per hold, first to last "
     << util::fmt(o.mean_s, 3) << " s [nm] |\n|---|---:|---:|---:|---|\n";
  for (const auto& [name, m] : ms) {
    const SlowScore s = slow_score(*m, test, 0, axis, o);
    std::string holds;
    for (double x : s.blocks.hold_end_creep) holds += (holds.empty() ? "" : ", ") + util::fmt(x, 3);
    os << "| " << name << " | " << util::fmt(s.move_short_nm, 3) << " | " << util::fmt(s.move_long_nm, 3) << " | "
       << util::fmt(s.hold_creep_nm, 3) << " | " << (holds.empty() ? "no hold" : holds) << " |\n";
  }
  return os.str();
}

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

}  // namespace piezo::analysis
