#include "piezo_compensation/analysis/residual/estimator_fit.h"

#include <stdexcept>

#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/estimation/forecast.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::analysis {

estimation::NoiseModel identify_estimator(const models::Model& model, const io::Dataset& data,
                                          const std::string& axis, std::size_t first_row) {
  if (first_row >= data.size()) throw std::invalid_argument("identify_estimator: no rows after the first_row");
  models::ModelPtr m = model.clone();
  models::StreamOptions so;
  so.mode = models::PredictionMode::kFreeRun;
  const models::StreamResult run = models::stream_model(*m, data, axis, so);
  const io::AxisSeries& ax = data.axis(axis);
  std::vector<double> p(run.prediction.begin() + first_row, run.prediction.end());
  std::vector<double> y(ax.position_nm.begin() + first_row, ax.position_nm.end());
  const io::Dataset part = data.slice(first_row, data.size());
  const NoiseFloor floor = estimate_noise_floor(part, axis, &p);
  estimation::IdentifyOptions o;
  o.dt_s = data.sample_period_s();
  o.reading_sigma_nm = floor.sigma_nm;
  o.step_nm = floor.quantisation_nm;
  estimation::NoiseModel nm = estimation::identify_noise_model(p, y, o);
  const std::vector<double> v(ax.voltage_v.begin() + first_row, ax.voltage_v.end());
  estimation::ForecastCalibrationOptions co;
  io::HoldRule rule;  // the forecast table's holds (piezo track): ≥ 300 s of an unchanged voltage
  rule.min_duration_s = 300.0;
  rule.use_phase = false;
  rule.tolerance_v = 0.0;
  for (const io::HoldRun& h : io::find_holds(data, axis, rule, first_row))
    co.holds.emplace_back(h.begin - first_row, h.end - first_row);
  estimation::calibrate_forecast(nm, o.dt_s, p, y, v, co);
  nm.method += "; reading σ from " + floor.method;
  return nm;
}

std::vector<double> fused_position(const models::Model& model, const io::Dataset& data, const std::string& axis,
                                   const io::Dataset* warmup) {
  models::ModelPtr m = model.clone();
  models::StreamOptions so;
  so.mode = models::PredictionMode::kFreeRun;
  std::vector<double> p, y;
  if (warmup) {
    p = models::stream_model(*m, *warmup, axis, so).prediction;
    y = warmup->axis(axis).position_nm;
    so.reset = false;
  }
  const std::size_t first = p.size();
  const std::vector<double> pd = models::stream_model(*m, data, axis, so).prediction;
  p.insert(p.end(), pd.begin(), pd.end());
  const std::vector<double>& yd = data.axis(axis).position_nm;
  y.insert(y.end(), yd.begin(), yd.end());
  if (!model.meta.estimator || model.meta.estimator.IsNull()) return pd;
  const estimation::NoiseModel nm =
      estimation::NoiseModel::from_yaml(model.meta.estimator, "the " + axis + " model's estimator block");
  if (!nm.fuse) return pd;
  const estimation::FilterTrace t = estimation::run_filter(nm, data.sample_period_s(), p, y);
  return std::vector<double>(t.fused_nm.begin() + static_cast<long>(first), t.fused_nm.end());
}

models::ModelPtr fit_axis_model(const io::Dataset& train, std::size_t n_fit, const std::string& axis,
                                const std::string& kind, std::uint64_t seed, bool estimator) {
  if (n_fit == 0 || n_fit >= train.size()) throw std::invalid_argument("fit_axis_model: no fit or no validation rows");
  if (kind == "auto") {
    models::ModelPtr m = fit_auto(train, n_fit, axis, seed);
    if (estimator) m->meta.estimator = identify_estimator(*m, train, axis, n_fit).to_yaml();
    return m;
  }
  const io::Dataset fit = train.slice(0, n_fit), val = train.slice(n_fit, train.size());
  training::FitRequest req;
  req.train = &fit;
  req.validation = &val;
  req.axis = axis;
  req.seed = seed;
  models::ModelPtr m = training::fit_model(kind, req);
  if (estimator) m->meta.estimator = identify_estimator(*m, train, axis, n_fit).to_yaml();
  return m;
}

}  // namespace piezo::analysis
