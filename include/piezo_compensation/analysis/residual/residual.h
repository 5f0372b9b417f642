// Residual tracing: find what a fitted model misses, add it as effect terms (models/augmented_model.h), refit,
// repeat until nothing significant is left, and report the error before and after.
// Generic: it knows nothing of the simulator; ground-truth (*_true_position_nm) and measured positions are never
// explanatory signals, segment/phase are metadata. Extra numeric columns are candidate signals.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/analysis/evaluation/metrics.h"
#include "piezo_compensation/analysis/residual/residual_acceptance.h"
#include "piezo_compensation/analysis/residual/residual_families.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::analysis {

// The effect families by name, read from the family table (analysis/residual/residual_families.h), in report order.
const std::vector<std::string>& residual_family_names();
// Gain families scale the base output (or the voltage) by 1 + f(signal): time_gain, cross_axis_gain, aux_gain.
bool is_gain_family(const std::string& family);
// The additive family on the same signal as a gain family ("aux_gain" → "aux_signal"), "" for others.
std::string additive_counterpart(const std::string& gain_family);
// Families whose terms are lines in time (time_drift, time_gain): they extrapolate without bound past TRAIN
// (AcceptanceThresholds::time_trend_min_removed_fraction).
bool extrapolates_in_time(const std::string& family);
// Families whose regressors are functions of the operating point (voltage, position) rather than of a
// physical signal; they must win by a clear margin (AcceptanceThresholds::operating_point_margin).
bool is_operating_point_family(const std::string& family);
// Families of sensor effects (FamilyTraits::in_readings): in the readings, not in the stage's position.
bool is_reading_family(const std::string& family);

// Runs of a model over data go through models::stream_model (models/model_stream.h), inputs through
// models::InputResolver: the one path and the one resolver.
using models::PredictionMode;
using models::parse_prediction_mode;

// True when `next` starts one sample period after `prev` ends (a time split of one recording).
bool continues_in_time(const io::Dataset& prev, const io::Dataset& next);

// One candidate: a family, the terms that express it (unweighted), what the parameters mean.
struct Candidate {
  std::string family;
  std::vector<models::EffectTerm> terms;
  std::map<std::string, double> parameters;          // numeric parameters (lag_s, period_nm, frequency_hz …)
  std::map<std::string, std::string> labels;         // text parameters (signal …)
};

// A family's score against the current residual.
struct FamilyScore {
  std::string family;
  bool available = true;        // false when the data holds nothing for it (e.g. no aux columns)
  std::string note;             // why unavailable, or how it was tested
  Candidate best;               // best variant (parameters chosen on training data)
  double explained_variance = 0.0;  // cross-validated (contiguous time blocks) fraction of residual variance
  double p_value = 1.0;         // against the noise floor (see docs/closing-the-loop.md)
  bool significant = false;
  double validation_gain = 0.0; // relative validation-MAE improvement when added (0 if not tried)
  double hold_validation_gain = 0.0;  // the same inside holds (0 without holds)
  std::pair<double, double> validation_gain_halves{0.0, 0.0};  // the same in the first and second half of validation
  bool half_clearly_worse = false;  // a half where the errors are clearly higher with it (paired 5-min blocks)
  // The noise-aware size (analysis/residual/residual_acceptance.h), on the validation part: the systematic error is the
  // validation MSE less the reading noise's σ² estimated from the data.
  double systematic_nm = 0.0;     // with it, √(MSE − σ²) [nm]
  double removed_fraction = 0.0;  // share of the systematic error (MSE − σ²) without it that it removes
  double removed_nm = 0.0;        // √(ΔMSE) [nm]; negative when it adds error
  bool clearly_better = false;    // validation errors clearly below those without it (paired blocks)
  std::vector<double> block_mae;  // validation |error| per paired block with it (comparisons between families)
  std::size_t parameters = 0;   // fitted weights of the best variant
  std::size_t variants = 0;     // how many parameter variants were searched
  std::string verdict;          // "kept", or why it was not (competing explanation, hold guard, too small)
};

// One accepted effect with its fitted parameters.
// The profile of a first-order lag τ: for each τ tried, the TRAIN RMS with the base refitted for it and every term
// refitted jointly (Backfitter::profile_lag). The chosen τ has the lowest; [lo_s, hi_s] spans the τ whose errors on
// the validation part (terms fitted on the fit part) are not clearly worse than the chosen one's (paired 5-min
// blocks, training::validation_prefers): a lag the data tell apart from the chosen one lies outside it.
struct LagProfile {
  std::vector<std::pair<double, double>> points;  // (τ [s], TRAIN RMS [nm]), τ ascending
  double chosen_s = 0.0, lo_s = 0.0, hi_s = 0.0;
  bool empty() const { return points.empty(); }
};

