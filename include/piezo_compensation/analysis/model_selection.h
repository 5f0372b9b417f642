// Model choice for any stage (issue 11): validation scores held out by time, sanity gates that refuse a fit
// the data cannot support, and `--model auto` (fit the candidate kinds, score each free-run on the slow part of its
// error, choose for the use with the noise taken out: issue 26).
// Knows nothing of the simulator: every threshold comes from the data the model was fitted and scored on.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/metrics.h"
#include "piezo_compensation/io/dataset.h"
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
ValidationScore score_validation(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                                 const std::string& axis);
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

// The slow part of the error (issue 26): the scores `--model auto` chooses by. The error of 30-s block means
// (predicted − measured), whose white reading noise averages away (σ/√n per block: ≈ 1.2 nm for 21 nm readings at
// 11 Hz), in five columns:
//  - moves: the blocks outside holds; holds: the blocks inside holds (a hold: the voltage unchanged, within
//    hold_tolerance_v, for at least hold_min_s; found from the voltage, no phase markers needed);
//  - hold ends: per hold, the mean error of its last hold_end_s (where the user parks the tip);
//  - cold fold: the held-out part run on its own, as a separate recording would start: the model reset at rest
//    at a start, its blocks after a window of cold_window_s; cold_starts such runs, started over the first half of
//    the part;
//  - carry-over: the kind fitted again on the training part's first half, scored on its second (carry_fold).
// overall: the weighted geometric mean of (column + noise_nm) over the columns present, less noise_nm (hold ends
// count hold_end_weight, the cold fold cold_weight, the carry-over carry_weight, moves and holds 1): a column counts by its ratio between
// candidates, not by its scale (a cold fold of 500 nm from the unknown start state does not drown moves of 0.3 nm), and a difference under the noise
// of a block mean counts little.
// On a short validation part (under min_blocks blocks) the block shrinks to 1/min_blocks of it (at least one
// sample), so a 10-s tail of a 200-Hz recording is scored in 32 blocks of 62 samples: more pairs for the paired
// block test than eighths gave.
struct SlowScoreOptions {
  double block_s = 30.0;
  double hold_min_s = 60.0;
  double hold_tolerance_v = 1e-6;
  double hold_end_s = 30.0;
  // Hold ends weigh as much as the other four columns together (1 + 1 + 0.25 + 1): half of the overall where all
  // five columns are present (more without the carry-over fold), the parked tip the choice is for; the carry-over
  // fold, a fit on half the recording, must not outvote them (docs/models.md, "`--model auto`: the choice rule").
  double hold_end_weight = 3.25;
  // The cold fold: cold_starts runs from rest, started at 0, 1/8, 2/8, … of the held-out part (their blocks
  // pooled), each scored after cold_window_s (at most a fifth of the part), weighted cold_weight in overall.
  // A quarter: a few starts of one part measure the start-state handling less surely than the continuation
  // measures the model (at 1 and 0.5 the 10-s tail's cold fold chose the KAN on 50-µm stages where it is 1.5× the
  // best kind on the continuation and 4× on a separate recording, docs/models.md).
  // cold_start_estimate: the window also fixes the start estimate (models::StreamOptions::anchor_s), as a new
  // recording would be started. Off: the offset it fits today absorbs the start-state error of the window and
  // keeps it after the state has converged (cold fold ×10 on mm3e_preisach, docs/models.md).
  double cold_window_s = 30.0;
  int cold_starts = 4;
  double cold_weight = 0.25;
  bool cold_start_estimate = false;
  // The carry-over fold (select_model; issue 26, a model that holds on the next recording): each candidate fitted
  // again on the first half of the training part alone and run free through that half into the second half, which
  // it has not seen: its block errors there are the column "carry-over", weighted carry_weight in overall. It
  // measures what the continuation's short tail cannot: whether the kind, fitted on this much of this stage, carries
  // over to motion it was not fitted on (a separate recording of the stage: docs/models.md). Costs one more fit on
  // half the data per candidate (neural kinds: another time_budget_s); skipped when the training part has fewer than
  // 4·min_blocks rows, and for every candidate when one candidate's half fit fails (compared on the same columns).
  bool carry_fold = true;
  double carry_weight = 1.0;
  // Several recordings (each zero unknown): a hold's rows are scored from the zero of its own first hold_zero_s,
  // as an operator parks a tip where the encoder says it is: the holds and hold ends columns then score the drift
  // after parking (the creep), not how the hold's level sits against the recording's mean, which the moves column
  // scores (docs/models.md, "`--model auto`: the choice rule").
  double hold_zero_s = 5.0;
  int min_blocks = 32;
  double noise_nm = 0.0;  // noise of a block mean [nm]; 0: select_model estimates it (σ of a reading / √rows)
};

