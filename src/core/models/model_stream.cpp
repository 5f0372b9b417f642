#include "piezo_compensation/models/model_stream.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "piezo_compensation/util/flush_subnormals.h"
#include "piezo_compensation/util/format.h"

namespace piezo::models {

PredictionMode parse_prediction_mode(const std::string& s) {
  if (s == "free-run" || s == "free_run") return PredictionMode::kFreeRun;
  if (s == "one-step" || s == "one_step") return PredictionMode::kOneStep;
  throw std::invalid_argument("unknown prediction mode '" + s + "' (free-run or one-step)");
}

const char* prediction_mode_name(PredictionMode m) { return m == PredictionMode::kOneStep ? "one-step" : "free-run"; }

namespace {
bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() > suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
}  // namespace

InputSource classify_input(const std::string& name, const std::string& own_axis, const std::vector<std::string>& axis_names) {
  InputSource s;
  s.name = name;
  if (name == "time_s") {
    s.kind = InputSource::Kind::kTime;
    return s;
  }
  for (const auto& ax : axis_names) {
    if (name == io::true_position_column(ax))
      throw io::DataError("column " + name + " is the true position and is never a model input");
    if (name == io::position_column(ax)) {
      if (ax == own_axis) throw io::DataError("column " + name + " is the modelled axis' own position and cannot be a model input");
      s.kind = InputSource::Kind::kAxisPosition;
      s.axis = ax;
      return s;
    }
    if (name == io::fused_position_column(ax)) {
      if (ax == own_axis) throw io::DataError("column " + name + " is the modelled axis' own fused position and cannot be a model input");
      s.kind = InputSource::Kind::kAxisFused;
      s.axis = ax;
      return s;
    }
    if (name == io::voltage_column(ax)) {
      s.kind = InputSource::Kind::kAxisVoltage;
      s.axis = ax;
      return s;
    }
  }
  if (ends_with(name, "_true_position_nm")) throw io::DataError("column " + name + " is a true position and is never a model input");
  s.kind = InputSource::Kind::kAux;
  return s;
}

InputResolver::InputResolver(const io::Dataset& data, const std::vector<std::string>& names, const std::string& own_axis) {
  std::vector<std::string> axis_names;
  for (const auto& ax : data.axes) axis_names.push_back(ax.name);
  for (const auto& name : names) {
    InputSource s;
    try {
      s = classify_input(name, own_axis, axis_names);
    } catch (const io::DataError& e) {
      throw io::DataError(data.source_or_data() + ": " + e.what());
    }
    const std::vector<double>* col = nullptr;
    switch (s.kind) {
      case InputSource::Kind::kTime: col = &data.time_s; break;
      case InputSource::Kind::kAxisVoltage: col = &data.axis(s.axis).voltage_v; break;
      case InputSource::Kind::kAxisPosition: col = &data.axis(s.axis).position_nm; break;
      case InputSource::Kind::kAux:
      case InputSource::Kind::kAxisFused:
        if (const io::AuxSignal* a = data.find_aux(name)) col = &a->values;
        break;
    }
    if (!col && s.kind == InputSource::Kind::kAxisFused)
      throw io::DataError(data.source_or_data() + ": the model reads " + name + ", axis " + s.axis +
                          "'s fused position, a column derived from that axis' model and readings "
                          "(analysis::add_fused_positions; piezo residual --other-model " + s.axis + "=FILE)");
    if (!col) throw io::DataError(data.source_or_data() + ": the model reads column " + name + ", which the data does not have");
    sources_.push_back(s);
    cols_.push_back(col);
    lagged_.push_back(s.kind == InputSource::Kind::kAxisPosition || s.kind == InputSource::Kind::kAxisFused);
  }
  row_.resize(cols_.size());
}

void InputResolver::fill(std::size_t i, double* out) const {
  for (std::size_t k = 0; k < cols_.size(); ++k) out[k] = (*cols_[k])[lagged_[k] && i > 0 ? i - 1 : i];
}

const double* InputResolver::at(std::size_t i) {
  if (cols_.empty()) return nullptr;
  fill(i, row_.data());
  return row_.data();
}

void Model::check_fixed_step(double dt_s) const {
  const double nominal = 1.0 / meta.sample_rate_hz;
  if (!(dt_s > 0) || !std::isfinite(dt_s))
    throw std::invalid_argument("model '" + kind() + "': a step must be a finite time > 0 s, got " + util::fmt(dt_s, 6));
  if (std::abs(dt_s - nominal) > kStepTolerance * nominal)
    throw std::invalid_argument("model '" + kind() + "' cannot run at a " + util::fmt(dt_s, 6) + "-s step (" +
                                util::fmt(1.0 / dt_s, 4) + " Hz; trained at " + util::fmt(meta.sample_rate_hz, 4) +
                                " Hz): " + fixed_rate_reason());
}

RowSteps::RowSteps(const Model& model, const io::Dataset& data) : t_(data.time_s) {
  if (!model.runs_at_any_rate() || data.size() < 2) return;
  const io::TimeBase tb = io::time_base(data.time_s);
  if (!(tb.period_s > 0)) return;
  period_s_ = tb.period_s;
  per_row_ = !tb.constant;
}

double RowSteps::step_s(std::size_t i) const {
  if (!(period_s_ > 0)) return std::numeric_limits<double>::quiet_NaN();
  if (!per_row_ || i == 0) return period_s_;
  const double dt = t_[i] - t_[i - 1];
  return dt > 0 && dt <= io::kMaxStepS ? dt : period_s_;
}

void RowSteps::apply(Model& model, std::size_t i) const {
  if (!per_row_ && i > 0) return;  // on a sample clock the step is set once
  const double dt = step_s(i);
  if (std::isfinite(dt)) model.set_step_s(dt);
}

namespace {

void stream_rows(Model& model, const io::Dataset& data, const std::string& axis, const StreamOptions& o,
                 std::vector<double>* pred) {
  const io::AxisSeries& ax = data.axis(axis);
  InputResolver inputs(data, model.aux_inputs(), axis);
  const RowSteps steps(model, data);
  const bool free_run = o.mode == PredictionMode::kFreeRun;
  if (pred) pred->assign(data.size(), 0.0);
  for (std::size_t i = 0; i < data.size(); ++i) {
    steps.apply(model, i);
    const ModelInput in{ax.voltage_v[i], inputs.at(i)};
    double y = model.predict(in);
    if (!std::isfinite(y)) {
      if (!(free_run && o.keep_diverging))
        throw std::runtime_error("model '" + model.kind() + "' predicted a non-finite position at row " +
                                 std::to_string(i + 1) + (data.source.empty() ? "" : " of " + data.source));
      y = y > 0 ? 1e12 : -1e12;
    }
    if (pred) (*pred)[i] = y;
    model.commit(in, free_run ? y : ax.position_nm[i]);
    if (pred && o.after_row) o.after_row(i, model);
  }
}
}  // namespace

namespace {
// Each recording on its own (its own history and zero), the results joined in row order.
StreamResult stream_recordings(Model& model, const io::Dataset& data, const std::string& axis, const StreamOptions& o) {
  if (o.warmup) throw std::invalid_argument(data.source_or_data() + ": a warm-up cannot precede several recordings");
  StreamResult all;
  all.prediction.reserve(data.size());
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const std::size_t begin = data.recording_rows(k).first;
    StreamOptions ok = o;
    ok.reset = o.reset || k > 0;
    if (o.after_row) ok.after_row = [&](std::size_t row, const Model& m) { o.after_row(begin + row, m); };
    const StreamResult r = stream_model(model, data.recording(k), axis, ok);
    all.prediction.insert(all.prediction.end(), r.prediction.begin(), r.prediction.end());
    all.windows.emplace_back(begin, begin + r.first_scored);
    all.starts.push_back(r.start);
    if (k == 0) all.first_scored = r.first_scored, all.start = r.start, all.anchor_offset_nm = r.anchor_offset_nm;
    all.anchored = all.anchored || r.anchored;
  }
  return all;
}
}  // namespace

