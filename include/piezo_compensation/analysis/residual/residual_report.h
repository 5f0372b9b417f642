// Writes the result of the residual loop (analysis/residual/residual.h) to a directory: report.md, report.json (via
// util::JsonWriter), predictions.csv, explain.csv (residual per step and each effect's explaining variable, for
// scripts/plotting/residual_plots.py) and model.yaml (the augmented model).
#pragma once

#include <string>

#include "piezo_compensation/analysis/residual/residual.h"

namespace piezo::analysis {

struct ResidualReportContext {
  std::string axis = "c", mode = "free-run", base_kind;
  std::string base_choice;  // how the base was chosen (e.g. "fitted pi_creep_lti", "file m.yaml"); optional
};

// Throws std::runtime_error naming a file that cannot be written.
void write_residual_report(const std::string& dir, const ResidualReportContext& ctx, const ResidualResult& res,
                           const io::Dataset& train, const io::Dataset& test, PredictionMode mode);

// One line for the terminal: TEST MAE before → after, the effects, and whether what is left is explained.
std::string residual_summary(const ResidualResult& res);

}  // namespace piezo::analysis
