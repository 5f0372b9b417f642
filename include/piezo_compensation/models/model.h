// The one streaming model interface used offline (fit, eval, residual) and live (predictor, inverse, forecast).
#pragma once

#include <yaml-cpp/yaml.h>

#include <limits>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/features/model_input.h"

namespace piezo::models {

// The input of one sample (features/model_input.h): the layer below models owns it, models use it.
using ModelInput = features::ModelInput;

class PiCreepModel;  // models/pi_model.h

// Where training-like operation keeps one linear state (Model::linear_state_nm): a line in the applied voltage and
// the scatter about it, both over the model's free run on its training data. The start estimate's prior for a
// history it has not seen (models/start_state.h).
struct LinearStatePrior {
  double intercept_nm = 0, slope_nm_per_v = 0, sigma_nm = 0;
};

// One recording (or part of one) a model was trained on: its own times, rows and a hash of its axis' voltage and
// position (models/model_file.h, training_spans), so a tool can tell the same rows when it meets them again.
struct TrainingSpan {
  std::string source;
  double begin_s = 0, end_s = 0;
  std::size_t rows = 0;
  std::string fingerprint;
};

// ModelMeta::fitted_on: what the training data was (io::data_origin at fit time; the file's training.fitted_on).
inline constexpr const char* kFittedOnSimulated = "simulated";
inline constexpr const char* kFittedOnRecorded = "recorded";

// Facts about a fitted model, stored in the model file beside the weights.
struct ModelMeta {
  std::string axis = "c";
  double sample_rate_hz = 11.0;
  std::string training_fingerprint;            // hash of the training data (see io::fingerprint)
  std::string training_source;                 // file(s) it was fitted on
  std::vector<TrainingSpan> trained_on;        // each training recording (empty: an older model file)
  // "simulated" or "recorded" (kFittedOn*); "" = not known (a model file written before the field): the predictor
  // refuses a simulated model on a real transport (compensation/model_check.h).
  std::string fitted_on;
  std::string time_clock;                      // what the training data's time_s was: "ros" (ROS time stamps,
                                               // a bag the nodes wrote) or "" (the data file's own time base)
  // The applied voltage's range in the training data [V] (NaN: not known): where a history the model has not seen
  // can have been (the start-up state estimate's synthetic histories span it).
  double train_voltage_min_v = std::numeric_limits<double>::quiet_NaN();
  double train_voltage_max_v = std::numeric_limits<double>::quiet_NaN();
  std::vector<LinearStatePrior> state_prior;   // per linear state (empty: not learned, e.g. an older model file)
  std::map<std::string, double> validation;    // e.g. {"one_step_mae_nm": 17.1, "free_run_mae_nm": 6.2}
  std::string created_utc;
  YAML::Node selection;                        // `--model auto`: the candidates' scores and the choice (or null)
  YAML::Node estimator;                        // the error filter's noise model (estimation/error_filter.h), or null
};

// Model::fixed_rate_reason of the kinds on the feature stream (linear and the neural kinds).
inline constexpr const char* kLaggedSamplesReason =
    "its features are lagged samples and windows counted in samples of the training rate";

class Model {
 public:
  virtual ~Model() = default;

  // Short kind name used in model files and on the command line: "linear", "dense", "lstm", "kan", "pi",
  // "pi_creep_log", "pi_creep_lti", "pi_creep_fractional", ...
  virtual std::string kind() const = 0;

  // Forget the history: the piezo has rested long at `voltage_v`, at `position_nm`.
  virtual void reset(double voltage_v, double position_nm) = 0;

  // Position [nm] at the current sample if `in` is applied now, given the committed history. Const: the
  // inverse and the drift forecast call it many times per sample with candidate voltages.
  virtual double predict(const ModelInput& in) const = 0;

  // Appends the current sample to the history: the input actually applied and the position to remember
  // for lagged-position features — the measurement in one-step mode, the model's own prediction in free-run.
  virtual void commit(const ModelInput& in, double position_nm) = 0;

  // Deep copy including the state (for look-ahead: drift forecast, inverse search, free-run branches).
  virtual std::unique_ptr<Model> clone() const = 0;

  // True when predict() reads remembered positions (so one-step and free-run differ).
  virtual bool uses_position_history() const = 0;

  // True when, for the current state, predict() is affine in voltage_v: then the inverse is closed form,
  // v = v0 + (target - predict(v0)) / slope, with slope from two predictions.
  virtual bool is_affine_in_voltage() const { return false; }

  // Names of the auxiliary input signals (data columns) the model reads through ModelInput::aux.
  virtual std::vector<std::string> aux_inputs() const { return {}; }

  // Kind-specific parameters and weights, written under the file's `model:` key (see model_file.h).
  virtual YAML::Node to_yaml() const = 0;

  // Number of trainable parameters (for reports).
  virtual std::size_t num_parameters() const = 0;

  // Linear states (the start-up state estimate, models/start_state.h): parts of the state whose effect on the
  // prediction adds linearly and then evolves on its own (creep modes: a shift decays with the mode's time
  // constant, whatever the input does). A recording's first seconds fit them by least squares.
  virtual std::size_t linear_state_count() const { return 0; }
  // State k's share of the next prediction [nm] (k < linear_state_count()).
  virtual double linear_state_nm(std::size_t /*k*/) const { return 0.0; }
  // Moves state k so that the next prediction changes by delta_nm (later ones by what the state makes of it).
  virtual void shift_linear_state(std::size_t /*k*/, double /*delta_nm*/) {}

  // What a tool asks of a kind without knowing it:
  // the time constants [s] of the creep modes (empty: none); an augmented model answers for its base.
  virtual std::vector<double> creep_mode_taus_s() const { return {}; }
  // The PI or Preisach model this is (null for every other kind): its play thresholds, creep law and maps, for a
  // refit of the same structure, the output map's fit and the C export.
  virtual const PiCreepModel* pi_family() const { return nullptr; }
  virtual PiCreepModel* pi_family() { return nullptr; }
  // Whether the kind takes an output map, a monotone bend of its hysteresis output (training/fitters.h).
  virtual bool takes_output_map() const { return false; }
  // Sample period. A kind whose time constants are in seconds (PI/Preisach hysteresis with creep modes) runs on
  // any step: set_step_s(dt) makes the next commit advance dt seconds (a jittered recording's own row steps).
  // fixed_rate_reason() is "" for such a kind, else why it runs only at meta.sample_rate_hz (lagged samples,
  // windows counted in samples); then set_step_s throws std::invalid_argument with that reason for a step more
  // than kStepTolerance from 1 / meta.sample_rate_hz.
  static constexpr double kStepTolerance = 0.01;  // relative
  virtual std::string fixed_rate_reason() const {
    return "kind '" + kind() + "' steps once per sample of its training rate";
  }
  virtual void set_step_s(double dt_s) { check_fixed_step(dt_s); }
  bool runs_at_any_rate() const { return fixed_rate_reason().empty(); }

  ModelMeta meta;

 protected:
  // Throws std::invalid_argument (with fixed_rate_reason()) unless dt_s is the training rate's step.
  void check_fixed_step(double dt_s) const;
};

using ModelPtr = std::unique_ptr<Model>;

}  // namespace piezo::models