StreamResult stream_model(Model& model, const io::Dataset& data, const std::string& axis, const StreamOptions& o) {
  if (data.recording_count() > 1) return stream_recordings(model, data, axis, o);
  const util::FlushSubnormals flush;  // decaying creep-filter states: see util/flush_subnormals.h
  StreamResult r;
  if (!(o.anchor_s >= 0) || !std::isfinite(o.anchor_s)) throw std::invalid_argument("anchor must be a finite time ≥ 0 s");
  const io::Dataset* first = o.warmup && !o.warmup->empty() ? o.warmup : &data;
  if (first->empty()) return r;
  const bool anchor = o.anchor_s > 0 && !data.empty();
  if (anchor) r.first_scored = start_window_rows(data, axis, o.anchor_s);  // checks the window first
  if (o.reset && anchor && first == &data) {
    // The one anchor: the start estimate chooses the state (or rest, offset only) from a cold start.
    StartOptions so;
    so.window_s = o.anchor_s;
    so.search_history = o.anchor_history;
    r.start = estimate_start(model, data, axis, so);
    prepare_start(model, data, axis, r.start.history);
  } else if (o.reset) {
    const io::AxisSeries& ax = first->axis(axis);
    model.reset(ax.voltage_v[0], ax.position_nm[0]);
  }
  if (first != &data) stream_rows(model, *first, axis, o, nullptr);
  stream_rows(model, data, axis, o, &r.prediction);
  if (anchor) {
    const std::size_t k = r.first_scored;
    // A free run from the estimate is the estimate's own stream: its offset stands, and so does a one-step stream's
    // of a model that reads no position (the same computation). A one-step stream of a model that reads the
    // position: the mean of measured − predicted over the window under the estimate's row weights (the rows where
    // the unknown history still moves the prediction count little, as in the estimate). A warm start without the
    // estimate: the plain mean over the window. The rest of the report is the estimate's.
    r.start.window_rows = k;
    const double* y = data.axis(axis).position_nm.data();
    const std::vector<double>& w = r.start.window_weight;
    const bool estimated = r.start.candidates > 0;
    if (estimated && (o.mode == PredictionMode::kFreeRun || !model.uses_position_history())) {
      // the estimate's own stream: its offset stands
    } else if (estimated && w.size() == k) {  // the weighted mean and RMS; the σ stays the estimate's
      double sw = 0, swr = 0, swrr = 0;
      for (std::size_t i = 0; i < k; ++i) sw += w[i], swr += w[i] * (y[i] - r.prediction[i]);
      r.start.offset_nm = swr / sw;
      for (std::size_t i = 0; i < k; ++i) swrr += w[i] * std::pow(y[i] - r.prediction[i] - r.start.offset_nm, 2);
      r.start.rms_nm = std::sqrt(swrr / sw);
    } else {  // a warm start, or offset only (no weights): the plain mean
      const WindowFit f = window_offset(y, r.prediction.data(), k);
      r.start.offset_nm = f.offset_nm;
      r.start.offset_sigma_nm = f.sigma_nm;
      r.start.rms_nm = f.rms_nm;
    }
    if (r.start.candidates == 0) r.start.rms_rest_nm = r.start.rms_nm, r.start.candidate = "warm (continued history)";
    r.anchor_offset_nm = r.start.offset_nm;
    r.anchored = true;
    for (double& p : r.prediction) p += r.anchor_offset_nm;
  }
  return r;
}

