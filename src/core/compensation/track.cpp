#include "piezo_compensation/compensation/track.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::compensation {

std::vector<std::pair<std::size_t, std::size_t>> find_holds(const std::vector<double>& v, double rate_hz,
                                                            double min_s) {
  std::vector<std::pair<std::size_t, std::size_t>> holds;
  const std::size_t min_n = static_cast<std::size_t>(std::ceil(min_s * rate_hz));
  std::size_t i0 = 0;
  for (std::size_t i = 1; i <= v.size(); ++i) {
    if (i < v.size() && v[i] == v[i0]) continue;
    if (i - i0 >= min_n) holds.push_back({i0, i});
    i0 = i;
  }
  return holds;
}

namespace {

// The reference a hold is scored against: the truth, or the mean of the readings in (i, i + w] within [.., e).
std::vector<double> hold_reference(const TrackResult& r, std::size_t b, std::size_t e, std::size_t w) {
  if (r.has_truth) return std::vector<double>(r.true_nm.begin() + static_cast<long>(b), r.true_nm.begin() + static_cast<long>(e));
  std::vector<double> ref(e - b, NAN);
  double s = 0;
  std::size_t n = 0, hi = b + 1;  // readings in (i, hi)
  for (std::size_t i = b; i < e; ++i) {
    if (i > b && std::isfinite(r.measured_nm[i])) s -= r.measured_nm[i], --n;  // row i leaves (i, …]
    for (; hi < e && hi <= i + w; ++hi)
      if (std::isfinite(r.measured_nm[hi])) s += r.measured_nm[hi], ++n;
    if (i + w < e && n > 0) ref[i - b] = s / static_cast<double>(n);
  }
  return ref;
}

void score_hold(const TrackResult& r, std::size_t b, std::size_t e, double rate, const TrackOptions& o,
                TrackHold& h) {
  const std::size_t first = b + static_cast<std::size_t>(std::lround(o.settle_skip_s * rate));
  const std::size_t end_n = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(o.end_window_s * rate)));
  h.start_s = r.time_s[b];
  h.end_s = r.time_s[e - 1];
  h.voltage_v = r.applied_v[b];
  if (first >= e) return;
  const std::vector<double> ref = hold_reference(r, b, e, end_n);
  // the last end_window_s with a reference: the hold's end
  std::size_t last = e;
  while (last > first && !std::isfinite(ref[last - 1 - b])) --last;
  double sm = 0, sig = 0, fm = 0, mm = 0, fe = 0, me = 0;
  std::size_t in2 = 0, nm = 0, scored = 0, checked = 0;
  for (std::size_t i = first; i < e; ++i) {
    sig += r.fused_sigma_nm[i];
    if (std::isfinite(r.measured_nm[i])) sm += r.measured_nm[i] - r.fused_nm[i], ++nm;
    if (r.has_truth) {
      checked += 1, in2 += std::abs(r.fused_nm[i] - r.true_nm[i]) <= 2.0 * r.fused_sigma_nm[i];
    } else if (i + 1 < e && std::isfinite(r.measured_nm[i + 1])) {
      const double band = 2.0 * std::sqrt(r.fused_sigma_nm[i] * r.fused_sigma_nm[i] + r.reading_sigma_nm * r.reading_sigma_nm);
      checked += 1, in2 += std::abs(r.measured_nm[i + 1] - r.fused_nm[i]) <= band;
    }
    const double x = ref[i - b];
    if (!std::isfinite(x)) continue;
    const double ef = std::abs(r.fused_nm[i] - x), em = std::abs(r.model_nm[i] - x);
    fm += ef, mm += em, ++scored;
    if (i + end_n >= last) fe = std::max(fe, ef), me = std::max(me, em);
  }
  h.scored = e - first;
  h.mean_sigma_nm = sig / static_cast<double>(h.scored);
  if (nm) h.measured_mean_minus_fused_nm = sm / static_cast<double>(nm);
  if (scored) {
    h.fused_mae_nm = fm / static_cast<double>(scored);
    h.model_mae_nm = mm / static_cast<double>(scored);
    h.fused_end_nm = fe;
    h.model_end_nm = me;
  }
  if (checked && (r.has_truth || std::isfinite(r.reading_sigma_nm))) h.within_2sigma = static_cast<double>(in2) / static_cast<double>(checked);
}

