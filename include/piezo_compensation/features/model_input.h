// What is known at one sample when a position is predicted: the input of FeatureStream and of models::Model.
#pragma once

namespace piezo::features {

// Causal by construction: the position of the sample being predicted is never an input; positions enter only
// through commit() of earlier samples.
struct ModelInput {
  double voltage_v = 0.0;        // voltage applied at this sample [V]
  const double* aux = nullptr;   // values of Model::aux_inputs() at this sample, in that order (null if none)
};

}  // namespace piezo::features
