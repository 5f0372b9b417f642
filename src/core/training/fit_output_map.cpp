// The output map of the PI and Preisach kinds (models/pi_model.h, OutputMap): a monotone cubic of the hysteresis
// output, fitted by alternation around the kind's own fit and kept when validation clearly prefers it.
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include <Eigen/Dense>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::training {

namespace {

using models::OutputMap;
using models::PiCreepModel;

// The smallest slope dS/dH a fitted map may have on its range: a loop bent so far that its branch is nearly flat
// would make the inverse ill-conditioned (a tenth of a nanometre of target moves the voltage by volts).
constexpr double kMinMapSlope = 0.2;
// The blocks of the validation comparison: each block's own zero, and the paired blocks of validation_prefers.
constexpr double kCompareBlockS = 300.0;
// A block whose voltage spans less than this share of the data's is a hold (or nearly): left out of the comparison.
constexpr double kMovingBlockSpan = 0.05;
// Refits of the kind on the positions less the map's bend (each followed by a new map). The map and the play weights
// share the loop's shape; two rounds settle the real c axis' map within a few nanometres of a third.
constexpr int kMapPasses = 2;
// Fewer moving blocks than this and validation cannot tell a map from noise: auto keeps the plain model.
constexpr std::size_t kMinCompareBlocks = 4;

// The hysteresis output H of every row: the same plays and weights without bias, creep or map.
std::vector<double> map_input_series(const PiCreepModel& m, const io::Dataset& data, const std::string& axis) {
  const PiCreepModel h(m.thresholds_v(), m.weights(), 0.0, models::CreepParams{}, m.sample_rate_hz(), m.knots_v(),
                       m.has_input_map());
  return models::free_run_prediction(h, data, axis);
}

// The absolute free-run errors of the rows in blocks that move (`block` rows, cut at recording starts; a block
// moves when its voltage spans over kMovingBlockSpan of the data's), each recording's zero (its mean error over those
// rows) taken out. The map is static: it bends the loop's shape while the voltage moves and adds a constant in a
// hold, so the comparison scores the moves, not the holds' drift, which creep and a recording's unknown prehistory
// set.
std::vector<double> moving_block_errors(const models::Model& model, const io::Dataset& data, const std::string& axis,
                                        std::size_t block) {
  const std::vector<double> pred = models::free_run_prediction(model, data, axis);
  const auto& y = data.axis(axis).position_nm;
  const auto& v = data.axis(axis).voltage_v;
  const auto [vmin, vmax] = std::minmax_element(v.begin(), v.end());
  const double min_span = kMovingBlockSpan * (*vmax - *vmin);
  std::vector<double> e;
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [rb, re] = data.recording_rows(k);
    std::vector<std::size_t> starts;
    double zero = 0;
    for (std::size_t b = rb; b + block <= re; b += block) {
      const auto [lo, hi] = std::minmax_element(v.begin() + static_cast<long>(b), v.begin() + static_cast<long>(b + block));
      if (!(*hi - *lo > min_span)) continue;
      starts.push_back(b);
      for (std::size_t i = b; i < b + block; ++i) zero += y[i] - pred[i];
    }
    if (starts.empty()) continue;
    zero /= static_cast<double>(starts.size() * block);
    for (std::size_t b : starts)
      for (std::size_t i = b; i < b + block; ++i) e.push_back(std::abs(y[i] - pred[i] - zero));
  }
  return e;
}

// Least squares of the residual y − (model without map) on z², z³ of H, one free intercept per recording; the map is
// shrunk towards the identity until its slope is at least kMinMapSlope everywhere on the range.
OutputMap fit_map(const PiCreepModel& model, const io::Dataset& data, const std::string& axis) {
  PiCreepModel plain = model;
  plain.set_output_map(OutputMap{});
  const std::vector<double> pred = models::free_run_prediction(plain, data, axis), H = map_input_series(plain, data, axis);
  const auto& y = data.axis(axis).position_nm;
  const auto [lo, hi] = std::minmax_element(H.begin(), H.end());
  OutputMap map;
  map.lo_nm = *lo, map.hi_nm = *hi;
  if (!(map.hi_nm > map.lo_nm)) return OutputMap{};
  const double mid = 0.5 * (map.lo_nm + map.hi_nm), half = 0.5 * (map.hi_nm - map.lo_nm);
  const std::vector<std::size_t> rec = data.recording_index();
  const Eigen::Index P = 2 + static_cast<Eigen::Index>(data.recording_count());
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(P, P);
  Eigen::VectorXd b = Eigen::VectorXd::Zero(P), x(P);
  for (std::size_t i = 0; i < y.size(); ++i) {
    if (!std::isfinite(pred[i]) || !std::isfinite(H[i])) continue;
    const double z = (H[i] - mid) / half;
    x.setZero();
    x(0) = z * z, x(1) = z * z * z, x(2 + static_cast<Eigen::Index>(rec[i])) = 1.0;
    G.selfadjointView<Eigen::Lower>().rankUpdate(x);
    b += x * (y[i] - pred[i]);
  }
  G = G.selfadjointView<Eigen::Lower>();
  G.diagonal().array() += 1e-9 * (1.0 + G.diagonal().array());
  const Eigen::VectorXd beta = G.ldlt().solve(b);
  map.quadratic_nm = beta(0), map.cubic_nm = beta(1);
  if (!std::isfinite(map.quadratic_nm) || !std::isfinite(map.cubic_nm)) return OutputMap{};
  if (map.min_slope() >= kMinMapSlope) return map;
  double keep = 0.0, drop = 1.0;  // the largest share of the fitted map whose slope stays above the floor
  for (int i = 0; i < 40; ++i) {
    const double f = 0.5 * (keep + drop);
    OutputMap s = map;
    s.quadratic_nm *= f, s.cubic_nm *= f;
    (s.min_slope() >= kMinMapSlope ? keep : drop) = f;
  }
  map.quadratic_nm *= keep, map.cubic_nm *= keep;
  return map;
}

// The options that refit the same structure (plays, creep input and law, hold weight) on shifted positions.
YAML::Node same_structure(const PiCreepModel& m, const YAML::Node& options) {
  YAML::Node o = refit_options(m, options);
  o["output_map"] = "off";
  if (!o["thresholds_v"] && !o["n_play"]) o["thresholds_v"] = m.thresholds_v();
  if (m.creep().kind != models::CreepKind::kNone && !o["creep_input"])
    o["creep_input"] = m.creep().on_hysteresis ? "hysteresis" : "voltage";
  if (!m.preisach() && !o["input_map"]) o["input_map"] = m.has_input_map() ? "on" : "off";
  if (!o["hold_weight"]) {
    const auto it = m.meta.validation.find("fit_hold_weight");
    const double f = it == m.meta.validation.end() ? 1.0 : it->second;
    if (f > 1.0) o["hold_weight"] = f;
    else o["hold_weight"] = "off";
  }
  return o;
}

// The plain fit as the kind's own fit returns it: without what fit_model adds afterwards (the training spans,
// the data's origin, the state prior, which the variant learns for itself).
models::ModelPtr plain_fit_as_fitted(const models::Model& plain) {
  models::ModelPtr m = plain.clone();
  m->meta.trained_on.clear();
  m->meta.fitted_on.clear();
  m->meta.state_prior.clear();
  return m;
}

}  // namespace

