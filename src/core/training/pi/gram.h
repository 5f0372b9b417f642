// The PI and Preisach fits' least squares (private to training/pi): the data a fit streams, the weighted Gram sums
// of rows produced one sample at a time, the caches that let a 1-D creep-law search re-form only the pairs that
// change, and the bounded solve on those sums.
#pragma once

#include <Eigen/Dense>

#include <cmath>
#include <cstddef>
#include <functional>
#include <utility>
#include <vector>

#include "piezo_compensation/models/creep_models.h"
#include "piezo_compensation/training/fit_common.h"

namespace piezo::training::pi {

struct FitData {
  const std::vector<double>* v;
  const std::vector<double>* y;
  double rate;
  bool initial_state_terms = true;
  const std::vector<double>* weight = nullptr;  // per-sample weight (hold weighting); null = all 1
};

struct EvalResult {
  double sse = INFINITY;
  std::vector<double> w, theta;
  double b = 0;
};

// The Gram entries among a row's leading `n` columns, the target and the constant, kept from the first evaluation
// of a search that re-solves with other trailing (creep) columns on the same data, basis and weights: those entries
// do not change, so later evaluations form only the pairs with a trailing column. Semantic order: the n columns, y, 1.
struct StaticGram {
  std::size_t n = 0;
  Eigen::MatrixXd block;  // (n + 2)², lower triangle; empty until the first evaluation filled it
};

// A 1-D search over one LTI mode's time constant (search_lti_taus) changes two columns of the creep fit's rows:
// that mode's filter state and its initial-state column; a search over the fractional law's α (search_alpha), only
// the creep column (the modes' weights, not the modes). Every other column, the target and their Gram pairs are the
// same for all evaluations of the search, so the rows are kept (weighted, the varying columns last) with their Gram;
// later evaluations refill the varying columns and form only their pairs, in the same 32-row chunks (the same sums,
// bit for bit, at a fraction of the cost). One per search: data, basis, creep input and weights fixed.
struct ModeSearchRows {
  std::vector<double> last_taus;   // the previous evaluation's time constants
  std::vector<double> taus;        // those the rows were kept for (mode j's entry varies)
  std::vector<char> slow;          // the modes with an initial-state column then
  std::size_t j = 0;               // the mode searched
  std::size_t ld = 0, skip = 0;    // row stride; physical columns before the varying ones (the others, y, 1)
  std::vector<std::size_t> phys;   // semantic column → physical
  std::vector<double> rows, gram;  // N × ld weighted rows; their ld × ld Gram (physical, lower triangle)
  bool kept = false;
  bool fractional = false;         // kept for an α search: the modes' states of every row are kept too
  std::vector<double> modes;       // fractional: N × (number of modes)
};

// Modes with an initial-state column: slower than 10 s, and faster than a third of the record (slower ones are
// indistinguishable from the bias there).
inline bool slow_mode(double tau, const FitData& d) {
  return d.initial_state_terms && tau >= 10.0 && tau <= d.v->size() / d.rate / 3;
}

// The columns a kept search varies: mode j's state (semantic index mode_col) and, when it has one, its initial-state
// column (init_col, else -1).
struct VaryingColumns {
  std::size_t mode_col = 0;
  long init_col = -1;
};


enum class SearchStep { kFull, kKeep, kReuse };

// How to evaluate the law `cp` (modes `t`, CreepBasis::taus) within a search. LTI: reuse the kept rows when only
// mode j changed since they were kept, keep them when exactly one mode changed since the last evaluation.
// Fractional: reuse them when the modes are those they were kept for, keep them when the last evaluation had the
// same modes. Else a full evaluation. `q`: the Gram's columns (x, y, 1); rows over 256 MB are not stored.
SearchStep search_step(ModeSearchRows* s, const models::CreepParams& cp, const std::vector<double>& t,
                       const FitData& d, std::size_t q);

// The varying columns of a kept search over mode j (search->j): the mode's column (first_mode + j) and its
// initial-state column (after the P0 columns, at its rank among the slow modes) when it has one; of an α search,
// the creep column (first_mode).
VaryingColumns varying_columns(const ModeSearchRows* s, const std::vector<double>& taus, const FitData& d,
                               std::size_t P0, std::size_t first_mode);

// The Gram of the kept rows with the varying columns (`count`) refilled by refill(t, weight_sqrt, out).
GramStats reuse_gram(ModeSearchRows& s, std::size_t N, std::size_t count, const std::vector<double>* weight,
                     std::size_t P, const std::function<void(std::size_t, double, double*)>& refill);

// Weighted Gram sums of rows produced one sample at a time: row(t, x) fills x (P values) and returns the target.
// Extra columns a_j^(t+1) for the poles in `init` absorb the unknown initial state of slow modes: a recording
// never starts from the rest the model's reset assumes, and without them the first hours bias the creep fit.
// `fixed` (optional): its leading columns' entries are taken from it once it holds them (and stored there first).
// `keep` (optional): the rows are kept there in its layout (for the columns `vc`), with their Gram.
GramStats stream_gram(std::size_t N, std::size_t P0, const std::function<double(std::size_t, double*)>& row,
                      const std::vector<double>& init = {}, const std::vector<double>* weight = nullptr,
                      StaticGram* fixed = nullptr, ModeSearchRows* keep = nullptr, const VaryingColumns& vc = {});

// Least squares on the Gram sums; columns flagged constrained stay ≥ their lower bound (`lower`, 0 where it is
// shorter). Solved on unit-diagonal (Jacobi-scaled) normal equations with a small ridge, so volts, nanometres and
// slow near-collinear mode columns do not set the conditioning, and no pair of columns can cancel at huge values.
// `pairs` (optional): column pairs whose weight difference is penalised by `smoothing` × the mean diagonal of those
// columns (the preisach pieces of one play: a smooth map of the play output, PI when the data show nothing else).
EvalResult solve(const GramStats& g, std::vector<bool> constrained, const std::vector<double>& lower = {},
                 const std::vector<std::pair<std::size_t, std::size_t>>& pairs = {}, double smoothing = 0.0);

}  // namespace piezo::training::pi
