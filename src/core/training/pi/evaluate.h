// The PI and Preisach fits' evaluators (private to training/pi): one least-squares fit of the weights for a given
// basis and creep law, with the creep on the voltage, on the hysteresis output (creep gains or play weights fixed)
// or both at once from the previous play weights.
#pragma once

#include <vector>

#include "basis.h"
#include "gram.h"

namespace piezo::training::pi {

// Creep on the voltage: play pieces and creep basis columns, all weights at once (play weights ≥ 0).
// `fixed` (optional): the play pieces' Gram entries, shared by the evaluations of one creep-law search.
// `search` (optional): the rows kept over a search of one LTI time constant or of α (ModeSearchRows).
EvalResult evaluate(const FitData& d, const Basis& hb, const models::CreepParams& cp, double min_w0,
                    StaticGram* fixed = nullptr, ModeSearchRows* search = nullptr);

// The hysteresis output H = Σ_i w_i·F_i of every sample for play weights w (fixed while a creep law is searched on H,
// so it is computed once per search, not once per evaluation).
std::vector<double> hysteresis_series(const FitData& d, const Basis& hb, const std::vector<double>& w);

// Creep on H with the play weights fixed up to a common scale: y = b + s·H + Σ_k θ_k·(basis of LP_j(H)).
// The free scale s lets the alternation move along the valley where a larger H and a smaller fast-creep gain
// explain the data almost equally well. H = hysteresis_series(d, hb, w). Returns w·s and θ/s (gains relative to
// the rescaled H).
EvalResult evaluate_creep_on_h(const FitData& d, const std::vector<double>& H, const std::vector<double>& w,
                               const models::CreepParams& cp, ModeSearchRows* search = nullptr);

// Creep on H, all weights at once given the previous play weights w_prev: y = b + Σ_i w_i·F_i + Σ_k θ_k·(basis of
// LP_j(H_prev) − H_prev), H_prev = Σ_i w_prev,i·F_i. The creep columns are the modes' lags behind H, so a fast mode
// cannot stand in for H itself. Iterated to w ∝ w_prev it is the creep-on-H model (the fit converts the gains);
// each step is one Gram of the voltage-input size (the alternation's w-step needs n_pieces × n_modes filter states
// per sample). θ is per nm of H_prev.
EvalResult evaluate_joint_on_h(const FitData& d, const Basis& hb, const std::vector<double>& w_prev,
                               const models::CreepParams& cp, double min_w0);

// Creep on H with the creep gains fixed: y = b + Σ_i w_i·(F_i + Σ_j g_j·LP_j(F_i)), F_i the play pieces, w_i ≥ 0.
EvalResult evaluate_w_given_creep_on_h(const FitData& d, const Basis& hb, const models::CreepParams& cp,
                                       double min_w0);

}  // namespace piezo::training::pi