// Holds of data[from, end) found from the voltage of `axis`: [begin, end) row ranges of at least hold_min_s, none
// across the start of a recording.
struct VoltageHold {
  std::size_t begin = 0, end = 0;
};
std::vector<VoltageHold> voltage_holds(const io::Dataset& data, const std::string& axis, std::size_t from,
                                       const SlowScoreOptions& o = {});

// Per column, |mean error| of each block [nm], in time order (same rows for every candidate on the same data,
// so two candidates' vectors pair entry by entry).
struct SlowErrors {
  std::vector<double> moves, holds, hold_ends, cold, carry;
};
// Block errors of `prediction` against `reference` on rows [from, reference.size()) (moves, holds, hold ends;
// `cold` is left empty). block = samples per block; partial blocks of at least half a block count.
SlowErrors slow_errors(const std::vector<double>& prediction, const std::vector<double>& reference,
                       const std::vector<VoltageHold>& holds, std::size_t from, std::size_t block,
                       std::size_t hold_end);
// Block errors of `prediction` on all rows (the cold fold's column).
std::vector<double> block_errors(const std::vector<double>& prediction, const std::vector<double>& reference,
                                 std::size_t block);

struct SlowScore {
  SlowErrors blocks;
  double moves_nm = NAN, holds_nm = NAN, hold_ends_nm = NAN, worst_hold_end_nm = NAN, cold_nm = NAN, carry_nm = NAN,
         overall_nm = NAN;
  double hold_ends_truth_nm = NAN, worst_hold_end_truth_nm = NAN;  // vs the true position (simulated data)
  double block_s = NAN;  // the block used (block_s, or shorter on a short validation part)
  bool valid() const { return std::isfinite(overall_nm); }
};
// Column means and the overall figure of `blocks` (truth figures left as they are).
SlowScore summarise_slow(const SlowErrors& blocks, const SlowScoreOptions& o = {});
// Scores `model` free-run on data[score_from, end): warm (run from rest at row 0 through the history before
// score_from, as `warm_free_run` when given: the free-run prediction of all rows) and cold (see cold_window_s). Runs models only through models::stream_model.
SlowScore slow_score(const models::Model& model, const io::Dataset& data, std::size_t score_from,
                     const std::string& axis, const SlowScoreOptions& o = {},
                     const std::vector<double>* warm_free_run = nullptr);
// The carry-over fold's block errors (SlowScoreOptions::carry_fold): `half_fit`, fitted on train's first `half`
// rows, run free from rest over all of train; |mean error| of blocks over rows [half, end) (a 30-s block, at most
// 1/min_blocks of those rows). Runs the model only through models::stream_model.
std::vector<double> carry_over_errors(const models::Model& half_fit, const io::Dataset& train, std::size_t half,
                                      const std::string& axis, const SlowScoreOptions& o = {});

// The choice among scored candidates. best_overall: the lowest overall; chosen: of the candidates within the
// noise of it (no column on which it is clearly better by training::validation_prefers over the paired block
// errors), the one with the fewest parameters (ties: lower overall). reason: one line.
struct ChoiceEntry {
  std::string label;
  std::size_t parameters = 0;
  const SlowScore* score = nullptr;  // null: refused, not a candidate
};
struct Choice {
  std::size_t chosen = SIZE_MAX, best_overall = SIZE_MAX;
  std::string reason;
};
// Whether `other` is within the noise of `best`: on no column does the paired block test prefer `best`.
// `worse` (optional) receives the names of the columns where it is clearly worse.
bool within_noise(const SlowScore& best, const SlowScore& other, std::vector<std::string>* worse = nullptr);
Choice choose_candidate(const std::vector<ChoiceEntry>& entries);

struct ModelCandidate {
  std::string label;   // "linear (lasso features)", "pi", ...
  std::string kind;
  YAML::Node options;  // kind options (null = defaults); for the lasso linear filled in during selection
  bool lasso_features = false;
};
// linear on lasso-selected features, pi, and every registered pi_creep_* and preisach* kind; `extra_kinds` (e.g. dense,
// lstm, kan) are added with default options.
std::vector<ModelCandidate> default_candidates(const std::vector<std::string>& extra_kinds = {});

struct SelectionRequest {
  const io::Dataset* train = nullptr;       // fitting part
  const io::Dataset* validation = nullptr;  // validation part handed to the fits (early stopping); may be null
  const io::Dataset* score_data = nullptr;  // data scored (train + validation, or the validation file)
  std::size_t score_from = 0;
  std::string axis = "c";
  std::vector<ModelCandidate> candidates;        // empty = default_candidates()
  double time_budget_s = 0.0;               // per candidate (neural kinds)
  SlowScoreOptions slow;
  std::uint64_t seed = 1;
  int threads = 2;
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
  std::string cold_start_off;  // non-empty: not chosen, its cold start is off by too much (cold_start_exclusions)
  // The fitted model (null when refused), so a caller can run every candidate on other data (the stage matrix's
  // separate recording); Selection::model is a copy of the chosen one with the figures stored.
  std::shared_ptr<const models::Model> model;
};

