// Model choice for any stage: validation scores on held-out data, sanity gates that refuse a fit the data cannot
// support, and `--model auto`: fit the candidate kinds, run each free over the held-out recordings, score it on the
// errors the use cares about (moves at 10 s and 60 s, hold creep), and take the fewest parameters within the noise of
// the best.
// Knows nothing of the simulator: every threshold comes from the data the model was fitted and scored on.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/analysis/evaluation/metrics.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fit_request.h"

namespace piezo::analysis {

// Scale of the data a model was fitted on, for the gates.
struct DataScale {
  double position_range_nm = 0.0;    // 0.1 … 99.9 percentile span of the measured positions
  double position_abs_max_nm = 0.0;  // largest |measured position|
  double voltage_span_v = 0.0;       // max − min applied voltage
  double duration_s = 0.0;           // length of the recording
};
DataScale data_scale(const io::Dataset& data, const std::string& axis);

// Held-out validation: the model runs over `data` from rest at its first sample and is scored on samples
// [score_from, end) (score_from > 0: the validation part is the tail of one recording, so the model enters
// it with the real history; 0: a separate file).
struct ValidationScore {
  ErrorStats free_run, one_step;              // vs the measurement
  ErrorStats free_run_truth, one_step_truth;  // vs the true position (simulated data), else invalid
  ErrorStats hold_free_run, hold_free_run_truth;
  std::size_t samples = 0;
  bool finite = true;                         // false: the model predicted NaN/inf (free_run then invalid)
  std::string failure;                        // why the prediction failed, when !finite
};
// `prediction` (optional) receives the predicted series, for the slow scores of the same run.
ValidationScore score_validation(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                                 const std::string& axis, SeriesPrediction* prediction = nullptr);
// Writes the figures into model.meta.validation (free_run_mae_nm, one_step_mae_nm, ..._vs_truth_nm, hold_...).
void store_validation(const ValidationScore& score, models::Model& model);

// A fit the data does not support. what(): one line naming the kind, the figure and the likely cause.
class FitRejected : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};
constexpr double kMaxFreeRunErrorOfRange = 0.25;  // gate: free-run validation MAE / position range
// The gates, in order: non-finite validation error; free-run MAE above 25 % of the position range; a
// parameter far outside what the data supports (an offset or displacement `*_nm` above 10× the data's
// scale, a weight `*_nm_per_v` whose displacement over the voltage span exceeds 10× the range, a time
// constant `tau*_s` above 10× the recording). Returns "" when the fit passes, else the message.
std::string sanity_problem(const models::Model& model, const ValidationScore* score, const DataScale& train_scale);
// Throws FitRejected with sanity_problem()'s message.
void check_fit_sanity(const models::Model& model, const ValidationScore* score, const DataScale& train_scale);

// Options for `linear` on the lasso-selected candidate features (λ_1se survivors), as `piezo fit --features
// lasso` makes them; `report` (optional) receives the lasso report.
YAML::Node lasso_linear_options(const io::Dataset& train, const std::string& axis, const training::ProgressFn& progress,
                                std::string* report = nullptr, std::size_t* kept = nullptr);

// The errors the use cares about, the scores `--model auto` chooses by. Readings and prediction are averaged over
// windows of mean_s (5 s: white reading noise averages away), per recording, from its own first row:
//  - moves at move_short_s and move_long_s (10 s, 60 s): for every pair of windows that far apart, both outside the
//    holds and in one recording, the predicted change minus the measured change. No zero is needed: an offset, a
//    recording's unknown encoder zero, cancels;
//  - hold creep: in each hold (the voltage unchanged, within hold_tolerance_v, for at least hold_min_s; found from
//    the voltage), the predicted change from the hold's first window to each later window minus the measured one:
//    the drift after a tip is parked, wherever the hold's level sits.
// Each column is the mean |error| of its entries; overall is the geometric mean of (column + noise) over the columns
// present, less the noise (a column counts by its ratio between candidates, not by its scale).
struct SlowScoreOptions {
  double mean_s = 5.0;
  double move_short_s = 10.0;
  double move_long_s = 60.0;
  double hold_min_s = 60.0;
  double hold_tolerance_v = 1e-6;
  // The paired test between two candidates runs over blocks of block_s of entries (entries within a minute are
  // correlated: one slow error shows in every pair that spans it).
  double block_s = 60.0;
  double noise_nm = 0.0;  // noise of a difference of two window means [nm]; 0: select_model estimates it
  double time_scale = 1.0;  // < 1: the times above scaled to a short held-out part (fitted_to_part)
};
// A held-out recording shorter than kMovesPerPart long moves: the window, both moves and the block scaled down by
// span / (kMovesPerPart · move_long_s), so that a short recording is scored on the same shape of errors at its own
// time scale rather than not at all (a 5-s tail at 200 Hz: moves of 0.2 s and 1.3 s).
constexpr double kMovesPerPart = 4.0;
SlowScoreOptions fitted_to_part(const SlowScoreOptions& o, const io::Dataset& data, std::size_t from);

