// Writes the evaluation of several models: DIR/report.md (the study's Table 3 and more), DIR/report.json
// (everything, for scripts), and the trace tables the plots are drawn from (DIR/traces_test.csv,
// DIR/traces_creep.csv, DIR/final_positions.csv).
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/analysis/evaluation/evaluation.h"

namespace piezo::analysis {

struct EvalContext {
  std::string test_path, creep_path, axis = "c";
  double noise_sigma_nm = kStudyEncoderNoiseNm;  // used for the floor and the Fig. 14 band
  double measured_sigma_nm = NAN;                // from measured − truth when the data has truth
  double warmup_s = 0;
  double anchor_s = 0;        // > 0: the first anchor_s seconds fixed each model's offset (EvalOptions::anchor_s)
  bool anchor_history = true; // with anchor_s: the start state was estimated too (EvalOptions::anchor_history)
  double final_window_s = 5;  // end-of-hold window
  std::vector<int> test_segments, creep_segments;  // scored segments (empty = all)
  double zero_window_s = 0, walk_end_s = 900;      // EvalOptions' zero before each recording's hold (0 = off)
  std::vector<std::string> lasso_notes;          // extra markdown sections (optional)
};

// Throws std::runtime_error naming the file that could not be written.
void write_eval_report(const std::string& dir, const EvalContext& ctx, const std::vector<ModelEvaluation>& evals,
                       const io::Dataset& test, const io::Dataset* creep);

std::string eval_markdown(const EvalContext& ctx, const std::vector<ModelEvaluation>& evals);

}  // namespace piezo::analysis
