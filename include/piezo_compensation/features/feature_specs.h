// Named feature sets: the study's selection, the full candidate set for lasso, and the physics-shaped family.
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"

namespace piezo::features {

// The study's lasso selection (§4.2.1) at its 11 Hz: V, ΔV, exponential sums over 60 and 300 steps, D_{t−10}
// and the mean of the past 10 positions. The study's mean ran over D_{t−9}…D_t and so contained the target;
// here it is D_{t−10}…D_{t−1} (causal).
FeatureSpec study_features();

// The §4.2 candidate set (lagged positions, last step, summed past steps, rolling exponential sums over several
// windows and decays) plus the hysteresis-operator family the study did not try: play and stop operators at
// several thresholds and low-passed play outputs with log-spaced time constants up to hours.
FeatureSpec candidate_features();

// Only voltage-history features (no positions): the candidates minus lagged positions. One-step = free-run.
// Includes V² (asymmetry) and low-passed play outputs at 1 s … 8.3 h (creep of the hysteretic displacement).
FeatureSpec physics_features();

// "study", "candidates" or "physics"; throws std::runtime_error listing the names otherwise.
FeatureSpec named_features(const std::string& name);
std::vector<std::string> feature_set_names();

}  // namespace piezo::features
