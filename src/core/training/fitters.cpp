#include "piezo_compensation/training/fitters.h"

#include <Eigen/Dense>

#include <cmath>
#include <map>
#include <stdexcept>

#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/training/fit_pi_creep_play.h"
#include "piezo_compensation/util/flush_subnormals.h"

namespace piezo::training {

namespace {

using models::CreepKind;
using models::ModelPtr;

// Every kind that can be fitted on its own; the names are those of models/registry.cpp's list.
const std::map<std::string, FitFn>& fitters() {
  static const std::map<std::string, FitFn> f = {
      {"linear", &fit_linear},
      {"pi", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kNone); }},
      {"pi_creep_log", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kLog); }},
      {"pi_creep_lti", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kLti); }},
      {"pi_creep_fractional", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kFractional); }},
      {"pi_creep_prony", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kProny); }},
      {"pi_creep_play", &fit_pi_creep_play},
      {"preisach", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kNone, true); }},
      {"preisach_creep_prony", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kProny, true); }},
      {"dense", [](const FitRequest& r) -> ModelPtr { return fit_dense(r); }},
      {"lstm", [](const FitRequest& r) -> ModelPtr { return fit_lstm(r); }},
      {"kan", [](const FitRequest& r) -> ModelPtr { return fit_kan(r); }},
  };
  return f;
}

// Each recording's zero (io::RecordingMark) is not physics: the positions of each training and validation
// recording less an offset estimated jointly with the model by alternation — fit, then each recording's mean
// free-run residual, centred over the training recordings (the model's own intercept keeps their common part), then
// fit again. The alternation alone contracts slowly (a kind's slow creep states take up part of each offset), so it
// starts from the offsets of a fixed-effects regression — the position on a cubic in the voltage and one intercept
// per recording — which a random walk's hysteresis averages out of.
constexpr int kRecordingOffsetPasses = 2;

// Each recording's mean of measured − predicted, the model run free from each recording's own rest.
std::vector<double> recording_residuals(const models::Model& model, const io::Dataset& data, const std::string& axis) {
  return models::recording_offsets(data, axis, models::free_run_prediction(model, data, axis));
}

// Each recording's intercept of y ≈ Σ_{p≤3} a_p·v^p + c_r, centred over the recordings.
std::vector<double> fixed_effect_offsets(const io::Dataset& data, const std::string& axis) {
  const auto& ax = data.axis(axis);
  const std::size_t R = data.recording_count(), P = 3 + R;
  const auto rec = data.recording_index();
  double vs = 0;
  for (double v : ax.voltage_v) vs = std::max(vs, std::abs(v));
  vs = vs > 0 ? vs : 1.0;
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(P), static_cast<Eigen::Index>(P));
  Eigen::VectorXd b = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(P));
  Eigen::VectorXd x(static_cast<Eigen::Index>(P));
  for (std::size_t i = 0; i < data.size(); ++i) {
    const double u = ax.voltage_v[i] / vs;
    x.setZero();
    x(0) = u, x(1) = u * u, x(2) = u * u * u, x(static_cast<Eigen::Index>(3 + rec[i])) = 1.0;
    G.selfadjointView<Eigen::Lower>().rankUpdate(x);
    b += x * ax.position_nm[i];
  }
  G = G.selfadjointView<Eigen::Lower>();
  const Eigen::VectorXd beta = G.ldlt().solve(b);
  std::vector<double> c(R);
  double mean = 0;
  for (std::size_t k = 0; k < R; ++k) c[k] = beta(static_cast<Eigen::Index>(3 + k)), mean += c[k] / static_cast<double>(R);
  for (double& v : c) v -= mean;
  return c;
}

void shift_recordings(io::Dataset& data, const std::string& axis, const std::vector<double>& by_nm) {
  auto& y = data.axis(axis).position_nm;
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [b, e] = data.recording_rows(k);
    for (std::size_t i = b; i < e; ++i) y[i] -= by_nm[k];
  }
}

models::ModelPtr fit_recordings(const FitFn& fit, const FitRequest& request) {
  io::Dataset train = *request.train;
  io::Dataset val = request.validation ? *request.validation : io::Dataset();
  FitRequest r = request;
  r.train = &train;
  r.validation = request.validation ? &val : nullptr;
  r.lasso_cache = nullptr;  // the shifted positions are other data
  r.plain_fit = nullptr;
  std::vector<double> offsets = fixed_effect_offsets(train, request.axis);
  shift_recordings(train, request.axis, offsets);
  if (r.validation) shift_recordings(val, request.axis, fixed_effect_offsets(val, request.axis));
  models::ModelPtr m;
  for (int pass = 0;; ++pass) {
    m = fit(r);
    if (!m || pass == kRecordingOffsetPasses) break;
    std::vector<double> d = recording_residuals(*m, train, request.axis);
    double mean = 0;
    for (double x : d) mean += x / static_cast<double>(d.size());
    for (std::size_t k = 0; k < d.size(); ++k) d[k] -= mean, offsets[k] += d[k];
    shift_recordings(train, request.axis, d);
    if (r.validation) shift_recordings(val, request.axis, recording_residuals(*m, val, request.axis));
  }
  if (m) {
    double ss = 0;
    for (double o : offsets) ss += o * o;
    m->meta.validation["training_recordings"] = static_cast<double>(offsets.size());
    m->meta.validation["recording_offset_rms_nm"] = std::sqrt(ss / static_cast<double>(offsets.size()));
  }
  return m;
}

}  // namespace

const FitFn& fitter(const std::string& kind) {
  static const FitFn none;
  models::model_kind(kind);  // throws listing the known kinds
  const auto it = fitters().find(kind);
  return it == fitters().end() ? none : it->second;
}

models::ModelPtr fit_model(const std::string& kind, const FitRequest& request) {
  const FitFn& fit = fitter(kind);
  if (!fit) throw std::runtime_error("kind '" + kind + "' cannot be fitted on its own");
  const util::FlushSubnormals flush;  // decaying creep-filter states: see util/flush_subnormals.h
  const bool recordings = request.train && request.train->recording_count() > 1;
  models::ModelPtr m = recordings ? fit_recordings(fit, request) : fit(request);
  if (m && request.train) {
    m->meta.trained_on = models::training_spans(*request.train, request.axis);
    // the predictor refuses a model of the simulator's physics on a real transport (compensation/model_check.h)
    m->meta.fitted_on = io::is_simulated(*request.train) ? models::kFittedOnSimulated : models::kFittedOnRecorded;
  }
  // Where the training keeps the linear states: the start estimate's prior on a recording it has not seen.
  // A failure here leaves the model without a prior (the start estimate then uses the candidates'), not unfitted.
  if (m && m->meta.state_prior.empty()) {
    try {
      m->meta.state_prior = models::learn_state_prior(*m, *request.train, request.axis);
    } catch (const std::exception&) {
      m->meta.state_prior.clear();
    }
  }
  return m;
}

}  // namespace piezo::training
