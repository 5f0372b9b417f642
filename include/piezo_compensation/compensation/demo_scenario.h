// The compensation demo's scenarios and their bookkeeping (scripts/demo, docs/predictor.md), ROS-free: the
// piezo_demo node only moves messages in and out. One axis is driven through a scenario twice, uncompensated
// then compensated, one intent per encoder sample (paired by io/sequence_pairer.h, the one pairing rule), and the
// true position is scored
//   "sawtooth": triangles of increasing amplitude (study Fig. 11) → deviation from the ideal line,
//   "creep": histories of the package's `creep` protocol, each followed by its hold → drift while holding,
//   "hold_trim": a short history of the `creep` protocol (its random walk, then its approach) and a long hold, run
//   with compensation on both times: the hold trim off (feedforward only), then on (compensation/hold_trim.h) →
//   worst and mean |true − intended| over the hold's last minutes,
//   "tracking_trim": an operator's moves (ramps to random targets, each followed by a hold), once to warm the
//   estimator and then twice with compensation and the hold trim on: the tracking trim off, then on
//   (compensation/tracking_trim.h) → max and mean |true − intended| during the moves and in the holds.
#pragma once

#include <cstdint>
#include <limits>
#include <map>
#include <optional>
#include <ostream>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/io/sequence_pairer.h"

namespace piezo::compensation {

struct DemoStep {
  int mode;           // 0 uncompensated, 1 compensated
  int segment;        // history index (creep) or 0
  std::string phase;  // "rest", "history", "hold", "saw", "warmup", "move" (and "hold_wait" in rows: the hold not yet applied)
  double intent_v;
  double held_s = 0.0;  // tracking_trim: time since the intent last changed (0 while it moves)
};

struct CreepDemoOptions {
  int seed = 3;                     // protocol seed (the demo's training plan uses the creep set of seed + 7)
  std::vector<int> scenarios{11, 8, 13, 6};  // protocol segments (0-based)
  double history_s = 1800.0, hold_s = 1800.0;
  double score_last_s = 1680.0;     // hold_trim: the hold is scored over its last this many seconds (28 min)
};

// The hold_trim scenario's defaults: one short history (120 s: the walk's end, the protocol's pre-approach, dwell
// and approach) before a 30-min hold, scored over its last 28 min.
CreepDemoOptions hold_trim_demo_defaults();

// The tracking_trim scenario: `moves` ramps from 0 V to random targets, each followed by a hold of hold_s, then a
// ramp back to 0 V and a rest; run three times (a warm-up, then the two scored passes), so both passes start from
// the same history.
struct MovesDemoOptions {
  int seed = 7;                     // the targets and rates
  int moves = 5;                    // per pass
  double hold_s = 300.0;            // after each move
  double target_min_v = -60.0, target_max_v = 60.0;
  double rate_min_v_per_s = 0.2, rate_max_v_per_s = 2.0;
  double rest_s = 30.0;             // at 0 V at the end of each pass
  double settle_s = 1.0;            // a hold's first this many seconds count as the move
  double hold_score_from_s = 120.0; // a hold is scored from this far into it
};
std::vector<DemoStep> moves_demo_steps(const MovesDemoOptions& o, double rate_hz);

// Both modes, one step per encoder sample at `rate_hz`.
std::vector<DemoStep> sawtooth_demo_steps(double rate_hz);
// Throws std::invalid_argument naming ~creep_scenarios when a scenario is not in the protocol.
std::vector<DemoStep> creep_demo_steps(const CreepDemoOptions& o, double rate_hz);

class DemoRun {
 public:
  // `scenario` "sawtooth", "creep" or "hold_trim" (else std::invalid_argument; hold_trim uses `creep` for its
  // protocol); `line` scores the intent (the predictor's
  // ideal line of the same model). `lockstep`: the device takes one sample per command (SYNC) and the predictor
  // commands only on an intent, so the demo paces the device: the next intent is given once the predictor has
  // published its prediction of the sample (it has then taken that sample into its model), and each hold starts
  // at its first sample.
  DemoRun(std::string scenario, const CreepDemoOptions& creep, IdealLine line, double rate_hz, bool lockstep = false,
          const MovesDemoOptions& moves = MovesDemoOptions());

  // What to do after a complete sample: switch the mode first when `set_mode` (compensation on/off, or with
  // switches_hold_trim() the hold trim on/off with compensation on), then send `intent_v`.
  struct Next {
    bool set_mode = false;
    bool compensated = false;
    bool hold_trim = false;   // hold_trim scenario: pass 1 (tracking_trim: always)
    bool tracking_trim = false;  // tracking_trim scenario: pass 1
    double intent_v = 0.0;
  };
  // The predictor's fused estimate and hold trim of a sample (Prediction.fused_position …), for the CSV.
  struct Estimate {
    double fused_nm = std::numeric_limits<double>::quiet_NaN();
    double fused_sigma_nm = std::numeric_limits<double>::quiet_NaN();
    double hold_trim_nm = std::numeric_limits<double>::quiet_NaN();
    std::string hold_trim_state;
    double tracking_trim_nm = std::numeric_limits<double>::quiet_NaN();
    std::string tracking_trim_state;
  };