struct FoundEffect {
  std::string family;
  std::map<std::string, double> parameters;   // incl. fitted amplitudes / gains
  std::map<std::string, std::string> labels;
  double explained_variance = 0.0;
  double p_value = 1.0;
  double validation_gain = 0.0;
  double hold_validation_gain = 0.0;
  std::vector<FamilyScore> competitors;       // other families that also validated, with why they lost
  ErrorStats test_after;                      // TEST error after adding this effect (and the ones before)
  // The stage position (sensor effects left out: is_reading_family) against the true position when the data has
  // it (n = 0 otherwise).
  ErrorStats test_after_truth;
  bool in_readings = false;                   // a sensor effect: in the readings, not in the stage's position
  std::vector<FamilyScore> ranking;           // all families at this step, best first
  std::vector<double> test_prediction;        // TEST prediction after this step
  // For a term on an auxiliary signal: its first-order lag's profile (empty otherwise).
  LagProfile lag_profile;
};

struct ResidualOptions {
  std::string axis = "c";
  PredictionMode mode = PredictionMode::kFreeRun;
  double validation_fraction = 0.25;   // last part of TRAIN used to check that an effect generalises in time
  int cv_folds = 5;
  int permutations = 40;               // circular-shift null draws per family
  AcceptanceThresholds acceptance;     // every threshold of the acceptance policy, each with its why
  int max_effects = 5;
  std::size_t max_score_samples = 24000;  // statistics on a decimated grid (the residual is strongly autocorrelated)
  std::vector<std::string> families;   // empty = all
  std::uint64_t seed = 1;
  std::function<void(const std::string&)> log;  // progress lines (may be empty)
  // Refits the base model on TRAIN's fit and validation parts (whose positions are then measurement minus the
  // effect terms): after each added effect the base and the terms are refitted alternately (backfitting), so a
  // base that absorbed part of the effect when first fitted gives it back. Empty = the base stays as given.
  // `previous` is the base being replaced: a refit may start from its creep law (training::refit_options); with
  // `same_structure` it keeps previous' structure too (refit_options(previous, options, true)): the refits of a lag
  // profile are compared with each other.
  std::function<models::ModelPtr(const io::Dataset& fit_part, const io::Dataset& validation_part,
                                 const models::Model& previous, bool same_structure)>
      refit_base;
  int backfit_iterations = 2;
  // Refits after a gain family is added (a gain is absorbed by the base more than an additive term; each refit
  // after the first takes out the secant estimate of the joint fit's gain, see trace_residual).
  int gain_backfit_iterations = 4;
  // When TEST continues TRAIN in time, TEST predictions run on from TRAIN instead of restarting from a reset
  // (a reset "rested at the first measured position" is wrong while creep from the past is still going on).
  bool warm_start = true;
  // TRAIN begins mid-history (a ~snapshot, a recording started on a stage already in use): the base started "at
  // rest at the first voltage" is off by the unknown initial state of its creep modes. A decaying exp(−t/τ) per
  // base mode (5 s ≤ τ ≤ twice TRAIN) is fitted alongside the terms as a nuisance and left out of the model.
  bool start_transients = false;
  // > 0: the first anchor_s seconds of TEST's measurement fix the prediction offset (and, from a cold start, the
  // model's start state: models/start_state.h); TEST is scored after them.
  double anchor_s = 0.0;
};

// A step change of the remainder (a mount slip, a knock): where the mean of what is left jumps.
struct StepChange {
  double time_s = 0;   // time of the step (the first sample after it)
  double size_nm = 0;  // mean after − mean before, over the windows either side
  double z = 0;        // size over its standard error (the block means' scatter, slow structure included)
};

// What is left after the last accepted effect, tested against the noise floor estimated from the data.
struct Remainder {
  bool explained = true;       // false: structure above the floor remains ("not explained")
  double noise_sigma_nm = 0;   // reading noise σ estimated from the data (analysis/evaluation/noise_floor.h)
  std::string noise_floor;     // how (NoiseFloor::describe())
  double structure_nm = 0;     // RMS of the slow part above what the noise alone gives [nm]
  double p_value = 1.0;        // block means against white noise of that σ
  double block_s = 0;          // block length of the test
  std::size_t blocks = 0;
  std::vector<std::pair<std::string, double>> correlates;  // signals and products by |correlation|, top first
  // When not explained: the largest step changes of what is left that stand above its scatter, largest first.
  // Reported only; a step is never added as an effect (it does not extrapolate: the next slip is anywhere).
  std::vector<StepChange> steps;
};
// residual = measured − prediction; position = the prediction; rows with mask[i] == 0 are left out (empty =
// all). Block means over block_s seconds against white noise of the σ estimated from the data (χ², p < alpha
// = structure); correlates: every signal the model could read and the products position × each aux signal,
// position × time, position × other axes' signals.
Remainder assess_remainder(const std::vector<double>& residual, const std::vector<double>& position, const io::Dataset& data,
                           const std::string& axis, const std::vector<char>& mask, double alpha, double block_s = 30.0);

