// The fit of every model kind, keyed by the kind names of models/registry.h (one explicit list in
// fitters.cpp, no static registrars). The fitting code of each kind is in training/fit_<kind>.cpp.
#pragma once

#include <Eigen/Dense>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/models/creep_models.h"
#include "piezo_compensation/models/dense_model.h"
#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/models/lstm_model.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/training/fit_request.h"

namespace piezo::training {

using FitFn = std::function<models::ModelPtr(const FitRequest&)>;

// The fitter of a kind; empty for kinds that cannot be fitted on their own ("augmented": `piezo residual`).
// Throws std::runtime_error listing the known kinds for a name that is no kind.
const FitFn& fitter(const std::string& kind);
// fitter(kind)(request), then the model's ModelMeta::state_prior learned on the training data (the one way to fit
// a kind: every caller goes through it); throws when the kind cannot be fitted on its own.
models::ModelPtr fit_model(const std::string& kind, const FitRequest& request);

// options: method (ols|ridge|lasso), ridge_lambda, lasso_choice (1se|min), folds, features (see fit_common.h).
// A fit whose position features amplify a start error in free run (free_run_gain > kMaxFreeRunGain on the training
// data) is refitted on its voltage features alone.
models::ModelPtr fit_linear(const FitRequest& req);
// The largest gap between two free runs of `model` over `data` started 1 µm apart (reset at the first voltage and
// reading, and 1 µm above it), in µm per µm: 0 for a model that reads no positions, about 1 or less for a free run
// that forgets or keeps its start, more for one that amplifies it (infinite when a run diverges).
double free_run_gain(const models::Model& model, const io::Dataset& data, const std::string& axis);
constexpr double kMaxFreeRunGain = 10.0;

// options: n_play (by validation, else 12), thresholds_v (list, overrides n_play), n_pairs (lti, 2), taus_s (lti
// start values; fix_taus: true keeps them), t1_s / alpha (fix instead of searching), warm_start (taus_s, t1_s or alpha
// a start refined near it), decades, modes_per_decade, tau_min_s, tau_max_s (clamped to [2 samples, training
// duration]), creep_input (auto|voltage|hysteresis), hold_weight (auto|off|factor),
// min_slope_fraction, refit_with_validation (false; pi, pi_creep_prony, preisach kinds), input_map (off|on|auto: the PI
// kinds' memory-free play cut into min(n_play, 12) pieces, a monotone map of V; auto: by validation; default off). Kinds pi, pi_creep_log,
// pi_creep_lti, pi_creep_fractional, pi_creep_prony; with preisach also "preisach" (kNone) and
// "preisach_creep_prony" (kProny), which take knots_per_span (≤ 65, default min(n_play, 12)) and piece_smoothing
// (0.1).
// Option output_map (all PI and Preisach kinds): off (default), on, or auto (with validation data: kept when
// validation clearly prefers it): the output map S of the hysteresis output (models/pi_model.h).
models::ModelPtr fit_pi_creep(const FitRequest& req, models::CreepKind kind, bool preisach = false);

// The option output_map, checked (off when not given).
std::string output_map_option(const YAML::Node& options);

// The model `fit` returns for `req`, then for a PI or Preisach model its output map: fitted on the training residual
// (z², z³ of the hysteresis output, one intercept per recording), the kind refitted with the same structure on the
// positions less the map's bend, the map fitted again. Kept when `always`, else when validation clearly prefers it
// over the first fit: free run from each validation recording's rest, scored on the 5-min blocks that move, each
// block's mean error taken out (the map bends the moves' shape; a hold only sees a constant), paired blocks
// (validation_prefers). The model's validation map records fit_output_map (1 or 0).
models::ModelPtr fit_with_output_map(const FitRequest& req, bool always, const FitFn& fit);

// The options that refit `previous` on new data (a backfitting round of `piezo residual`): its creep law's time
// constants (taus_s, t1_s or alpha) as a start refined near it (warm_start) rather than searched over the whole
// range; the rest is chosen again. With `same_structure`, also its play thresholds, creep input and maps (refits
// that are compared with each other, as in a lag profile). Options the caller gave win. Other kinds: `options`
// unchanged.
YAML::Node refit_options(const models::Model& previous, const YAML::Node& options, bool same_structure = false);

// Non-negative least squares on normal equations: min ½xᵀGx − cᵀx with x_j ≥ 0 where constrained[j]
// (Lawson–Hanson active set). G must be positive definite on the free set.
Eigen::VectorXd nnls_gram(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, const std::vector<bool>& constrained);

// Trains a dense model (with a hyperparameter search when request.tune_trials > 0).
std::unique_ptr<models::DenseModel> fit_dense(const FitRequest& request);
std::unique_ptr<models::LstmModel> fit_lstm(const FitRequest& request);
std::unique_ptr<models::KanModel> fit_kan(const FitRequest& request);

}  // namespace piezo::training
