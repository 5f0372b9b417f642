// Dependency-free C99 headers of fitted models for the manipulator's own controller. Every function is
// `static` and prefixed, so several models can live in one translation unit:
//   typedef struct {...} <p>_state;
//   void   <p>_init(<p>_state*, double voltage_v, double position_nm);   // rest at V, D (Model::reset)
//   double <p>_predict(const <p>_state*, double voltage_v);               // Model::predict
//   void   <p>_commit(<p>_state*, double voltage_v, double position_nm);  // Model::commit
//   double <p>_step(<p>_state*, double voltage_v, double measured_nm);    // predict + commit; NAN = free-run
//   double <p>_inverse(const <p>_state*, double target_nm);               // only where closed form (P_HAS_INVERSE)
#pragma once

#include <string>

#include "piezo_compensation/models/model.h"

namespace piezo::models {

std::string export_c99_linear(const Model& model, const std::string& prefix);  // kind "linear" (no aux features)
std::string export_c99_pi(const Model& model, const std::string& prefix);      // kinds "pi", "pi_creep_*", "preisach*"
std::string export_c99_pi_creep_play(const Model& model, const std::string& prefix);  // kind "pi_creep_play"
// Kind "augmented": the base's header (prefix <p>_base) plus the effect terms. Its predict/commit/step take one
// more argument, `const double* aux`: the values of <p>_AUX_NAMES (Model::aux_inputs()) at the sample.
std::string export_c99_augmented(const Model& model, const std::string& prefix);
// Through the registry; throws naming the kind when it has no exporter. prefix must be a C identifier.
std::string export_c99(const Model& model, const std::string& prefix);

}  // namespace piezo::models
