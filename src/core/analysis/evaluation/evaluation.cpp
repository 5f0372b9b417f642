#include "piezo_compensation/analysis/evaluation/evaluation.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::analysis {

namespace {
constexpr int kHold = static_cast<int>(protocols::Phase::kHold);
}

std::vector<Hold> find_holds(const io::Dataset& d, double min_duration_s) {
  std::vector<Hold> out;
  if (d.axes.empty() || d.size() < 2) return out;
  io::HoldRule rule;
  rule.min_duration_s = std::max(min_duration_s, kVoltageHoldMinS);
  rule.min_marked_s = min_duration_s;
  const double dt = d.sample_period_s();
  for (const io::HoldRun& h : io::find_holds(d, d.axes.front().name, rule))
    out.push_back({h.begin, h.end, h.segment, double(h.end - h.begin) * dt});
  return out;
}

void check_model_for_eval(const models::Model& model, const std::string& path, const std::string& axis,
                          const io::Dataset& test, const io::Dataset* creep) {
  models::check_model_matches_data(model, test, path, axis);
  if (creep && !creep->empty()) models::check_model_matches_data(model, *creep, path, axis);
}

SeriesPrediction predict_series(const models::Model& model, const io::Dataset& d, const std::string& axis,
                                double anchor_s, bool anchor_history) {
  SeriesPrediction p;
  if (d.empty()) return p;
  models::StreamOptions so;
  so.anchor_s = anchor_s;
  so.anchor_history = anchor_history;
  so.mode = models::PredictionMode::kOneStep;
  auto one = model.clone();
  const models::StreamResult r1 = models::stream_model(*one, d, axis, so);
  p.one_step = r1.prediction;
  p.first_scored = r1.first_scored;
  p.scored = models::scored_mask(r1, d.size());
  p.one_step_offset_nm = r1.anchor_offset_nm;
  p.start = r1.start;
  if (!model.uses_position_history()) {
    p.free_run = p.one_step;  // no position history: the two modes are the same computation
    p.free_run_offset_nm = p.one_step_offset_nm;
    return p;
  }
  so.mode = models::PredictionMode::kFreeRun;
  so.keep_diverging = true;  // a diverging free-run is a result, not an error
  auto free = model.clone();
  const models::StreamResult r2 = models::stream_model(*free, d, axis, so);
  p.free_run = r2.prediction;
  p.free_run_offset_nm = r2.anchor_offset_nm;
  p.start = r2.start;
  return p;
}

namespace {
bool in_segments(const io::Dataset& d, std::size_t i, const std::vector<int>& segments) {
  if (segments.empty()) return true;
  if (d.segment.empty()) return false;
  return std::find(segments.begin(), segments.end(), d.segment[i]) != segments.end();
}
}  // namespace

std::vector<int> parse_segments(const std::string& list) {
  std::vector<int> out;
  std::size_t pos = 0;
  while (pos <= list.size()) {
    const std::size_t comma = std::min(list.find(',', pos), list.size());
    const std::string part = list.substr(pos, comma - pos);
    int a = 0, b = 0;
    char extra = 0;
    if (std::sscanf(part.c_str(), "%d-%d%c", &a, &b, &extra) == 2 && a <= b) {
      for (int k = a; k <= b; ++k) out.push_back(k);
    } else if (std::sscanf(part.c_str(), "%d%c", &a, &extra) == 1) {
      out.push_back(a);
    } else {
      throw std::invalid_argument("segment list '" + list + "': cannot read '" + part + "' (use e.g. 2 or 3-17)");
    }
    pos = comma + 1;
  }
  return out;
}

std::vector<char> hold_mask(const io::Dataset& d, const std::vector<int>& segments) {
  std::vector<char> m(d.size(), 0);
  for (const auto& h : find_holds(d))
    for (std::size_t i = h.begin; i < h.end; ++i) m[i] = in_segments(d, i, segments);
  return m;
}

std::vector<char> hysteresis_mask(const io::Dataset& d, double warmup_s, const std::vector<int>& segments) {
  std::vector<char> m(d.size(), 1);
  for (std::size_t i = 0; i < d.size(); ++i)
    m[i] = (d.phase.empty() || d.phase[i] != kHold) && in_segments(d, i, segments);
  for (std::size_t k = 0; k < d.recording_count(); ++k) {  // each recording's own warm-up
    const auto [b, e] = d.recording_rows(k);
    for (std::size_t i = b; i < e && d.time_s[i] - d.time_s[b] < warmup_s; ++i) m[i] = 0;
  }
  return m;
}

namespace {
SetMetrics metrics(const SeriesPrediction& p, const io::AxisSeries& ax, const std::vector<char>& mask) {
  SetMetrics s;
  s.one_step.vs_measured = error_stats(p.one_step, ax.position_nm, mask);
  s.free_run.vs_measured = error_stats(p.free_run, ax.position_nm, mask);
  if (ax.has_truth()) {
    s.one_step.vs_truth = error_stats(p.one_step, ax.true_position_nm, mask);
    s.free_run.vs_truth = error_stats(p.free_run, ax.true_position_nm, mask);
  }
  return s;
}
double hold_mean(const std::vector<double>& v, std::size_t b, std::size_t e) {
  if (v.empty() || b >= e) return NAN;
  double s = 0;
  for (std::size_t i = b; i < e; ++i) s += v[i];
  return s / double(e - b);
}
}  // namespace

