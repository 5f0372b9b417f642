// Fusing a model with a noisy, quantised encoder (docs/estimation.md, docs/predictor.md "Estimator"). ROS-free.
//
// The model's prediction p is the filter's known input; its state is the model's error e = truth − p, in two
// parts: a slow part (random walk: what stays wrong after the stage settles — branch and creep mismatch) and a
// fast part (first-order Gauss–Markov, time constant fast_tau_s: the part of the error that settles after a move).
// Both grow with the model's own motion |Δp|, so the filter is tight in long holds and honest after moves. The
// slow part may also ramp: its rate of change is a third state, a random walk of q_drift_nm2_per_s3 (the creep a
// model with a wrong start state keeps mispredicting through a whole hold; 0 in files without the key). The
// reading is the truth p + e plus Gaussian noise of σ (noise_sigma_nm) before a quantiser of step q (step_nm): its
// exact likelihood (estimation/quantised_reading.h) is the measurement model of every axis. Axis c (20 nm steps,
// σ ≈ 20 nm) is the dithered end of it, axes a/b (250 nm steps) the quantised end, where the information is in the
// crossings during moves and the flicker between two levels in holds.
//
// The update is assumed-density (moment matching): the Gaussian prior times the exact likelihood, projected on a
// Gaussian with its exact mean and variance. Why not a particle filter: for a linear-Gaussian state the posterior
// after any sequence of quantised readings is log-concave (the likelihood is the integral of a Gaussian over an
// interval, a log-concave function of e), so it has one mode and a Gaussian holds it well; the update costs one
// pair of erfc where a particle filter costs hundreds, and its state is five numbers.
//
// Three guards keep the σ honest where a Gaussian summary of the posterior is not:
// - A level read again and again (a hold that does not flicker) says only that the truth stayed inside the cell,
//   away from its edges. The Gaussian's tails beyond the edges are cut at every reading, which would shrink σ far
//   below what the readings know; so while the level is unchanged the error's variance is kept at least
//   min(variance without readings since the level was first read, (q − 2d)²/12), d the margin from the edges that
//   N unchanged readings support (P(no flicker at d) = 1/N), while that region is wider than 2σ (a flat-topped
//   posterior; narrower, as with dithered readings, the repeated levels average down as a Gaussian's would).
// - A stuck encoder: the level unchanged while the model moved further than a step, the error's growth (3σ) and the
//   noise (2σ) can explain since it was first read. Its readings since then are undone (the state goes back to
//   that first reading, with the process noise since) and none is taken until the level changes: the filter
//   predicts, its σ grows, the hold trim sees a stale encoder.
// - A reading more than gate_s predictive σ outside its cell is not taken. When the rejected readings' level
//   changes (the encoder is alive and the model's error is larger than expected: a cold start far off, a move
//   unlike those identified on), the slow error's variance is widened to reach the reading and it is taken.
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
  double reading_sigma_nm = 0.0;    // σ of one reading about the truth, quantisation included: √(σ² + q²/12)
  double step_nm = 0.0;             // encoder step q (0 = not quantised)
  // σ of the noise before the quantiser. Model files without it (identified before the quantised reading model)
  // load with √(reading_sigma_nm² − q²/12).
  double noise_sigma_nm = 0.0;
  double q_rest_nm2_per_s = 0.0;    // slow error: variance rate at rest
  double q_motion_nm = 0.0;         // slow error: variance per nm of predicted motion [nm²/nm]
  double q_fast_nm = 0.0;           // fast error: variance per nm of predicted motion [nm²/nm]
  double q_drift_nm2_per_s3 = 0.0;  // slow error's rate of change: variance rate of its random walk
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
  double gate_s = 5.0;              // readings further than this many predictive σ outside their cell are not taken
  // false: model-only (fused = model). Written by the identification when the readings cannot identify the
  // quantised reading model (fewer than 10 level changes: an encoder that never crosses a level), its method saying
  // why; and by identifications before the quantised reading model for axes whose step is coarse against the noise:
  // such a file keeps loading, and its describe() says to re-identify.
  bool fuse = true;
  // The forecast's σ (estimation/forecast.h): per horizon [s], the scale of the propagated σ while the voltage is
  // held over the horizon and while it moves, calibrated on the identification's data (calibrate_forecast). Empty:
  // the propagated σ unscaled.
  std::vector<double> forecast_horizons_s, forecast_sigma_scale_hold, forecast_sigma_scale_move;
  std::string method;               // how it was identified (one line)
  std::size_t samples = 0;          // readings the identification used
  double log_likelihood = 0.0;      // per reading, at the identified parameters

  YAML::Node to_yaml() const;
  // Throws std::invalid_argument naming `where` and the key when a field is missing, not a number or out of range.
  static NoiseModel from_yaml(const YAML::Node& node, const std::string& where);
  std::string describe() const;     // one line for reports and diagnostics
};

