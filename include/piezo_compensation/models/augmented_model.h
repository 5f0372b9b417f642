// A base model plus extra effect terms found by the residual tool (analysis/residual/residual.h), kind "augmented".
//   prediction = base prediction + offset_nm + Σ_terms w · z_term(inputs, base prediction)
// Each term is a small causal regressor generator (lag, low-pass, play, sin/cos, powers) on one signal: the own
// voltage, the base model's predicted position, the data time, or a named data column (another axis' voltage,
// an auxiliary signal such as a temperature). Columns and time enter through ModelInput::aux (see aux_inputs()).
// The base model is committed with (position − correction), so it keeps seeing the part of the signal it was
// fitted to: in free-run that is exactly its own free-run, so the terms can be fitted on the base residual.
// Each term acts on the stage's position (a stage effect: what the feedforward must position) or only on the
// readings (a sensor effect, acts_on: readings, e.g. the encoder's interpolation error). predict() gives what the
// encoder reads (base + offset + every term), as the residual loop fits it; with set_stage_position(true) it gives
// the stage position (the sensor terms left out), and sensor_part_nm() what the sensor terms add to the readings:
// the compensator inverts the stage position and hands the sensor part to the estimator's reading model.
#pragma once

#include <yaml-cpp/yaml.h>

#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/models/model.h"

namespace piezo::models {

// Signal names a term can read besides data columns.
inline constexpr const char* kSignalVoltage = "voltage";    // this axis' applied voltage [V]
inline constexpr const char* kSignalPosition = "position";  // the base model's predicted position [nm]
inline constexpr const char* kSignalTime = "time_s";        // the data's time column [s] (read as an input)
// Where a term acts (EffectTerm::acts_on).
inline constexpr const char* kActsOnPosition = "position";
inline constexpr const char* kActsOnReadings = "readings";

// The term types (EffectTerm::type in a model file; term_kind and term_kind_name convert, the one place the names
// are read). The order is the C export's term code (models/c_export.h).
enum class TermKind { kLinear, kPlay, kSinCos, kRate, kPowers, kGain, kGainQuadratic };
TermKind term_kind(const std::string& type);  // throws std::runtime_error naming the known types
const char* term_kind_name(TermKind kind);

struct EffectTerm {
  // "linear"          [y]                                   y = lowpass_τ(lag_L(s))
  // "play"            [lowpass_τ(play_r(lag_L(s)))]          hysteretic memory of a signal
  // "sincos"          [sin(2π y/period), cos(2π y/period)]   y = lag_L(s); period in the signal's unit
  // "rate"            [d, |d|, sign(d)·d²], each low-passed τ d = s_t − s_{t−1}
  // "powers"          [u², u³], u = (s − pre_center)/pre_scale
  // "gain"            [(q − reference)·g]                    q = `scales` (base output or voltage), g below
  // "gain_quadratic"  [(q − reference)·g, (q − reference)·g²], g = (lowpass_τ(lag_L(s)) − pre_center)/pre_scale
  //                   a gain effect: the base output (or the voltage, to first order) scaled by 1 + f(signal)
  std::string type = "linear";
  std::string signal = kSignalVoltage;
  std::string family;              // effect family it was added for (report only)
  double lag_s = 0.0;
  double time_constant_s = 0.0;    // 0 = no low-pass
  double threshold = 0.0;          // play threshold, in the signal's unit
  double period = 0.0;             // sincos period, in the signal's unit (s for time, nm for position)
  double pre_center = 0.0, pre_scale = 1.0;  // powers and gains: centring of the signal
  std::string scales = kSignalPosition;      // gains: what is scaled, "position" (base output) or "voltage"
  // Where the effect is: "position" (the stage moves: prediction and feedforward) or "readings" (only the
  // encoder reads it: the estimator's reading model). Files without the key: position.
  std::string acts_on = kActsOnPosition;
  bool in_readings() const { return acts_on == kActsOnReadings; }
  double reference = 0.0;                    // gains: value of the scaled quantity the gain acts about
  TermKind kind() const { return term_kind(type); }  // throws for an unknown type
  bool is_gain() const { return kind() == TermKind::kGain || kind() == TermKind::kGainQuadratic; }
  // Standardisation of each raw regressor (fitted on training data) and its weight [nm per standardised unit].
  std::vector<double> center, scale, weight;

  std::size_t num_regressors() const;
  std::string name() const;  // e.g. "sincos(position, P=150 nm)"
  YAML::Node to_yaml() const;
  static EffectTerm from_yaml(const YAML::Node& node);  // throws std::runtime_error naming the bad key
};

// Streaming state of a list of terms at one sample rate: the one path used by fitting, search and prediction.
// Terms on "position" read the corrected position x_base + offset + (weighted non-position terms), so a
// position-periodic error is looked up at the drift-corrected position, not at the base model's.
class EffectTermStream {
 public:
  EffectTermStream(std::vector<EffectTerm> terms, double sample_rate_hz, double offset_nm = 0.0);
  ~EffectTermStream();
  EffectTermStream(const EffectTermStream&);
  EffectTermStream& operator=(const EffectTermStream&);