// Whether the training recording identifies a kind (issue 26, a model that holds on the next recording): the
// carry-over fold's slow error (the kind fitted again on the training part's first half, run free into its second
// half) against the full fit's on the validation part's moves, each with the block noise added,
//   ratio = (carry-over + noise) / (moves + noise).
// Over kCarryOverAdvised, half the recording does not predict its other half: the recording is too short or too
// narrow to pin the kind's parameters, and a separate recording is likely to be worse than the validation part
// says (measured on the stage matrix: docs/models.md, "Checking a model").
constexpr double kCarryOverAdvised = 2.0;
struct Identification {
  double carry_nm = NAN, moves_nm = NAN, noise_nm = 0.0;
  std::string unchecked;  // why there is no ratio (empty when there is one)
  double ratio() const { return (carry_nm + noise_nm) / (moves_nm + noise_nm); }
  bool checked() const { return std::isfinite(ratio()); }
  bool flagged() const { return checked() && ratio() > kCarryOverAdvised; }
  // One line: the two figures, the ratio and, over kCarryOverAdvised, what it means and what to do; or why it was
  // not checked.
  std::string describe(const std::string& label, double train_s) const;
};
// From a candidate's slow score (its carry-over column; not checked when the fold did not run or the validation
// part has no moves).
Identification identification(const SlowScore& score, double block_noise_nm);
// The noise of a block mean on the request's validation part (σ of a reading / √rows per block); NaN when the part is
// too short for a noise figure or missing.
double estimate_block_noise(const SelectionRequest& request);
// For one kind fitted outside select_model (`piezo fit --model KIND`): `fitted`'s slow score on the validation part
// and the carry-over fold (one more fit of the kind, with the candidate's options, on the training part's first
// half). Never throws: a failure is the `unchecked` reason.
Identification check_identification(const SelectionRequest& request, const ModelCandidate& candidate,
                                    const models::Model& fitted);

// The warning a loader gives for a model file whose stored identification check (validation carry_over_ratio) is
// over kCarryOverAdvised, naming the file and the ratio; empty when it has none or it is within (the predictor logs
// it at start-up and at ~reload_model).
std::string unidentified_model_warning(const models::Model& model, const std::string& path);

struct Selection {
  models::ModelPtr model;  // the winner, validation figures stored; null when every candidate was refused
  std::size_t best = 0;    // index into table: the chosen candidate
  std::size_t best_overall = 0;  // index of the lowest overall slow error (== best unless a simpler one was within noise)
  std::vector<CandidateResult> table;
  DataScale scale;         // of the training part
  std::string reason;      // one line: why the chosen candidate
  double block_noise_nm = NAN;  // estimated noise of one block mean (σ of a reading / √samples per block)
  SlowScoreOptions slow_options;
  Identification identification;  // of the chosen candidate (its ratio stored as validation carry_over_ratio)
};
// The carry-over column counts only when every scored candidate (not refused, a valid slow score) has it: when one
// lacks it (its half fit failed), it is dropped from every candidate and their scores summarised again, so no
// candidate is compared on fewer columns than another (the carry-over is often the largest; select_model calls it).
void align_carry_over(std::vector<CandidateResult>& table, const SlowScoreOptions& o);
// A model whose cold start is far off is no model to park a tip with, whatever its other columns: a candidate
// whose cold fold is over kMaxColdFoldFraction of the position range is not chosen when another candidate's is
// within it. Per score (null: not scored), "" or the reason it is left out.
constexpr double kMaxColdFoldFraction = 0.10;
std::vector<std::string> cold_start_exclusions(const std::vector<const SlowScore*>& scores, double position_range_nm);

// Fits every candidate, scores it free-run on the validation part (the gates: score_validation), refuses the ones
// failing a gate, scores the rest on the slow part of the error (slow_score) and chooses by choose_candidate.
// Throws FitRejected (listing each candidate's reason) when none passes.
Selection select_model(const SelectionRequest& request);

// Markdown table: kind, parameters, moves, holds, hold ends, cold fold, overall [nm], status; then the reason line.
std::string selection_table(const Selection& selection);
// {criterion, chosen, chosen_kind, reason, block_s, position_range_nm, candidates: [...]} for the model file's
// `selection:`.
YAML::Node selection_yaml(const Selection& selection);

}  // namespace piezo::analysis