std::string output_map_option(const YAML::Node& options) {
  const std::string v = option_str(options, "output_map", "off");
  if (v != "auto" && v != "on" && v != "off")
    throw std::runtime_error("option 'output_map': expected auto, on or off, got '" + v + "'");
  return v;
}

models::ModelPtr fit_with_output_map(const FitRequest& req, bool always, const FitFn& fit) {
  models::ModelPtr first = req.plain_fit ? plain_fit_as_fitted(*req.plain_fit) : fit(req);
  PiCreepModel* base = first->pi_family();
  if (!base) return first;
  const bool validate = req.validation && req.validation->has_axis(req.axis) && !always;
  if (!always && !validate) return first;
  // Alternation: the map on the last fit's residual against the measured positions, the kind refitted (same
  // structure) on the positions less the map's bend.
  OutputMap map = fit_map(*base, *req.train, req.axis);
  if (map.empty()) return first;
  models::ModelPtr second;
  PiCreepModel* refit = base;
  FitRequest r = req;
  r.lasso_cache = nullptr;
  r.plain_fit = nullptr;
  r.options.reset(same_structure(*base, req.options));  // reset: assignment would write into the caller's node
  io::Dataset shifted = *req.train;
  for (int pass = 0; pass < kMapPasses; ++pass) {
    const std::vector<double> H = map_input_series(*refit, *req.train, req.axis);
    const auto& y0 = req.train->axis(req.axis).position_nm;
    auto& y = shifted.axis(req.axis).position_nm;
    for (std::size_t i = 0; i < y.size(); ++i) y[i] = y0[i] - (map(H[i]) - H[i]);
    r.train = &shifted;
    second = fit(r);
    refit = second->pi_family();
    if (!refit) return first;
    map = fit_map(*refit, *req.train, req.axis);
    if (map.empty()) return first;
  }
  refit->set_output_map(map);
  refit->meta = base->meta;
  refit->meta.validation["fit_output_map"] = 1.0;
  if (!validate) return second;
  const std::size_t block = static_cast<std::size_t>(std::max(1.0, kCompareBlockS * req.validation->sample_rate_hz()));
  const auto e_with = moving_block_errors(*refit, *req.validation, req.axis, block);
  const auto e_without = moving_block_errors(*base, *req.validation, req.axis, block);
  if (e_with.size() >= kMinCompareBlocks * block && validation_prefers(e_with, e_without, block)) return second;
  base->meta.validation["fit_output_map"] = 0.0;
  return first;
}

}  // namespace piezo::training