// The filter's state, for a node that resumes (compensation/resume.h): the error's two parts, their covariance and
// the last prediction (the next one's motion drives the process noise).
struct FilterState {
  double slow_nm = 0.0, fast_nm = 0.0, drift_nm_per_s = 0.0;
  // the covariance of (slow, fast, drift), row by row, upper triangle: ss, sf, sd, ff, fd, dd
  std::array<double, 6> covariance{};
  double last_predicted_nm = 0.0;
  double rate_scale = 1.0;  // the factor on the variance rates the innovations asked for (ErrorFilter::rate_scale)
  bool started = false;
};

class ErrorFilter {
 public:
  ErrorFilter(const NoiseModel& model, double dt_s);  // throws std::invalid_argument for dt_s ≤ 0
  void reset();  // e = 0 with the cold-start covariance (a start, or a model restarted at the measurement)
  // A start whose slow error is already known: the start-up state estimate's offset and its 1σ (models/
  // start_state.h: measured − predicted over the start window). reset() is reset(0, initial_sigma_nm); a
  // non-finite σ falls back to initial_sigma_nm. Throws std::invalid_argument for a non-finite offset or σ < 0.
  void reset(double slow_error_nm, double slow_sigma_nm);
  // One sample: the model's prediction (its change from the last sample drives the process noise), then the
  // reading when `valid` (a lost or stale reading: predict only, the covariance grows). `reading_offset_nm`: what the
  // sensor adds to this reading besides the position (a sensor effect the caller's model knows, e.g. the encoder's
  // interpolation error): the expected reading is the position plus it, before the noise and the quantiser.
  void step(double predicted_nm, double measured_nm, bool valid, double reading_offset_nm = 0.0);

  // n samples at rest without readings, in closed form (a node that was down while the stage held).
  void hold(std::size_t samples);
  FilterState state() const;
  void set_state(const FilterState& s);  // throws std::invalid_argument for a non-finite or non-PSD state

  double error_nm() const { return x_(0) + x_(1); }
  double fused_nm() const { return last_p_ + (model_.fuse ? error_nm() : 0.0); }
  double sigma_nm() const;
  double slow_error_nm() const { return x_(0); }
  bool fusing() const { return model_.fuse; }
  // The model's error is known better than one reading tells: 1σ ≤ max(q/8, σ/2) (σ before the quantiser; one
  // reading alone gives about q/√12 on a/b, σ on c). False from a cold start until the readings have pinned it (on
  // a/b: the crossings of the first moves).
  bool zero_known() const;
  const NoiseModel& noise_model() const { return model_; }
  // Sum over readings of the Gaussian log-likelihood of the innovations (the prediction-error decomposition).
  double log_likelihood() const { return loglik_; }
  std::size_t updates() const { return updates_; }
  std::size_t samples_since_reading() const { return since_reading_; }
  double last_innovation_nm() const { return innovation_; }
  std::size_t adaptations() const { return adaptations_; }  // times the consistency test raised the variance
  std::size_t rejected_readings() const { return rejections_; }  // readings outside the gate, not taken
  std::size_t widenings() const { return widenings_; }  // times the gate's alive test widened the slow error
  std::size_t stale_readings() const { return stale_; }  // readings of a level the model moved two steps away from
  // The factor on the noise model's four variance rates the innovations' spread asks for (1: as identified; raised
  // when the readings scatter more than the rates predict, as on physics the identification did not see; at most
  // kMaxRateScale), and the times it was raised.
  double rate_scale() const { return rate_scale_; }
  std::size_t rate_scalings() const { return rate_scalings_; }
  static constexpr double kMaxRateScale = 16.0;