// Holds of data[from, end) found from the voltage of `axis` (io::find_holds with the rule of `o`): [begin, end) row
// ranges of at least hold_min_s, none across the start of a recording.
std::vector<io::HoldRun> voltage_holds(const io::Dataset& data, const std::string& axis, std::size_t from,
                                       const SlowScoreOptions& o = {});

// Per column, the |error| of each entry [nm] in time order (the same entries for every candidate scored on the same
// data, so two candidates' vectors pair entry by entry). hold_end_creep: per hold, the signed creep error from its
// first window to its last (predicted − measured), the figure an operator reads per hold.
struct SlowErrors {
  std::vector<double> move_short, move_long, hold_creep;
  std::vector<double> hold_end_creep;
};
// The entries of `prediction` against `reference` on data's rows [from, end) (the windows and pairs above).
SlowErrors use_errors(const std::vector<double>& prediction, const std::vector<double>& reference,
                      const io::Dataset& data, const std::string& axis, std::size_t from,
                      const SlowScoreOptions& o = {});

struct SlowScore {
  SlowErrors blocks;
  double move_short_nm = NAN, move_long_nm = NAN, hold_creep_nm = NAN, worst_hold_creep_nm = NAN, overall_nm = NAN;
  double hold_creep_truth_nm = NAN;  // the hold creep column against the true position (simulated data)
  std::size_t block = 1;             // entries per block of the paired test
  double noise_nm = 0.0;             // noise of one entry (SlowScoreOptions::noise_nm)
  bool valid() const { return std::isfinite(overall_nm); }
};
// Column means and the overall figure of `blocks`.
SlowScore summarise_slow(const SlowErrors& blocks, const SlowScoreOptions& o = {});
// Scores `model` run free from rest over `data` (as `warm_free_run` when given: the free-run prediction of all rows)
// on rows [score_from, end). Runs models only through models::stream_model.
SlowScore slow_score(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                     const std::string& axis, const SlowScoreOptions& o = {},
                     const std::vector<double>* warm_free_run = nullptr);

// Markdown: per model, its use errors run free from rest over every recording of `test` (each from its own first row):
// 10-s and 60-s moves, hold creep (mean), and each hold's creep error from its first window to its last (signed,
// predicted − measured), as `piezo eval` prints them.
std::string use_error_table(const std::vector<std::pair<std::string, const models::Model*>>& models,
                            const io::Dataset& test, const std::string& axis, const SlowScoreOptions& o = {});

// The choice among scored candidates. best_overall: the lowest overall; chosen: of the candidates within the
// noise of it, the one with the fewest parameters (ties: lower overall). reason: one line. Clearly worse on a column:
// the paired test over blocks (training::validation_prefers) prefers the best, and the column's mean is higher by
// more than the noise of one entry: a difference smaller than the noise of one measured move or creep is no
// difference to a user, however consistent.
struct ChoiceEntry {
  std::string label;
  std::size_t parameters = 0;
  const SlowScore* score = nullptr;  // null: refused, not a candidate
};
struct Choice {
  std::size_t chosen = SIZE_MAX, best_overall = SIZE_MAX;
  std::string reason;
};
// Whether `other` is within the noise of `best`: on no column is it clearly worse.
// `worse` (optional) receives the names of the columns where it is clearly worse.
bool within_noise(const SlowScore& best, const SlowScore& other, std::vector<std::string>* worse = nullptr);
Choice choose_candidate(const std::vector<ChoiceEntry>& entries);

struct ModelCandidate {
  std::string label;   // "linear (lasso features)", "pi", ...
  std::string kind;
  YAML::Node options;  // kind options (null = defaults); for the lasso linear filled in during selection
  bool lasso_features = false;
};
// Every registered kind whose auto_candidacy is kDefault (models/registry.h), each as fitted and with the output map;
// `extra_kinds` (kinds marked kExtra or kDefault; `linear` on lasso-selected features, `kan` on a fixed step budget)
// are added. Throws std::invalid_argument for a kind `--model auto` cannot try.
std::vector<ModelCandidate> default_candidates(const std::vector<std::string>& extra_kinds = {});

struct SelectionRequest {
  const io::Dataset* train = nullptr;       // fitting part
  const io::Dataset* validation = nullptr;  // validation part handed to the fits (early stopping); may be null
  const io::Dataset* score_data = nullptr;  // data scored (train + validation, or the validation recordings)
  std::size_t score_from = 0;
  std::string axis = "c";
  std::vector<ModelCandidate> candidates;   // empty = default_candidates()
  double time_budget_s = 0.0;               // per candidate (neural kinds)
  SlowScoreOptions slow;
  std::uint64_t seed = 1;
  int threads = 2;
  bool identify = true;                     // run the identification check on the chosen candidate
  training::ProgressFn progress;
};

