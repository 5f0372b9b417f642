#include "piezo_compensation/analysis/estimator_fit.h"

#include <stdexcept>

#include "piezo_compensation/analysis/noise_floor.h"
#include "piezo_compensation/models/model_stream.h"

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
  nm.method += "; reading σ from " + floor.method;
  return nm;
}

}  // namespace piezo::analysis
