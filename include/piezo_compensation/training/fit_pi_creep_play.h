// The fit of kind "pi_creep_play" (models/pi_creep_play_model.h): non-negative least squares on the play and
// low-pass basis, by the Gram sums of one streaming pass per recording.
#pragma once

#include <vector>

#include "piezo_compensation/models/model.h"
#include "piezo_compensation/training/fit_request.h"

namespace piezo::training {

// Options:
//   n_play       play operators, thresholds evenly over half the training voltage span (default 10)
//   thresholds_v the thresholds [V] instead (first 0, increasing; overrides n_play)
//   taus_s       the low-passes' time constants [s], each in [1 sample, 10⁵ s] (default 1, 5, 20, 60, 200,
//                600, 2000, those up to the training data's duration)
//   move_weight  weight of the changes over the move horizons beside the levels in the least squares (default
//                4); 0: levels only
//   move_horizons_s  the horizons [s] (default 10, 60)
//   bends        true (default): each play's bend pieces on its training range
//   (models/pi_creep_play_model.h);
//                false: straight plays only
// The fit: Σ (y − ŷ)² + move_weight·Σ_h Σ (Δ_h y − Δ_h ŷ)² over each recording, Δ_h the change over horizon h
// (the moves a feedforward makes, which need no zero); every w_i, g_ij ≥ 0, one intercept per recording (their mean, by rows, is the bias); the
// memory-free play's step slope is kept ≥ 10⁻³ of the total so the model stays strictly increasing in V.
models::ModelPtr fit_pi_creep_play(const FitRequest& req);

// The default time constants [s].
std::vector<double> default_play_creep_taus_s();

}  // namespace piezo::training
