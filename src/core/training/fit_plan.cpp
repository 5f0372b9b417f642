#include "piezo_compensation/training/fit_plan.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace piezo::training {

FitRequest FitPlan::request() const {
  FitRequest r;
  r.train = &train;
  r.validation = validation.empty() ? nullptr : &validation;
  r.axis = axis;
  r.options = YAML::Clone(options);  // a request may add to its options; the plan keeps its own
  return r;
}

void split_by_fraction(FitPlan& plan, io::Dataset all, double split) {
  if (!(split > 0 && split <= 1)) throw std::invalid_argument("split must be in (0, 1]");
  plan.split_at = 0;
  plan.validation = io::Dataset();
  if (all.recording_count() > 1) {
    const std::size_t r = all.recording_count();
    const std::size_t keep = static_cast<std::size_t>(std::llround(split * static_cast<double>(r)));
    if (keep < 1) throw std::invalid_argument("split must leave at least one training recording");
    plan.train = all.slice(0, all.recording_rows(std::min(keep, r) - 1).second);
    if (keep < r) plan.validation = all.slice(all.recording_rows(keep).first, all.size());
  } else {
    const std::size_t n = static_cast<std::size_t>(split * static_cast<double>(all.size()));
    if (n < 20) throw std::invalid_argument("split leaves too few training samples");
    plan.train = all.slice(0, n);
    if (n < all.size()) plan.validation = all.slice(n, all.size()), plan.split_at = n;
  }
  plan.train.source = plan.validation.source = all.source;
  plan.all = std::move(all);
}

void split_at_row(FitPlan& plan, io::Dataset all, std::size_t rows) {
  rows = std::min(rows, all.size());
  plan.train = all.slice(0, rows);
  plan.validation = all.slice(rows, all.size());
  plan.split_at = rows;
  plan.all = std::move(all);
}

YAML::Node plan_options(const std::string& file, const std::vector<std::string>& sets) {
  YAML::Node options(YAML::NodeType::Map);
  if (!file.empty()) {
    try {
      options = YAML::LoadFile(file);
    } catch (const YAML::Exception& e) {
      throw std::invalid_argument("options " + file + ": " + e.what());
    }
    if (!options.IsMap()) throw std::invalid_argument("options " + file + ": expected a mapping");
  }
  for (const auto& kv : sets) {
    const auto eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) throw std::invalid_argument("set expects KEY=VALUE, got '" + kv + "'");
    try {
      options[kv.substr(0, eq)] = YAML::Load(kv.substr(eq + 1));
    } catch (const YAML::Exception& e) {
      throw std::invalid_argument("set " + kv + ": " + e.what());
    }
  }
  return options;
}

void stamp_origin(models::Model& model, const io::Dataset& train, const std::string& source) {
  model.meta.time_clock = train.time_clock;
  if (model.meta.training_source.empty()) model.meta.training_source = source;
  if (io::is_simulated(train)) model.meta.fitted_on = models::kFittedOnSimulated;
}

}  // namespace piezo::training