void score_from(TrackResult& r, double from_s) {
  if (!r.has_truth) return;
  double f = 0, m = 0, in2 = 0, n = 0;
  for (std::size_t i = 0; i < r.time_s.size(); ++i) {
    if (r.time_s[i] - r.time_s[0] < from_s) continue;
    const double ef = std::abs(r.fused_nm[i] - r.true_nm[i]);
    f += ef, m += std::abs(r.model_nm[i] - r.true_nm[i]), n += 1;
    in2 += ef <= 2.0 * r.fused_sigma_nm[i];
  }
  if (n > 0) r.all_fused_mae_nm = f / n, r.all_model_mae_nm = m / n, r.all_within_2sigma = in2 / n;
}

void summarise(TrackResult& r) {
  double f = 0, m = 0, in2 = 0, n = 0, fe = 0, me = 0;
  for (const auto& h : r.holds) {
    if (!h.scored || !std::isfinite(h.fused_mae_nm)) continue;
    f += h.fused_mae_nm * h.scored, m += h.model_mae_nm * h.scored, in2 += h.within_2sigma * h.scored;
    n += h.scored;
    fe = std::max(fe, h.fused_end_nm), me = std::max(me, h.model_end_nm);
  }
  if (n > 0) {
    r.fused_mae_nm = f / n, r.model_mae_nm = m / n, r.within_2sigma = in2 / n;
    r.worst_fused_end_nm = fe, r.worst_model_end_nm = me;
  }
}

TrackResult track_one(models::ModelPtr model, const io::Dataset& data, const std::string& axis, const TrackOptions& o);

// Each recording on its own from a cold start, the results joined.
TrackResult track_recordings(const models::Model& model, const io::Dataset& data, const std::string& axis,
                             const TrackOptions& o) {
  TrackResult all;
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const io::Dataset part = data.recording(k);
    TrackResult r = track_one(model.clone(), part, axis, o);
    const double shift = data.recordings.empty() ? 0.0 : data.recordings[k].time_shift_s;
    for (double& t : r.time_s) t += shift;
    for (auto& h : r.holds) h.start_s += shift, h.end_s += shift;
    auto add = [](std::vector<double>& to, const std::vector<double>& from) { to.insert(to.end(), from.begin(), from.end()); };
    add(all.time_s, r.time_s), add(all.applied_v, r.applied_v), add(all.measured_nm, r.measured_nm);
    add(all.model_nm, r.model_nm), add(all.fused_nm, r.fused_nm), add(all.fused_sigma_nm, r.fused_sigma_nm);
    add(all.true_nm, r.true_nm);
    all.holds.insert(all.holds.end(), r.holds.begin(), r.holds.end());
    all.forecast.add(r.forecast);
    if (k == 0) all.estimator = r.estimator, all.fusing = r.fusing, all.has_truth = r.has_truth,
                all.reading_sigma_nm = r.reading_sigma_nm;
    if (!r.start_estimate.empty())
      all.start_estimate += (all.start_estimate.empty() ? "" : "\n") + part.source + ": " + r.start_estimate;
  }
  all.recordings = data.recording_count();
  summarise(all);
  return all;
}

}  // namespace

TrackResult track_recording(models::ModelPtr model, const io::Dataset& data, const std::string& axis,
                            const TrackOptions& o) {
  if (!model) throw std::invalid_argument("track: no model");
  if (data.recording_count() > 1) return track_recordings(*model, data, axis, o);
  return track_one(std::move(model), data, axis, o);
}

