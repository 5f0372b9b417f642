#include "piezo_compensation/training/fitters.h"

#include <map>
#include <stdexcept>

#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/util/flush_subnormals.h"

namespace piezo::training {

namespace {

using models::CreepKind;
using models::ModelPtr;

// Every kind that can be fitted on its own; the names are those of models/registry.cpp's list.
const std::map<std::string, FitFn>& fitters() {
  static const std::map<std::string, FitFn> f = {
      {"linear", &fit_linear},
      {"pi", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kNone); }},
      {"pi_creep_log", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kLog); }},
      {"pi_creep_lti", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kLti); }},
      {"pi_creep_fractional", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kFractional); }},
      {"pi_creep_prony", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kProny); }},
      {"preisach", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kNone, true); }},
      {"preisach_creep_prony", [](const FitRequest& r) { return fit_pi_creep(r, CreepKind::kProny, true); }},
      {"dense", [](const FitRequest& r) -> ModelPtr { return fit_dense(r); }},
      {"lstm", [](const FitRequest& r) -> ModelPtr { return fit_lstm(r); }},
      {"kan", [](const FitRequest& r) -> ModelPtr { return fit_kan(r); }},
  };
  return f;
}

}  // namespace

const FitFn& fitter(const std::string& kind) {
  static const FitFn none;
  models::model_kind(kind);  // throws listing the known kinds
  const auto it = fitters().find(kind);
  return it == fitters().end() ? none : it->second;
}

models::ModelPtr fit_model(const std::string& kind, const FitRequest& request) {
  const FitFn& fit = fitter(kind);
  if (!fit) throw std::runtime_error("kind '" + kind + "' cannot be fitted on its own");
  const util::FlushSubnormals flush;  // decaying creep-filter states: see util/flush_subnormals.h
  models::ModelPtr m = fit(request);
  // Where the training keeps the linear states: the start estimate's prior on a recording it has not seen.
  // A failure here leaves the model without a prior (the start estimate then uses the candidates'), not unfitted.
  if (m && m->meta.state_prior.empty()) {
    try {
      m->meta.state_prior = models::learn_state_prior(*m, *request.train, request.axis);
    } catch (const std::exception&) {
      m->meta.state_prior.clear();
    }
  }
  return m;
}

}  // namespace piezo::training
