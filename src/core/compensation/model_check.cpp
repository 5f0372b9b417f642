#include "piezo_compensation/compensation/model_check.h"

#include <fstream>
#include <stdexcept>

#include "piezo_compensation/compensation/live_inputs.h"
#include "piezo_compensation/models/model_file.h"

namespace piezo::compensation {

models::ModelPtr load_compensator_model(const std::string& path, const std::string& axis) {
  if (path.empty()) throw std::runtime_error("no model file given");
  if (!std::ifstream(path)) throw std::runtime_error(path + ": cannot open model file");
  models::ModelPtr m;
  try {
    m = models::load_model(path);
  } catch (const std::exception& e) {
    const std::string what = e.what();
    throw std::runtime_error(what.find(path) == std::string::npos ? path + ": " + what : what);
  }
  if (!m) throw std::runtime_error(path + ": model file gave no model");
  if (!axis.empty()) models::check_model_axis(*m, axis, path);
  try {
    InputFeeder check(*m, m->meta.axis, {});  // inputs the predictor can feed, right clock
  } catch (const std::exception& e) {
    throw std::runtime_error(path + ": " + e.what());
  }
  if (!(m->meta.sample_rate_hz > 0.0)) throw std::runtime_error(path + ": model has no positive sample_rate_hz");
  return m;
}

TransportCheck check_model_transport(const models::ModelMeta& meta, bool real_transport, bool allow_simulated,
                                     const std::string& path, const std::string& allow_param) {
  TransportCheck c;
  if (!real_transport) return c;
  if (meta.fitted_on == models::kFittedOnSimulated) {
    if (allow_simulated)
      c.warning = path + ": fitted on simulated data, run on a real transport because " + allow_param +
                  " is true: it compensates the simulator's physics, not the rig's";
    else
      c.error = path + ": fitted on simulated data, refused on a real transport (fit a model on a recording of "
                "this rig, or set " + allow_param + " to true to run it anyway)";
  } else if (meta.fitted_on.empty()) {
    c.warning = path + ": the model file does not say what it was fitted on (no training.fitted_on): run as "
                "fitted on a recording; refit it if it was fitted on simulated data";
  }
  return c;
}

}  // namespace piezo::compensation
