#include "piezo_compensation/compensation/resume.h"

#include <algorithm>
#include <cmath>

#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/util/format.h"

namespace piezo::compensation {

namespace {

using util::fmt;

template <class T>
void repeat_last(std::vector<T>& v, std::size_t m) {
  if (!v.empty()) v.assign(m, v.back());
}

// m rows of `last` (one row) held: every column repeated, time from t0 on at step dt.
io::Dataset held_rows(const io::Dataset& last, std::size_t m, double t0, double dt) {
  io::Dataset d = last;
  d.time_s.resize(m);
  for (std::size_t i = 0; i < m; ++i) d.time_s[i] = t0 + dt * static_cast<double>(i);
  for (auto& a : d.axes) repeat_last(a.voltage_v, m), repeat_last(a.position_nm, m), repeat_last(a.true_position_nm, m);
  for (auto& x : d.aux) repeat_last(x.values, m);
  repeat_last(d.segment, m);
  repeat_last(d.phase, m);
  return d;
}

// The estimator over the history's readings and the model's predictions, then held for the gap's samples.
std::optional<estimation::FilterState> resume_filter(const models::Model& model, const io::AxisSeries& ax,
                                                     const std::vector<double>& predicted, double dt,
                                                     std::size_t held, std::string& status) {
  if (!model.meta.estimator || model.meta.estimator.IsNull()) return std::nullopt;
  try {
    const estimation::NoiseModel nm = estimation::NoiseModel::from_yaml(model.meta.estimator, "model " + model.kind());
    if (!nm.fuse) return std::nullopt;
    estimation::ErrorFilter f(nm, dt);
    for (std::size_t i = 0; i < predicted.size(); ++i)
      f.step(predicted[i], ax.position_nm[i], std::isfinite(ax.position_nm[i]));
    f.hold(held);
    status = "; estimator resumed at 1σ " + fmt(f.sigma_nm(), 3) + " nm";
    return f.state();
  } catch (const std::exception& e) {
    status = std::string("; estimator not resumed: ") + e.what();
    return std::nullopt;
  }
}

Resume refused(std::string why) {
  Resume r;
  r.status = "not resumed: " + std::move(why);
  return r;
}

}  // namespace

Resume resume_model(const models::Model& model, const io::Dataset& history, const std::string& axis, double now_s,
                    double now_v, const ResumeOptions& o) {
  const std::string src = history.source_or_data();
  if (history.size() < 2) return refused(src + " holds fewer than 2 rows");
  if (!history.has_axis(axis)) return refused(src + " has no axis " + axis);
  const io::AxisSeries& ax = history.axis(axis);
  const std::size_t n = history.size();
  const double last_v = ax.voltage_v[n - 1], end_s = history.time_s[n - 1];
  const double gap_s = now_s - end_s;
  if (!std::isfinite(now_s) || !std::isfinite(now_v)) return refused("the time or voltage now is not finite");
  if (!(gap_s >= 0.0))
    return refused("now (" + fmt(now_s, 12) + " s) is before the end of " + src + " (" + fmt(end_s, 12) +
                   " s): another clock, or not the run before");
  if (gap_s > o.max_gap_s)
    return refused(fmt(gap_s, 4) + " s since the end of " + src + ", more than " + fmt(o.max_gap_s, 4) + " s");
  if (!(std::abs(now_v - last_v) <= o.voltage_tolerance_v))
    return refused(axis + " is at " + fmt(now_v, 6) + " V, " + src + " ended at " + fmt(last_v, 6) + " V (more than " +
                   fmt(o.voltage_tolerance_v, 3) + " V apart: the stage moved while nothing recorded it)");
  const double dt = io::median_step_s(history.time_s);
  if (!(dt > 0.0)) return refused(src + " has no sample period");
  if (gap_s < 0.5 * dt)
    return refused("now (" + fmt(now_s, 12) + " s) is within half a sample period of the end of " + src +
                   ": that sample may be in it");
  for (std::size_t i = 0; i < n; ++i)
    if (!std::isfinite(ax.voltage_v[i]))
      return refused(src + " holds a non-finite voltage of " + axis + " at row " + std::to_string(i + 1));
  models::ModelPtr m = model.clone();
  double last_nm = 0.0;
  std::optional<estimation::FilterState> filter;
  std::string filter_status;
  try {
    models::StreamOptions so;  // reset at rest at the first row
    so.mode = o.mode;
    std::vector<double> p = models::stream_model(*m, history, axis, so).prediction;
    last_nm = p.back();
    // The hold: the samples between the history's last row and now (now's own sample is the caller's next), in
    // chunks through the same path (state continued), at most 10^5 rows in memory at a time.
    const double steps = std::round(gap_s / dt);
    const std::size_t rows = steps > 1.0 ? static_cast<std::size_t>(steps) - 1 : 0;
    filter = resume_filter(model, ax, p, dt, rows, filter_status);
    const io::Dataset last = history.slice(n - 1, n);
    so.reset = false;
    for (std::size_t done = 0; done < rows;) {
      const std::size_t k = std::min<std::size_t>(rows - done, 100000);
      const io::Dataset hold = held_rows(last, k, end_s + dt * static_cast<double>(done + 1), dt);
      last_nm = models::stream_model(*m, hold, axis, so).prediction.back();
      done += k;
    }
  } catch (const std::exception& e) {
    return refused(std::string("the model's run over ") + src + " failed: " + e.what());
  }
  Resume r;
  r.resumed = true;
  r.history_s = end_s - history.time_s[0];
  r.history_rows = n;
  r.gap_s = gap_s;
  r.last_voltage_v = last_v;
  r.predicted_nm = last_nm;
  r.status = "resumed on " + fmt(r.history_s, 5) + " s of recorded history (" + std::to_string(n) + " rows of " + src +
             "), held " + fmt(gap_s, 4) + " s at " + fmt(last_v, 5) + " V since" + filter_status;
  r.model = std::move(m);
  if (filter) filter->last_predicted_nm = last_nm;
  r.filter = filter;
  return r;
}

}  // namespace piezo::compensation
