// Model choice for any stage (issue 11): validation scores held out by time, sanity gates that refuse a fit
// the data cannot support, and `--model auto` (fit the candidate kinds, score each free-run, keep the best).
// Knows nothing of the simulator: every threshold comes from the data the model was fitted and scored on.
#pragma once

#include <yaml-cpp/yaml.h>

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
  double fit_s = 0.0;
  std::size_t parameters = 0;
  std::string refused;  // non-empty: the fit threw or failed a gate (the message)
};

struct Selection {
  models::ModelPtr model;  // the winner, validation figures stored; null when every candidate was refused
  std::size_t best = 0;    // index into table
  std::vector<CandidateResult> table;
  DataScale scale;         // of the training part
};
// Fits every candidate, scores it free-run on the validation part, refuses the ones failing a gate, keeps the
// lowest free-run MAE vs the measurement. Throws FitRejected (listing each candidate's reason) when none passes.
Selection select_model(const SelectionRequest& request);

// Markdown table: candidate, free-run MAE [nm] and [% of range], max [nm], parameters, fit time, status.
std::string selection_table(const Selection& selection);
// {criterion, chosen, chosen_kind, position_range_nm, candidates: [...]} for the model file's `selection:`.
YAML::Node selection_yaml(const Selection& selection);

}  // namespace piezo::analysis
