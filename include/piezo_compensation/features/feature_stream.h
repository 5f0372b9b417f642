// Declarative, causal features with windows in seconds, computed one sample at a time.
#pragma once

#include <yaml-cpp/yaml.h>

#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/features/model_input.h"

namespace piezo::features {

// One feature. Windows, lags and time constants are in seconds and converted to samples with the data's
// sample rate, so a spec fitted at 11 Hz means the same physical thing at any other constant rate.
struct FeatureDef {
  // "voltage"           V_t
  // "voltage_sq"        V_t²                          (asymmetric hysteresis: the modified PI's polynomial term)
  // "voltage_step"      V_t - V_{t-1}
  // "step_sum"          V_t - V_{t-w}                 (sum of the past steps over window_s)
  // "exp_sum"           Σ_{k=0}^{w-1} α^k V_{t-k}      (α from decay; window_s = w; study's rolling exponential sum)
  // "lowpass"           first-order low-pass of V with time_constant_s (infinite exponential memory)
  // "play"              play (backlash) operator of V with threshold_v
  // "stop"              stop (elastic-perfectly-plastic) operator of V with threshold_v
  // "play_lowpass"      low-pass (time_constant_s) of the play operator output (threshold_v): creep of hysteresis
  // "play_hinge"        max(play(V, threshold_v) − knot_v, 0): an open ramp of a play output above knot_v; weighted
  //                     sums over knots give any piecewise-linear map of it (the preisach kinds' pieces)
  // "lagged_position"   D_{t-L}, L = lag_s in samples (L ≥ 1)
  // "position_mean"     mean of D_{t-w} … D_{t-1}      (past samples only; the study's mean included D_t)
  // "aux"               auxiliary signal `signal` (optionally lagged by lag_s and low-passed by time_constant_s)
  std::string type;
  double window_s = 0.0;
  double decay = 0.0;            // α per sample for exp_sum, 0 < α < 1
  double time_constant_s = 0.0;
  double threshold_v = 0.0;
  double knot_v = 0.0;           // play_hinge knot [V]
  double lag_s = 0.0;
  std::string signal;            // for "aux"

  std::string name() const;      // human-readable, e.g. "exp_sum(V, 5.45 s, a=0.95)"
  bool reads_position() const;   // lagged_position, position_mean: the model's own past positions in free run
};

struct FeatureSpec {
  std::vector<FeatureDef> features;
  // Standardisation applied after computing: (x - mean) / scale. Empty = identity. Fitted on training data.
  std::vector<double> mean, scale;

  YAML::Node to_yaml() const;
  static FeatureSpec from_yaml(const YAML::Node& node);  // throws std::runtime_error naming the bad key
  bool uses_positions() const;
  std::vector<std::string> aux_signals() const;
  std::size_t size() const { return features.size(); }
};

// Streaming state for one FeatureSpec at one sample rate.
class FeatureStream {
 public:
  FeatureStream(const FeatureSpec& spec, double sample_rate_hz);
  ~FeatureStream();
  FeatureStream(const FeatureStream&);
  FeatureStream& operator=(const FeatureStream&);

  void reset(double voltage_v, double position_nm);
  // Standardised features of the current sample for input `in` (state unchanged). out has size() entries.
  void compute(const ModelInput& in, double* out) const;
  // Advance the history with the applied input and the remembered position.
  void commit(const ModelInput& in, double position_nm);
  std::size_t size() const;
  const FeatureSpec& spec() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace piezo::features