std::vector<double> free_run_prediction(const Model& model, const io::Dataset& data, const std::string& axis) {
  StreamOptions so;
  so.mode = PredictionMode::kFreeRun;
  so.keep_diverging = true;
  auto m = model.clone();
  return stream_model(*m, data, axis, so).prediction;
}

std::vector<double> recording_offsets(const io::Dataset& data, const std::string& axis, const std::vector<double>& predicted_nm,
                                      std::size_t from) {
  const auto& y = data.axis(axis).position_nm;
  if (predicted_nm.size() != y.size())
    throw std::invalid_argument("recording_offsets: " + std::to_string(predicted_nm.size()) + " predictions for " +
                                std::to_string(y.size()) + " rows");
  std::vector<double> out(data.recording_count(), 0.0);
  for (std::size_t k = 0; k < out.size(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    const std::size_t b = std::max(rb, from);
    if (b >= re) continue;
    double s = 0;
    for (std::size_t i = b; i < re; ++i) s += y[i] - predicted_nm[i];
    out[k] = s / static_cast<double>(re - b);
  }
  return out;
}

std::vector<char> scored_mask(const StreamResult& r, std::size_t n) {
  std::vector<char> m(n, 1);
  if (r.windows.empty()) {
    std::fill(m.begin(), m.begin() + static_cast<long>(std::min(n, r.first_scored)), 0);
    return m;
  }
  for (const auto& [b, e] : r.windows)
    std::fill(m.begin() + static_cast<long>(std::min(n, b)), m.begin() + static_cast<long>(std::min(n, e)), 0);
  return m;
}

}  // namespace piezo::models