 private:
  void check_consistency(double s);
  void check_spread(double nu, double explained);
  void predict(double dp, Eigen::Vector3d& x, Eigen::Matrix3d& P) const;
  double var_error(const Eigen::Matrix3d& P) const { return P(0, 0) + 2.0 * P(0, 1) + P(1, 1); }
  // false: the reading was outside the gate and not taken (level_nm: the reading itself, whose changes say the
  // encoder is alive)
  bool take_reading(double y_minus_p_nm, double level_nm);
  bool track_level(double measured_nm, double predicted_nm);  // false: a stale level
  void floor_unchanged_level();
  NoiseModel model_;
  double dt_s_, phi_, sigma_;
  bool started_ = false;
  double last_p_ = 0.0;
  Eigen::Vector3d x_ = Eigen::Vector3d::Zero();  // slow, fast, slow's rate [nm/s]
  Eigen::Matrix3d P_ = Eigen::Matrix3d::Zero();
  double loglik_ = 0.0, innovation_ = 0.0;
  std::size_t updates_ = 0, since_reading_ = 0;
  struct Window {  // exponential means of the innovations and of their variance over one time scale
    std::size_t n = 0, count = 0;
    double alpha = 0.0, nu_bar = 0.0, s_bar = 0.0;
  };
  std::array<Window, 3> windows_;
  std::size_t adaptations_ = 0;
  struct SpreadBlock {  // Σν², Σ explained, Σ explained² over the readings of one block (windows_[1]'s length)
    double nu2 = 0.0, e = 0.0, e2 = 0.0;
    std::size_t count = 0;
  };
  SpreadBlock spread_;
  double rate_scale_ = 1.0;
  std::size_t rate_scalings_ = 0;
  std::size_t rejected_run_ = 0, rejections_ = 0, widenings_ = 0;
  std::size_t taken_ = 0;        // readings taken since the last reset
  double taken_level_nm_ = 0.0;  // the level of the last reading taken
  double rejected_level_nm_ = 0.0;
  bool rejected_level_changed_ = false;
  // the level last taken: since it was first read, the model's range, the readings, the variance without them
  bool have_level_ = false;
  double level_nm_ = 0.0, level_p_min_ = 0.0, level_p_max_ = 0.0, level_first_var_ = 0.0;
  std::size_t level_n_ = 0, stale_ = 0;
  bool level_stale_ = false;
  Eigen::Vector3d level_x_ = Eigen::Vector3d::Zero();  // the state after the level's first reading
  Eigen::Matrix3d level_P_ = Eigen::Matrix3d::Zero();
  Eigen::Matrix3d level_free_P_ = Eigen::Matrix3d::Zero();  // … and its covariance since, without readings
};

struct IdentifyOptions {
  double dt_s = 1.0 / 11.0;
  // From the noise floor of the data (analysis/evaluation/noise_floor.h), quantisation included; > 0. The σ before the
  // quantiser starts from √(σ² − q²/12) (a tenth of a step where rounding dominates the floor) and is then
  // identified with the variance rates by the same likelihood.
  double reading_sigma_nm = 0.0;
  double step_nm = 0.0;
  // Fast time constants tried; each gets its own maximum-likelihood fit of the three variance rates.
  std::vector<double> fast_tau_grid_s{5.0, 20.0, 60.0, 200.0};
  std::size_t max_evaluations = 400;   // Nelder–Mead per time constant
};

// Maximum likelihood of the filter's variance rates and the noise σ before the quantiser on one run of the model
// over data (free-run predictions and the readings; NaN readings are lost ones), under the quantised reading model
// (the prediction-error decomposition: the sum of log P(reading | readings before)). The data should be held out from the model's fit (its validation
// part), else the model's error — and so the process noise — is underestimated. Readings with fewer than 10 level
// changes do not identify it (the likelihood is flat in σ and the rates): the result is then model-only
// (`fuse: false`) and its method says so. Throws std::invalid_argument for mismatched lengths, fewer than 200
// readings, or σ ≤ 0 on readings that change level.
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