  // Column signals (data columns, incl. "time_s") the terms read, in the order `columns` must supply them.
  const std::vector<std::string>& column_signals() const;
  std::size_t num_regressors() const;
  const std::vector<EffectTerm>& terms() const;
  double offset_nm() const;
  void set_offset_nm(double offset_nm);

  void reset();
  // Raw (unstandardised) regressors of the current sample; state unchanged.
  void raw(double voltage_v, double base_position_nm, const double* columns, double* out) const;
  // Standardised regressors (using each term's center/scale).
  void standardised(double voltage_v, double base_position_nm, const double* columns, double* out) const;
  // offset + Σ w · standardised regressors; with `readings_nm`, the part of it the readings-only terms give.
  double correction(double voltage_v, double base_position_nm, const double* columns, double* readings_nm = nullptr) const;
  // Commits the sample; returns its correction (what correction() gave before the commit), from the same pass.
  double commit(double voltage_v, double base_position_nm, const double* columns, double* readings_nm = nullptr);
  // raw() then commit() in one pass over the terms (each term reads only its own state): the same numbers.
  void raw_and_commit(double voltage_v, double base_position_nm, const double* columns, double* out);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

class AugmentedModel : public Model {
 public:
  AugmentedModel(ModelPtr base, std::vector<EffectTerm> terms, double offset_nm, double sample_rate_hz);
  AugmentedModel(const AugmentedModel& other);

  std::string kind() const override { return "augmented"; }
  void reset(double voltage_v, double position_nm) override;
  double predict(const ModelInput& in) const override;
  void commit(const ModelInput& in, double position_nm) override;
  std::unique_ptr<Model> clone() const override;
  bool uses_position_history() const override;
  bool is_affine_in_voltage() const override;
  std::vector<std::string> aux_inputs() const override;  // base model's first, then the terms' columns
  YAML::Node to_yaml() const override;
  std::size_t num_parameters() const override;
  std::vector<double> creep_mode_taus_s() const override;
  // The base model's (the terms' states are not linear states).
  std::size_t linear_state_count() const override { return base_->linear_state_count(); }
  double linear_state_nm(std::size_t k) const override { return base_->linear_state_nm(k); }
  void shift_linear_state(std::size_t k, double delta_nm) override { base_->shift_linear_state(k, delta_nm); }
  // The base's reason, or the terms' when one counts a lag, a low-pass or a difference in samples; else any step.
  std::string fixed_rate_reason() const override;
  void set_step_s(double dt_s) override;

  const Model& base() const { return *base_; }
  const std::vector<EffectTerm>& terms() const { return stream_.terms(); }
  double offset_nm() const { return stream_.offset_nm(); }
  double sample_rate_hz() const { return sample_rate_hz_; }
  // Base prediction and correction for the current sample (for reports and tests).
  double base_prediction(const ModelInput& in) const;
  // What the sensor terms (acts_on: readings) add to the readings at the current sample (0 without any).
  double sensor_part_nm(const ModelInput& in) const;
  bool has_sensor_terms() const;
  // true: predict() gives the stage position (the sensor terms left out) and commit() takes one (the base is
  // committed with position − the stage terms' correction). false (the default): what the encoder reads. A runtime
  // setting, not stored in the file; copies keep it.
  void set_stage_position(bool on) { stage_position_ = on; }
  bool stage_position() const { return stage_position_; }

  static ModelPtr from_yaml(const YAML::Node& model_node);

  // While set (non-null), commit() appends the base part of the sample's prediction — the base model's own
  // prediction — to *trace, so one stream gives the model's predictions and its base's (compensation/
  // base_handover.h). The caller keeps *trace alive while it is set; a copy or clone() starts without one.
  void set_base_trace(std::vector<double>* trace) { base_trace_ = trace; }

  // Whether `running` (or its base, when it is augmented itself) is this model's base — kind and every parameter —
  // and reads no inputs: then adopt_base_state takes its state (compensation/base_handover.h).
  bool can_adopt_base_state(const Model& running) const;
  // The base becomes a copy of running's (state included); offset_change_nm is added to the offset.
  // Throws std::invalid_argument unless can_adopt_base_state(running).
  void adopt_base_state(const Model& running, double offset_change_nm);

 private:
  void split(const ModelInput& in, std::vector<double>& base_aux, std::vector<double>& cols) const;

  ModelPtr base_;
  EffectTermStream stream_;
  double sample_rate_hz_ = 11.0;
  std::size_t n_base_aux_ = 0;
  std::vector<std::string> aux_names_;
  std::vector<int> col_index_;  // term column j → index into ModelInput::aux
  std::vector<double>* base_trace_ = nullptr;
  bool stage_position_ = false;
};

}  // namespace piezo::models