namespace {

TrackResult track_one(models::ModelPtr model, const io::Dataset& data, const std::string& axis, const TrackOptions& o) {
  const io::AxisSeries& ax = data.axis(axis);
  if (data.size() < 2) throw std::invalid_argument("track: " + data.source + " has fewer than 2 rows");
  const double rate = data.sample_rate_hz();
  const auto [vmin, vmax] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
  AxisCompensatorConfig cfg;
  const double pad = 0.1 * std::max(1.0, *vmax - *vmin);
  cfg.voltage_min_v = *vmin - pad;
  cfg.voltage_max_v = *vmax + pad;
  cfg.sample_rate_hz = rate;
  cfg.start_estimate_s = o.start_estimate_s;
  // As `piezo eval --anchor-s` (models/start_state.h): the recording's voltage span on both sides of its first voltage.
  cfg.start_voltage_min_v = std::min(*vmin, ax.voltage_v[0] - (*vmax - *vmin));
  cfg.start_voltage_max_v = std::max(*vmax, ax.voltage_v[0] + (*vmax - *vmin));
  IdealLineOptions lo;
  lo.voltage_min_v = cfg.voltage_min_v;
  lo.voltage_max_v = cfg.voltage_max_v;
  lo.hold_s = 60.0;
  lo.sample_rate_hz = rate;
  const IdealLine line = ideal_line_from_model(*model, lo);
  models::InputResolver inputs(data, model->aux_inputs(), axis);
  AxisCompensator comp(std::move(model), line, cfg);

  TrackResult r;
  r.has_truth = ax.has_truth();
  r.estimator = comp.estimator_status();
  r.fusing = comp.estimator() && comp.estimator()->fusing();
  if (comp.estimator()) r.reading_sigma_nm = comp.estimator()->noise_model().reading_sigma_nm;
  const std::size_t n = data.size();
  r.time_s = data.time_s;
  r.applied_v = ax.voltage_v;
  r.measured_nm = ax.position_nm;
  r.true_nm = r.has_truth ? ax.true_position_nm : std::vector<double>(n, NAN);
  r.model_nm.resize(n);
  r.fused_nm.resize(n);
  r.fused_sigma_nm.resize(n);
  std::vector<estimation::FilterState> states(comp.estimator() ? n : 0);
  const models::RowSteps steps(comp.model(), data);  // a jittered recording's own row steps, as stream_model
  for (std::size_t i = 0; i < n; ++i) {
    const double y = ax.position_nm[i];
    if (const double dt = steps.step_s(i); std::isfinite(dt)) comp.set_step_s(dt);
    const SampleUpdate u = comp.on_sample(ax.voltage_v[i], y, std::isfinite(y), inputs.at(i));
    r.model_nm[i] = u.predicted_nm;
    r.fused_nm[i] = u.fused_nm;
    r.fused_sigma_nm[i] = u.fused_sigma_nm;
    if (comp.estimator()) states[i] = comp.estimator()->state();
    if (std::isnan(r.zero_known_s) && comp.estimator() && comp.estimator()->zero_known())
      r.zero_known_s = data.time_s[i] - data.time_s[0];
  }
  r.start_estimate = comp.start_estimate_status();
  const auto holds = find_holds(ax.voltage_v, rate, o.min_hold_s);
  if (r.fusing)
    r.forecast = score_forecasts(comp.estimator()->noise_model(), 1.0 / rate, r.model_nm, r.measured_nm,
                                 r.has_truth ? r.true_nm : std::vector<double>{}, r.applied_v, states, holds, o.forecast);
  for (const auto& [b, e] : holds) {
    TrackHold h;
    score_hold(r, b, e, rate, o, h);
    r.holds.push_back(h);
  }
  summarise(r);
  score_from(r, o.score_from_s);
  return r;
}

}  // namespace

}  // namespace piezo::compensation
