// Model inversion: the voltage that, by the model and the committed history, puts the tip at a target position
// at the current sample. Closed form when the model is affine in voltage, bracketed root finding otherwise.
#pragma once

#include <string>

#include "piezo_compensation/models/model.h"

namespace piezo::compensation {

struct InverseOptions {
  double voltage_min_v = -80.0;
  double voltage_max_v = 80.0;
  double tolerance_nm = 0.01;    // stop when |predict(v) - target| is below this
  int max_iterations = 80;       // bracketed search only
};

struct InverseResult {
  bool ok = false;               // false: non-finite prediction, or no voltage inside the limits reaches the target
  double voltage_v = 0.0;        // solution (ok), else the limit closest to the target (or NaN when non-finite)
  double predicted_nm = 0.0;     // model position at voltage_v
  bool closed_form = false;
  int evaluations = 0;           // calls to Model::predict
  std::string error;             // one line when !ok
};

// `aux` is passed to the model unchanged (values of Model::aux_inputs() at this sample, or null).
InverseResult invert(const models::Model& model, double target_nm, const InverseOptions& options,
                     const double* aux = nullptr);

}  // namespace piezo::compensation
