// Fusing a model with a noisy, quantised encoder (docs/predictor.md, "Estimator"). ROS-free.
//
// The model's prediction p is the filter's known input; its state is the model's error e = truth − p, in two
// parts: a slow part (random walk: what stays wrong after the stage settles — branch and creep mismatch) and a
// fast part (first-order Gauss–Markov, time constant fast_tau_s: the part of the error that settles after a move).
// Both grow with the model's own motion |Δp|, so the filter is tight in long holds and honest after moves. The
// reading y = p + e + v, v ~ N(0, σ²) with σ the reading noise including the encoder step (dithered readings).
// The same filter is the start-up estimate: its initial covariance is the model's error at a cold start, which
// the first readings pin down.
//
// Where the encoder step is large against the noise (σ < q/2, the 250 nm steps of axes a/b) the readings'
// mean is biased by up to q/2 and averaging does not remove it: the axis runs model-only (fused = model) and
// says so, so it is never worse than feedforward.
#pragma once

#include <array>
#include <cstddef>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <yaml-cpp/yaml.h>

namespace piezo::estimation {

// The noise model of one axis' model error: identified from data (identify_noise_model), stored in the model
// file's `estimator:` block, read by the predictor and `piezo track`.
struct NoiseModel {
  double reading_sigma_nm = 0.0;    // σ of one reading about the truth, quantisation included
  double step_nm = 0.0;             // encoder step (0 = not quantised)
  double q_rest_nm2_per_s = 0.0;    // slow error: variance rate at rest
  double q_motion_nm = 0.0;         // slow error: variance per nm of predicted motion [nm²/nm]
  double q_fast_nm = 0.0;           // fast error: variance per nm of predicted motion [nm²/nm]
  double fast_tau_s = 30.0;         // fast error: settling time constant
  double initial_sigma_nm = 0.0;    // 1σ of the model's error when it starts at rest on a reading (cold start)
  double model_sigma_nm = 0.0;      // model-only axes: the model's slow error, 1σ (what the σ output reports)
  // Innovation consistency: the mean of the innovations over adapt_window_s, 6× and 30× that (10 s, 1 min, 5 min)
  // is tested against its own standard error; beyond adapt_k of them the filter lags a change its process noise did
  // not expect (a jump: a move whose error is larger than those it was identified on; a ramp: creep mismatch or an
  // unmodelled drift in a long hold), and the slow error's variance is raised by that mean's square. adapt_k = 0
  // turns it off. 3 standard errors (0.27 % per independent test); each window is tested at every sample, so a
  // consistent filter still trips now and then, each trip costing only a brief loss of averaging.
  double adapt_window_s = 10.0;
  double adapt_k = 3.0;
  bool fuse = true;                 // false: the readings cannot inform this axis (see the header)
  std::string method;               // how it was identified (one line)
  std::size_t samples = 0;          // readings the identification used
  double log_likelihood = 0.0;      // per reading, at the identified parameters

  YAML::Node to_yaml() const;
  // Throws std::invalid_argument naming `where` and the key when a field is missing, not a number or out of range.
  static NoiseModel from_yaml(const YAML::Node& node, const std::string& where);
  std::string describe() const;     // one line for reports and diagnostics
};

// Dithered readings (Widrow): the noise before the quantiser is at least half a step, so the mean of the
// readings is unbiased. Otherwise the axis runs model-only.
bool readings_inform(double reading_sigma_nm, double step_nm);

class ErrorFilter {
 public:
  ErrorFilter(const NoiseModel& model, double dt_s);  // throws std::invalid_argument for dt_s ≤ 0
  void reset();  // e = 0 with the cold-start covariance (a start, or a model restarted at the measurement)
  // A start whose slow error is already known: the start-up state estimate's offset and its 1σ (models/
  // start_state.h: measured − predicted over the start window). reset() is reset(0, initial_sigma_nm); a
  // non-finite σ falls back to initial_sigma_nm. Throws std::invalid_argument for a non-finite offset or σ < 0.
  void reset(double slow_error_nm, double slow_sigma_nm);
  // One sample: the model's prediction (its change from the last sample drives the process noise), then the
  // reading when `valid` (a lost or stale reading: predict only, the covariance grows).
  void step(double predicted_nm, double measured_nm, bool valid);

  double error_nm() const { return x_(0) + x_(1); }
  double fused_nm() const { return last_p_ + (model_.fuse ? error_nm() : 0.0); }
  double sigma_nm() const;
  double slow_error_nm() const { return x_(0); }
  bool fusing() const { return model_.fuse; }
  const NoiseModel& noise_model() const { return model_; }
  // Sum over readings of the Gaussian log-likelihood of the innovations (the prediction-error decomposition).
  double log_likelihood() const { return loglik_; }
  std::size_t updates() const { return updates_; }
  std::size_t samples_since_reading() const { return since_reading_; }
  double last_innovation_nm() const { return innovation_; }
  std::size_t adaptations() const { return adaptations_; }  // times the consistency test raised the variance

 private:
  void check_consistency(double s);
  NoiseModel model_;
  double dt_s_, phi_, r_;
  bool started_ = false;
  double last_p_ = 0.0;
  Eigen::Vector2d x_ = Eigen::Vector2d::Zero();
  Eigen::Matrix2d P_ = Eigen::Matrix2d::Zero();
  double loglik_ = 0.0, innovation_ = 0.0;
  std::size_t updates_ = 0, since_reading_ = 0;
  struct Window {  // exponential means of the innovations and of their variance over one time scale
    std::size_t n = 0, count = 0;
    double alpha = 0.0, nu_bar = 0.0, s_bar = 0.0;
  };
  std::array<Window, 3> windows_;
  std::size_t adaptations_ = 0;
};

struct IdentifyOptions {
  double dt_s = 1.0 / 11.0;
  double reading_sigma_nm = 0.0;   // from the noise floor of the data (analysis/noise_floor.h); > 0
  double step_nm = 0.0;
  // Fast time constants tried; each gets its own maximum-likelihood fit of the three variance rates.
  std::vector<double> fast_tau_grid_s{5.0, 20.0, 60.0, 200.0};
  std::size_t max_evaluations = 400;   // Nelder–Mead per time constant
};

// Maximum likelihood of the filter's variance rates on one run of the model over data (free-run predictions and
// the readings; NaN readings are lost ones). The data should be held out from the model's fit (its validation
// part), else the model's error — and so the process noise — is underestimated. Throws std::invalid_argument for
// mismatched lengths, fewer than 200 readings, or σ ≤ 0.
NoiseModel identify_noise_model(const std::vector<double>& predicted_nm, const std::vector<double>& measured_nm,
                                const IdentifyOptions& options);

// The filter run over a whole series (offline: `piezo track`, identification, tests).
struct FilterTrace {
  std::vector<double> fused_nm, sigma_nm;
  double log_likelihood = 0.0;
};
FilterTrace run_filter(const NoiseModel& model, double dt_s, const std::vector<double>& predicted_nm,
                       const std::vector<double>& measured_nm);

}  // namespace piezo::estimation