// A request for a split by time: fit on `train`, hand `validation` (may be null) to the fits, score `score_data`
// from `score_from`; default candidates.
SelectionRequest selection_request(const io::Dataset& train, const io::Dataset* validation,
                                   const io::Dataset& score_data, std::size_t score_from, const std::string& axis);

struct CandidateResult {
  ModelCandidate candidate;
  ValidationScore score;
  SlowScore slow;
  double fit_s = 0.0;
  std::size_t parameters = 0;
  std::string refused;  // non-empty: the fit threw or failed a gate (the message)
  // The fitted model (null when refused), so a caller can run every candidate on other data (the stage matrix's
  // separate recording); Selection::model is a copy of the chosen one with the figures stored.
  std::shared_ptr<const models::Model> model;
};

// Whether the training recording identifies a kind: the kind fitted again on the training part's first half and run
// free into its second half, its overall use error there (carry-over) against the full fit's on the validation part,
// each with the noise added,
//   ratio = (carry-over + noise) / (validation + noise).
// Over kCarryOverAdvised, half the recording does not predict its other half: the recording is too short or too
// narrow to pin the kind's parameters, and a separate recording is likely to be worse than the validation part says
// (kCarryOverAdvised is in evaluation.h: `piezo eval` reads the stored ratio against it too).
struct Identification {
  double carry_nm = NAN, validation_nm = NAN, noise_nm = 0.0;
  std::string unchecked;  // why there is no ratio (empty when there is one)
  double ratio() const { return (carry_nm + noise_nm) / (validation_nm + noise_nm); }
  bool checked() const { return std::isfinite(ratio()); }
  bool flagged() const { return checked() && ratio() > kCarryOverAdvised; }
  // One line: the two figures, the ratio and, over kCarryOverAdvised, what it means and what to do; or why it was
  // not checked.
  std::string describe(const std::string& label, double train_s) const;
};
// From the two overall figures (not checked when either is missing).
Identification identification(double carry_nm, double validation_nm, double noise_nm);
// The noise of a difference of two window means on the request's validation part (√2 σ of a reading / √rows per
// window); NaN when the part is too short for a noise figure or missing.
double estimate_block_noise(const SelectionRequest& request);
// The carry-over check of `fitted` (its slow score on the validation part: `validation`, or computed when null;
// the request's options fitted_to_part the validation part, as select_model scores):
// one more fit of the candidate's kind, with its options, on the training part's first half (whole recordings when
// there are several). Never throws: a failure is the `unchecked` reason.
Identification check_identification(const SelectionRequest& request, const ModelCandidate& candidate,
                                    const models::Model& fitted, const SlowScore* validation = nullptr);

// The warning a loader gives for a model file whose stored identification check (validation carry_over_ratio) is
// over kCarryOverAdvised, naming the file and the ratio; empty when it has none or it is within (the predictor logs
// it at start-up and at ~reload_model).
std::string unidentified_model_warning(const models::Model& model, const std::string& path);

struct Selection {
  models::ModelPtr model;  // the winner, validation figures stored; null when every candidate was refused
  std::size_t best = 0;    // index into table: the chosen candidate
  std::size_t best_overall = 0;  // index of the lowest overall (== best unless a simpler one was within noise)
  std::vector<CandidateResult> table;
  DataScale scale;         // of the training part
  std::string reason;      // one line: why the chosen candidate
  double block_noise_nm = NAN;  // estimated noise of a difference of two window means
  SlowScoreOptions slow_options;
  Identification identification;  // of the chosen candidate (its ratio stored as validation carry_over_ratio)
};

// Fits every candidate, scores it free-run on the validation part (the gates: score_validation), refuses the ones
// failing a gate, scores the rest on the use errors (slow_score) and chooses by choose_candidate; then checks the
// chosen one's identification. Throws FitRejected (listing each candidate's reason) when none passes.
Selection select_model(const SelectionRequest& request);

// `--model auto` on one training part cut by rows, as `piezo residual` runs it: candidates fitted on rows [0, n_fit),
// the rest their validation and scored after the model has run through the fit part. The chosen model (selection
// stored); *chosen (optional) receives the chosen candidate (kind and options, for refits), *table the table.
models::ModelPtr fit_auto(const io::Dataset& train, std::size_t n_fit, const std::string& axis, std::uint64_t seed,
                          ModelCandidate* chosen = nullptr, std::string* table = nullptr);

// Markdown table: kind, parameters, moves at 10 s and 60 s, hold creep, worst hold creep, overall [nm], status;
// then the rule and the reason line.
std::string selection_table(const Selection& selection);
// {criterion, chosen, chosen_kind, reason, ..., candidates: [...]} for the model file's `selection:`.
YAML::Node selection_yaml(const Selection& selection);

}  // namespace piezo::analysis