// Step changes of a residual (rows with mask 0 left out): block means (block_first: each block's first row, B
// rows a block), the mean over 4 blocks after each boundary against the 4 before, in units of the block means'
// own scatter; local maxima with |z| ≥ z_min, largest first, at most max_steps, each time refined to the row.
std::vector<StepChange> find_steps(const std::vector<double>& residual, const std::vector<char>& mask,
                                   const std::vector<double>& time_s, const std::vector<double>& block_means,
                                   const std::vector<std::size_t>& block_first, std::size_t B, double noise_sigma_nm,
                                   double z_min, std::size_t max_steps);

// One line for logs and reports: at the noise floor, or not explained with its size, top correlate and steps.
std::string describe_remainder(const Remainder& r);

struct ResidualResult {
  ErrorStats before_test, after_test;
  ErrorStats before_test_truth, after_test_truth;  // the stage position against the truth; n = 0 without truth
  ErrorStats before_validation, after_validation;
  bool warm_started = false;  // TEST predictions continued from TRAIN (see ResidualOptions::warm_start)
  double anchor_s = 0.0;              // ResidualOptions::anchor_s as used
  std::size_t test_first_scored = 0;  // first TEST row scored (after the anchor window; 0 without one)
  std::vector<char> test_mask;        // TEST rows scored
  std::vector<FoundEffect> effects;        // in the order added
  std::vector<FamilyScore> final_ranking;  // the last round (nothing significant or limit reached)
  Remainder remainder;                     // TEST residual after all effects
  std::vector<double> test_pred_before, test_pred_after;  // what the encoder reads
  std::vector<double> test_position_after;  // the stage position: test_pred_after without sensor effects
  models::ModelPtr model;                  // the augmented model (base + terms), fitted on TRAIN
};

// Another axis enters the cross-axis families through its best-known position: the column
// io::fused_position_column(axis), when TRAIN and TEST have it, in place of its raw readings (its voltage stays a
// candidate, kept only where it validates better than that position). This adds the column for each axis of
// `models` (axis name → that axis' model, with its estimator block when it has one): analysis::fused_position, its
// model fused with its encoder (its model alone where nothing fuses); TEST's runs on from TRAIN when TEST continues
// TRAIN in time and `warm_start`. Throws io::DataError for an axis TRAIN or TEST lacks, std::invalid_argument for
// a model of `own_axis` or an empty one. `log` (may be empty) gets one line per axis.
void add_fused_positions(io::Dataset& train, io::Dataset& test,
                         const std::map<std::string, std::shared_ptr<const models::Model>>& models,
                         const std::string& own_axis, bool warm_start = true,
                         const std::function<void(const std::string&)>& log = {});

// `base` must already be fitted (on TRAIN's first part); it is cloned, not changed.
ResidualResult trace_residual(const models::Model& base, const io::Dataset& train, const io::Dataset& test,
                              const ResidualOptions& options);

// ---- building blocks (exposed for tests) ----

// Cross-validated explained variance of r by the columns of Z (row-major, n × k) plus an intercept, over
// `folds` contiguous blocks; also with r circularly shifted by each of `shifts` samples (null draws).
struct CvScore {
  double explained_variance = 0.0;
  std::vector<double> null_explained_variance;
};
CvScore cv_explained_variance(const std::vector<double>& r, const std::vector<double>& Z, std::size_t k, int folds,
                              const std::vector<std::size_t>& shifts);

// Strongest periodic component of r against a variable u (time or position): searches frequencies (cycles per
// unit of u) in [f_min, f_max], refines the peak and tests it. On a uniform grid (time) against a red-noise
// background: the periodogram divided by the AR(1) spectrum fitted to r, then the median of that over [f/2, 2f]
// around the peak (periodogram ordinates ≈ exponential; Bonferroni over the frequencies searched). On a
// non-uniform u (position; r in time order): r and each frequency's sinusoid pair prewhitened by r's AR(1)
// filter, the whitened regression's explained sum of squares over twice the whitened variance (power_ratio),
// its maximum over the grid tested against the same scan with r shifted circularly against u (rank, Gumbel
// tail): the residual's slow structure and holds at one position are in the null, not in the peak.
struct PeriodicPeak {
  double frequency = 0.0;   // cycles per unit of u
  double amplitude = 0.0;   // of r's sinusoid at that frequency [unit of r]
  double power_ratio = 0.0; // peak power / red-noise background mean (position: whitened ESS / 2σ²_w)
  double p_value = 1.0;
  std::size_t searched = 0;
  std::string skipped;      // why nothing was searched (e.g. too many frequencies over a non-uniform u), else ""
};
// p-value of a maximum (over variants or frequencies) against the same maximum on null draws: the empirical rank
// ((1 + draws ≥ it)/(1 + draws)), and beyond every draw a Gumbel tail fitted to the draws by moments (the law of
// a maximum; a Gaussian tail is too thin for it).
double null_max_p_value(double observed, const std::vector<double>& null_max);

PeriodicPeak find_periodic_peak(const std::vector<double>& u, const std::vector<double>& r, double f_min, double f_max,
                                double oversample = 4.0);

}  // namespace piezo::analysis
