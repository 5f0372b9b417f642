// Building blocks the residual loop's parts share (analysis/residual*.cpp): what the loop knows about TRAIN,
// the fitted level of the residual, the streamed regressors of effect terms and their joint fit. Not a tool
// interface: use trace_residual (analysis/residual/residual.h).
#pragma once

#include <cstddef>
#include <random>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/analysis/residual/residual_families.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/augmented_model.h"

namespace piezo::analysis::detail {

// Everything the loop needs about TRAIN, computed once.
struct Context {
  const io::Dataset* data = nullptr;
  std::string axis;
  double fs = 11.0;
  std::vector<double> voltage, measured, x_base;  // x_base: base model prediction per row
  std::vector<std::string> other_axes;            // other axes' voltage and position column names
  std::vector<std::string> aux_names;             // auxiliary columns
  double x_at_zero_v = 0.0;                       // the stage's position at 0 V: where a stroke gain acts about
  // Start-state transients (ResidualOptions::start_transients): exp(−(t − t₀)/τ_j) per row, one column per τ_j.
  // A base started "at rest at the first voltage" on data that begins mid-history is wrong by the unknown initial
  // state of each of its creep modes, which decays with that mode's τ: fitted as nuisance terms, never put in the
  // model (the live model has the true history).
  std::vector<double> transient_taus_s;
  std::vector<std::vector<double>> transient;
  double noise_sigma_nm = 0.0;  // reading noise σ estimated from TRAIN (analysis/evaluation/noise_floor.h)
  // Longest low-pass time constant a variant may have (0 = no limit): the loop sets Validator::max_time_constant_s,
  // half the validation part; a longer one is a time constant the validation rows cannot judge.
  double max_time_constant_s = 0.0;
};

// The fitted level of the base residual besides the effect terms: a constant and the start-state transients.
struct Level {
  double offset_nm = 0.0;
  std::vector<double> transient_nm;  // weight per Context::transient column [nm at t₀]
};

double mean_of(const std::vector<double>& v, std::size_t a, std::size_t b);
double mae_of(const std::vector<double>& r, std::size_t a, std::size_t b);
double span_of(const std::vector<double>& v);
// A signal over TRAIN as the terms read it (models::InputResolver): its mean and (population) SD, the centre and
// scale a gain term standardises it by.
struct SignalStats {
  double mean = 0.0, sd = 0.0;
};
SignalStats signal_stats(const Context& c, const std::string& signal);
bool reads_position(const std::vector<models::EffectTerm>& terms);
models::EffectTerm make_term(const std::string& family, const std::string& type, const std::string& signal,
                             double lag_s = 0.0, double tau_s = 0.0);

// Raw regressors of `terms` over all rows (streamed from row 0). `fixed` terms (already weighted) run in the
// same stream so that position terms see the corrected position; only `terms`' columns are returned.
std::vector<double> regressors(const Context& c, const std::vector<models::EffectTerm>& fixed, double offset,
                               const std::vector<models::EffectTerm>& terms, std::size_t& k_out);
// Fits centre/scale and weights of `terms` (jointly, with an offset) to the base residual on rows [a, b).
void fit_terms(const Context& c, std::vector<models::EffectTerm>& terms, Level& level, std::size_t a, std::size_t b);
// Model prediction on TRAIN rows from x_base plus the terms.
std::vector<double> corrected(const Context& c, const std::vector<models::EffectTerm>& terms, const Level& level);
// measured − corrected(…) on every TRAIN row.
std::vector<double> residual_of(const Context& c, const std::vector<models::EffectTerm>& terms, const Level& level);

// A family's variants on the current residual (parameters chosen later, on training data).
struct FamilyCandidates {
  std::vector<Candidate> variants;
  bool spectral = false;  // p-value from the periodogram test, not from shifts
  PeriodicPeak peak;
  std::string note;
};
FamilyCandidates candidates(Family family, const Context& c, const std::vector<double>& residual,
                            const std::vector<double>& position, std::size_t stride);

}  // namespace piezo::analysis::detail

namespace piezo::analysis::detail {

// A family's cross-validated fit on the current residual: its best variant and its significance.
FamilyScore score_family(Family family, const Context& c, const std::vector<models::EffectTerm>& fixed,
                         const Level& level, const std::vector<double>& residual, const std::vector<double>& position,
                         const ResidualOptions& o, std::mt19937_64& rng);
// Fitted parameters of one effect from the weights of its terms [first, first + count).
void describe(const std::vector<models::EffectTerm>& terms, std::size_t first, std::size_t count, FoundEffect& e);

}  // namespace piezo::analysis::detail
