// Resuming a model on the history it was running on (docs/predictor.md, "Resume"): a node restarted on a stage
// whose voltages it recorded (the ~snapshot bag of the run before) puts the model in the state that history leaves
// it in, then holds it at the last voltage for the time the node was down, instead of starting at rest or
// guessing the history from the first seconds (models/start_state.h). ROS-free; the predictor's ~resume_from.
#pragma once

#include <cstddef>
#include <optional>
#include <string>

#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::compensation {

struct ResumeOptions {
  // A longer time between the history's last row and now: not resumed (what happened in between is not known).
  double max_gap_s = 86400.0;
  // The voltage now must be within this of the history's last voltage (else the stage moved while nothing
  // recorded it, and the recorded history is not its history): not resumed.
  double voltage_tolerance_v = 0.05;
  // How the model runs over the history: as it ran live (the compensator's position_feedback: one-step).
  models::PredictionMode mode = models::PredictionMode::kFreeRun;
};

struct Resume {
  bool resumed = false;
  std::string status;           // one line: what was done, or why not (the model is then left as it was)
  double history_s = 0.0;       // span of the history streamed
  std::size_t history_rows = 0;
  double gap_s = 0.0;           // held at the last voltage for this long (now − the history's last row)
  double last_voltage_v = 0.0;  // the history's last voltage (the hold's)
  double predicted_nm = 0.0;    // the model's position at the end of the hold
  models::ModelPtr model;       // the resumed copy (null when not resumed)
  // The estimator's state (estimation/error_filter.h) when the model file has a fused `estimator:` block: the
  // filter run over the history's readings beside the model (from a cold start at its first row, as the node ran),
  // then held at rest for the gap without readings (its σ grows by the rest rate). Empty otherwise.
  std::optional<estimation::FilterState> filter;
};

// Streams a copy of `model` over `history` (reset at rest at its first row's voltage and measured position, in
// options.mode (free run unless the model ran one-step live), the one streaming path, its inputs from the history's columns), then holds it at the last row's voltage and inputs over
// the samples between the last row and now_s (round((now_s − last time) / period) − 1 of them, time_s advancing at
// the history's median sample period; now's own sample is the caller's next). now_s is on the history's clock
// (the predictor: ROS time, as ~snapshot stamps its rows). Refused, with the reason in
// status (Resume::model null), when: the history is empty or lacks the axis or one of the model's inputs; a voltage is not finite;
// now_s is less than half a sample period after the history's end (that sample may be in it) or further than
// max_gap_s after it; now_v is not within voltage_tolerance_v of
// the last voltage; or the model's run diverges. `model` itself is not changed. Never throws on bad data (a broken
// estimator block: resumed without the filter state, and the status says why).
Resume resume_model(const models::Model& model, const io::Dataset& history, const std::string& axis, double now_s,
                    double now_v, const ResumeOptions& options = {});

}  // namespace piezo::compensation