HoldErrors hold_errors(const std::vector<double>& predicted, const std::vector<double>& reference, const io::Dataset& d,
                       const std::vector<char>& mask, double window_s) {
  HoldErrors h;
  if (reference.empty()) return h;
  std::vector<char> m = hold_mask(d);
  for (std::size_t i = 0; i < m.size(); ++i) m[i] = m[i] && (mask.empty() || mask[i]);
  h.in_holds = error_stats(predicted, reference, m);
  const double rate = d.size() > 1 ? d.sample_rate_hz() : 1.0;
  const std::size_t w = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(window_s * rate)));
  double sum = 0, mx = 0;
  for (const auto& hold : find_holds(d)) {
    const std::size_t b = hold.end > hold.begin + w ? hold.end - w : hold.begin;
    if (!m[hold.end - 1] || !m[b]) continue;
    const double e = hold_mean(predicted, b, hold.end) - hold_mean(reference, b, hold.end);
    h.end_error_nm.push_back(e);
    sum += std::fabs(e);
    mx = std::max(mx, std::fabs(e));
  }
  if (!h.end_error_nm.empty()) {
    h.end_max_abs_nm = mx;
    h.end_mean_abs_nm = sum / static_cast<double>(h.end_error_nm.size());
  }
  return h;
}

std::vector<ZeroedHold> zeroed_holds(const std::vector<double>& free_run, const io::Dataset& data, const std::string& axis,
                                     const EvalOptions& opt) {
  std::vector<ZeroedHold> out;
  if (opt.zero_window_s <= 0 || data.size() < 2) return out;
  const auto& y = data.axis(axis).position_nm;
  const double rate = data.sample_rate_hz();
  auto rows = [&](double s) { return static_cast<std::size_t>(std::lround(s * rate)); };
  const std::size_t zw = rows(opt.zero_window_s), ww = rows(opt.walk_end_s);
  const std::size_t ew = std::max<std::size_t>(1, rows(opt.final_window_s));
  const std::vector<Hold> holds = find_holds(data);
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    const auto h = std::find_if(holds.begin(), holds.end(), [&](const Hold& x) { return x.begin >= rb && x.begin < re; });
    if (h == holds.end() || h->begin < rb + std::max(zw, ww) || h->end - h->begin < 2 * ew) continue;
    ZeroedHold z;
    z.recording = data.recordings.empty() ? data.source_or_data() : data.recordings[k].name;
    z.hold_s = h->duration_s;
    double s = 0;
    for (std::size_t i = h->begin - zw; i < h->begin; ++i) s += y[i] - free_run[i];
    z.offset_nm = s / static_cast<double>(zw);
    double a = 0;
    for (std::size_t i = h->begin - ww; i < h->begin; ++i) a += std::abs(free_run[i] + z.offset_nm - y[i]);
    z.walk_mae_nm = a / static_cast<double>(ww);
    z.creep_measured_nm = hold_mean(y, h->end - ew, h->end) - hold_mean(y, h->begin, h->begin + ew);
    z.creep_predicted_nm = hold_mean(free_run, h->end - ew, h->end) - hold_mean(free_run, h->begin, h->begin + ew);
    out.push_back(z);
  }
  return out;
}

ModelEvaluation evaluate_model(const models::Model& model, const std::string& name, const io::Dataset& test,
                               const io::Dataset* creep, const EvalOptions& opt) {
  ModelEvaluation ev;
  ev.name = name;
  ev.kind = model.kind();
  ev.num_parameters = model.num_parameters();
  ev.uses_positions = model.uses_position_history();
  if (const auto c = model.meta.validation.find("carry_over_ratio"); c != model.meta.validation.end())
    ev.carry_over_ratio = c->second;
  ev.test = predict_series(model, test, opt.axis, opt.anchor_s, opt.anchor_history);
  auto after_anchor = [](std::vector<char> m, const std::vector<char>& scored) {
    for (std::size_t i = 0; i < m.size() && i < scored.size(); ++i) m[i] = m[i] && scored[i];
    return m;
  };
  ev.hysteresis = metrics(ev.test, test.axis(opt.axis),
                          after_anchor(hysteresis_mask(test, opt.warmup_s, opt.test_segments), ev.test.scored));
  const io::Dataset& cd = creep ? *creep : test;
  ev.creep_pred = creep ? predict_series(model, *creep, opt.axis, opt.anchor_s, opt.anchor_history) : ev.test;
  ev.zeroed = zeroed_holds(ev.test.free_run, test, opt.axis, opt);
  const io::AxisSeries& cax = cd.axis(opt.axis);
  ev.creep = metrics(ev.creep_pred, cax, after_anchor(hold_mask(cd, opt.creep_segments), ev.creep_pred.scored));
  {
    const std::vector<char> m = after_anchor(hold_mask(cd, opt.creep_segments), ev.creep_pred.scored);
    ev.holds_free_run = hold_errors(ev.creep_pred.free_run, cax.position_nm, cd, m, opt.final_window_s);
    if (cax.has_truth()) ev.holds_free_run_truth = hold_errors(ev.creep_pred.free_run, cax.true_position_nm, cd, m, opt.final_window_s);
  }
  const double rate = cd.size() > 1 ? cd.sample_rate_hz() : 1.0;
  for (const auto& h : find_holds(cd)) {
    if (!in_segments(cd, h.begin, opt.creep_segments) || !ev.creep_pred.scored[h.end - 1]) continue;
    const std::size_t w = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(opt.final_window_s * rate)));
    const std::size_t b = h.end > h.begin + w ? h.end - w : h.begin;
    FinalDeviation f;
    f.segment = h.segment;
    f.hold_s = h.duration_s;
    f.measured_nm = hold_mean(cax.position_nm, b, h.end);
    f.truth_nm = cax.has_truth() ? hold_mean(cax.true_position_nm, b, h.end) : NAN;
    f.one_step_nm = hold_mean(ev.creep_pred.one_step, b, h.end);
    f.free_run_nm = hold_mean(ev.creep_pred.free_run, b, h.end);
    ev.finals.push_back(f);
  }
  return ev;
}

}  // namespace piezo::analysis