  // Device reports by sample sequence and stamp [s]; the one that completes a sample (truth, encoder, voltage)
  // returns the next intent (lock-step: once the prediction of that sample is in). Several samples completed at
  // once each take a step; the intent returned is the last one, with `set_mode` if any of them switched.
  // Samples arriving after the scenario ended return nothing.
  std::optional<Next> on_truth(std::uint32_t seq, double true_nm, double stamp_s = 0.0);
  std::optional<Next> on_encoder(std::uint32_t seq, double encoder_nm, double stamp_s = 0.0, bool valid = true);
  std::optional<Next> on_voltage(std::uint32_t seq, double applied_v, double stamp_s = 0.0);
  // The predictor's output for the sample stamped `stamp_s`: `commanded_v` the uncorrected command, `sent_v` what
  // went to the driver. Lock-step: returns the intent that waited for it.
  std::optional<Next> on_prediction(double stamp_s, double commanded_v, double sent_v, bool fallback,
                                    const Estimate& estimate);
  std::optional<Next> on_prediction(double stamp_s, double commanded_v, double sent_v, bool fallback) {
    return on_prediction(stamp_s, commanded_v, sent_v, fallback, Estimate());
  }

  bool done() const { return next_ > steps_.size(); }
  bool lockstep() const { return lockstep_; }
  const io::PairerCounters& pairing() const { return pairer_.counters(); }
  std::size_t steps() const { return steps_.size(); }
  std::size_t progress() const { return std::min(next_, steps_.size()); }
  const IdealLine& line() const { return line_; }
  double rate_hz() const { return rate_hz_; }
  const std::string& scenario() const { return scenario_; }
  // hold_trim: the passes differ by ~set_hold_trim, compensation stays on.
  bool switches_hold_trim() const { return scenario_ == "hold_trim"; }
  // tracking_trim: the passes differ by ~set_tracking_trim, compensation and the hold trim stay on.
  bool switches_tracking_trim() const { return scenario_ == "tracking_trim"; }
  bool records_estimates() const { return switches_hold_trim() || switches_tracking_trim(); }

  struct Row {
    DemoStep step;
    double time_s, ideal_nm, true_nm, encoder_nm, applied_v;  // time_s: scenario sample index / rate
    double stamp_s = 0.0;                                     // the device's stamp of the sample
  };
  const std::vector<Row>& rows() const { return rows_; }

  // hold_trim, tracking_trim: the CSV also has the predictor's fused_nm, fused_sigma_nm, hold_trim_nm,
  // hold_trim_state (tracking_trim: and tracking_trim_nm, tracking_trim_state).
  void write_csv(std::ostream& os) const;
  // The metrics: sawtooth deviation from the ideal line in % of the stroke, creep drift per hold, or the hold
  // error per hold (hold_trim).
  void write_json(std::ostream& os) const;

  // hold_trim scoring, per hold in scenario order: worst and mean |true − intended| over the hold's last
  // score_last_s (the whole hold when it is shorter), and the samples scored.
  struct HoldScore {
    int mode = 0, segment = 0;
    double hold_v = 0.0, intended_nm = 0.0, worst_nm = 0.0, mae_nm = 0.0, start_error_nm = 0.0;
    std::size_t samples = 0, active_samples = 0;  // active: the predictor's hold_trim_state was "active"
  };
  std::vector<HoldScore> hold_scores() const;

  // tracking_trim scoring per scored pass (0: the tracking trim off, 1: on): |true − intended| during the moves
  // (ramps and each hold's first settle_s) and in the holds from hold_score_from_s; the applied voltages' range.
  struct MoveScore {
    double move_max_nm = 0.0, move_mean_nm = 0.0, hold_max_nm = 0.0, hold_mean_nm = 0.0;
    std::size_t move_samples = 0, hold_samples = 0, tracking_active_samples = 0;
    double applied_min_v = std::numeric_limits<double>::infinity();
    double applied_max_v = -std::numeric_limits<double>::infinity();
  };
  std::vector<MoveScore> move_scores() const;

 private:
  void write_sawtooth_json(std::ostream& js) const;
  void write_hold_trim_json(std::ostream& js) const;
  void write_creep_json(std::ostream& js) const;
  void write_tracking_trim_json(std::ostream& js) const;
  std::optional<Next> take(const std::vector<io::PairedSample>& samples);
  std::optional<Next> step(const io::PairedSample& sample);
  std::optional<Next> release();

  std::string scenario_;
  CreepDemoOptions creep_;
  MovesDemoOptions moves_;
  IdealLine line_;
  double rate_hz_;
  bool lockstep_;
  std::vector<DemoStep> steps_;
  std::size_t next_ = 0;
  std::vector<Row> rows_;
  io::SequencePairer pairer_;
  std::optional<Next> pending_;        // lock-step: the next intent, waiting for the prediction of its sample
  double pending_stamp_s_ = 0.0, newest_prediction_s_ = -1e300;
  std::map<std::pair<int, int>, bool> hold_started_, forced_;
  std::map<std::pair<int, int>, int> hold_delay_;
  std::vector<double> hold_sent_v_;
  std::vector<std::pair<double, Estimate>> estimates_;  // hold_trim: by prediction stamp, in arrival order
  const Estimate* estimate_at(double stamp_s) const;
};

}  // namespace piezo::compensation
