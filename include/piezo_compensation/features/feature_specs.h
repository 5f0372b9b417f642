// Named feature sets: the study's selection, the full candidate set for lasso, and the physics-shaped family.
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/features/feature_stream.h"
#include "piezo_compensation/io/dataset.h"

namespace piezo::features {

// The study's lasso selection (§4.2.1) at its 11 Hz: V, ΔV, exponential sums over 60 and 300 steps, D_{t−10}
// and the mean of the past 10 positions. The study's mean ran over D_{t−9}…D_t and so contained the target;
// here it is D_{t−10}…D_{t−1} (causal).
FeatureSpec study_features();

// What a data-placed feature set is placed on: the training data's voltage extremes, length and rate.
using DataSpan = io::DataSpan;

// The §4.2 candidate set (lagged positions, last step, summed past steps, rolling exponential sums over several
// windows and decays) plus the hysteresis-operator family the study did not try: play and stop operators at
// several thresholds and low-passed play outputs with log-spaced time constants up to hours. With `span`: only the
// candidates the data can identify (identifiable_on).
FeatureSpec candidate_features(const DataSpan* span = nullptr);

// The features of `spec` whose memory a recording of span.duration_s can show: time constants, windows and lags
// up to a third of it (as the voltage_history set places its slowest low-pass). A slower one is a constant or the
// voltage itself over the recording, and a fit may weight such near-copies hugely against each other: exact on
// that recording, far off from any other start (docs/models.md, "The stage matrix").
FeatureSpec identifiable_on(const FeatureSpec& spec, const DataSpan& span);
// `spec` without the features that read the measured position (FeatureDef::reads_position): what a free run can
// compute from the voltage alone.
FeatureSpec voltage_only(FeatureSpec spec);

// Only voltage-history features (no positions): the candidates minus lagged positions. One-step = free-run.
// Includes V² (asymmetry) and low-passed play outputs at 1 s … 8.3 h (creep of the hysteretic displacement).
FeatureSpec physics_features();

// Only voltage history, placed on the data itself (the neural kinds' default): V, ΔV, play operators at 3, 10,
// 20 and 40 % of the voltage span, and low-passes of the 10 % play output with time constants at 1/3000, 1/300,
// 1/30 and 1/3 of the duration (at least 2 samples). No positions, so one-step = free-run, and 10 columns (the
// 53 of `physics` cost 8–9× the training time).
FeatureSpec voltage_history_features(const DataSpan& span);

// "study", "candidates", "physics" or "voltage_history" (needs `span`: placed on the data); throws
// std::runtime_error listing the names otherwise.
FeatureSpec named_features(const std::string& name, const DataSpan* span = nullptr);
std::vector<std::string> feature_set_names();
// Throws the error of named_features for a name that is no set (the data-placed sets need no data here).
void check_feature_set_name(const std::string& name);

}  // namespace piezo::features
