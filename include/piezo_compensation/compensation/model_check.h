// What a model file must be for the per-axis compensator to drive it (the predictor's ~model_file, the demo's
// model), the stand-in when it is not, and the rule for a model fitted on simulated data on a real transport.
// ROS-free: the predictor node logs and reports what these return.
#pragma once

#include <cmath>
#include <memory>
#include <string>

#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

// Stand-in when a model file cannot be loaded: every prediction is NaN, so the axis runs on the uncorrected
// command with bounded steps and says why, instead of the node refusing to move the piezo.
class UnavailableModel : public models::Model {
 public:
  std::string kind() const override { return "unavailable"; }
  void reset(double, double) override {}
  double predict(const models::ModelInput&) const override { return std::nan(""); }
  void commit(const models::ModelInput&, double) override {}
  models::ModelPtr clone() const override { return std::make_unique<UnavailableModel>(*this); }
  bool uses_position_history() const override { return false; }
  YAML::Node to_yaml() const override { return YAML::Node(); }
  std::size_t num_parameters() const override { return 0; }
};

// Loads a model file (models/model_file.h) and checks it can be driven by the compensator: with `axis`, that it
// was fitted for that axis (models::check_model_axis); that its inputs can be fed live (compensation::InputFeeder);
// that it has a positive sample rate. Throws std::runtime_error with one line naming the file.
models::ModelPtr load_compensator_model(const std::string& path, const std::string& axis = "");

// Where a model may run (ModelMeta::fitted_on against the transport the commands go to).
struct TransportCheck {
  std::string error;    // non-empty: refused; one line naming the model file and allow_param
  std::string warning;  // non-empty: allowed, but the operator should know (a simulated model allowed, or unknown)
};
// A model fitted on simulated data (fitted_on "simulated") on a real transport is refused unless allow_simulated
// (the parameter named allow_param, e.g. "~allow_simulated_model"): the simulator's physics is not the rig's.
// A model file that does not say (fitted_on "", written before the field) is run as recorded, with a warning on a
// real transport. On a simulated transport every model runs.
TransportCheck check_model_transport(const models::ModelMeta& meta, bool real_transport, bool allow_simulated,
                                     const std::string& path, const std::string& allow_param);

}  // namespace piezo::compensation
