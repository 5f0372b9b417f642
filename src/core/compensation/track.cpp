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

void score_hold(const TrackResult& r, std::size_t b, std::size_t e, double rate, const TrackOptions& o,
                TrackHold& h) {
  const std::size_t first = b + static_cast<std::size_t>(std::lround(o.settle_skip_s * rate));
  const std::size_t end_n = static_cast<std::size_t>(std::lround(o.end_window_s * rate));
  h.start_s = r.time_s[b];
  h.end_s = r.time_s[e - 1];
  h.voltage_v = r.applied_v[b];
  if (first >= e) return;
  h.scored = e - first;
  double sm = 0, sig = 0, fm = 0, mm = 0, fe = 0, me = 0;
  std::size_t in2 = 0, nm = 0;
  for (std::size_t i = first; i < e; ++i) {
    sig += r.fused_sigma_nm[i];
    if (std::isfinite(r.measured_nm[i])) sm += r.measured_nm[i] - r.fused_nm[i], ++nm;
    if (!r.has_truth) continue;
    const double ef = std::abs(r.fused_nm[i] - r.true_nm[i]), em = std::abs(r.model_nm[i] - r.true_nm[i]);
    fm += ef, mm += em;
    if (ef <= 2.0 * r.fused_sigma_nm[i]) ++in2;
    if (i + end_n >= e) fe = std::max(fe, ef), me = std::max(me, em);
  }
  h.mean_sigma_nm = sig / h.scored;
  if (nm) h.measured_mean_minus_fused_nm = sm / nm;
  if (r.has_truth) {
    h.fused_mae_nm = fm / h.scored;
    h.model_mae_nm = mm / h.scored;
    h.fused_end_nm = fe;
    h.model_end_nm = me;
    h.within_2sigma = static_cast<double>(in2) / h.scored;
  }
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
    if (!h.scored || !r.has_truth) continue;
    f += h.fused_mae_nm * h.scored, m += h.model_mae_nm * h.scored, in2 += h.within_2sigma * h.scored;
    n += h.scored;
    fe = std::max(fe, h.fused_end_nm), me = std::max(me, h.model_end_nm);
  }
  if (n > 0) {
    r.fused_mae_nm = f / n, r.model_mae_nm = m / n, r.within_2sigma = in2 / n;
    r.worst_fused_end_nm = fe, r.worst_model_end_nm = me;
  }
}

}  // namespace

TrackResult track_recording(models::ModelPtr model, const io::Dataset& data, const std::string& axis,
                            const TrackOptions& o) {
  if (!model) throw std::invalid_argument("track: no model");
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
  const std::size_t n = data.size();
  r.time_s = data.time_s;
  r.applied_v = ax.voltage_v;
  r.measured_nm = ax.position_nm;
  r.true_nm = r.has_truth ? ax.true_position_nm : std::vector<double>(n, NAN);
  r.model_nm.resize(n);
  r.fused_nm.resize(n);
  r.fused_sigma_nm.resize(n);
  for (std::size_t i = 0; i < n; ++i) {
    const double y = ax.position_nm[i];
    const SampleUpdate u = comp.on_sample(ax.voltage_v[i], y, std::isfinite(y), inputs.at(i));
    r.model_nm[i] = u.predicted_nm;
    r.fused_nm[i] = u.fused_nm;
    r.fused_sigma_nm[i] = u.fused_sigma_nm;
    if (std::isnan(r.zero_known_s) && comp.estimator() && comp.estimator()->zero_known())
      r.zero_known_s = data.time_s[i] - data.time_s[0];
  }
  r.start_estimate = comp.start_estimate_status();
  for (const auto& [b, e] : find_holds(ax.voltage_v, rate, o.min_hold_s)) {
    TrackHold h;
    score_hold(r, b, e, rate, o, h);
    r.holds.push_back(h);
  }
  summarise(r);
  score_from(r, o.score_from_s);
  return r;
}

}  // namespace piezo::compensation
