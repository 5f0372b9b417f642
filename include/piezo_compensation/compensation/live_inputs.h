// Live values of a model's inputs (Model::aux_inputs()), ROS-free: the predictor node fills a LiveInputs from its
// topics and each axis' InputFeeder resolves its model's inputs for one paired sample by the same classification
// the offline resolver uses (models::classify_input):
//  - time_s: the sample's stamp. The model file must say its time_s was ROS time (meta.time_clock == "ros",
//    data read from a bag the nodes wrote); any other clock is refused, since the values would not match.
//  - <axis>_voltage_v: that axis' voltage report with this sample's sequence number (the controller numbers all
//    axes alike), waited for and declared lost by the one pairing rule (io/sequence_pairer.h).
//  - <axis>_position_nm of another axis: its reading at the previous sample, by the same rule.
//  - <axis>_fused_position_nm of another axis: its fused estimate at the previous sample (add_fused: the predictor
//    gives each axis' estimate after its update; a model-only axis gives its model's prediction), by the same rule.
//  - any other name: an auxiliary signal from a topic: the newest value stamped at or before the sample's stamp
//    (the rule the bag snapshot and the offline resolver use), so which topic's message arrives first does not
//    change the prediction. It has a staleness limit. A stale or missing signal feeds
//    its fallback: the last fresh value fed (before any, the model's neutral value for it); when it comes back
//    the fed value moves to the fresh one over `recovery_s`, so the corrected voltage never jumps because of it.
#pragma once

#include <cstdint>
#include <deque>
#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/io/sequence_pairer.h"
#include "piezo_compensation/models/model.h"
#include "piezo_compensation/models/model_stream.h"

namespace piezo::compensation {

inline constexpr const char* kRosTimeClock = "ros";

struct AuxFeedOptions {
  double stale_after_s = 5.0;  // a signal older than this (receipt time) is stale
  double recovery_s = 10.0;    // ramp from the fallback back to the fresh value
};

// One manipulator's latest reports, readings and aux signals.
class LiveInputs {
 public:
  struct Report {
    std::uint32_t seq;
    double value;
  };
  struct Aux {
    double value = 0.0;
    double stamp_s = 0.0;  // the sensor's stamp (receipt time when it has none): orders the values
    double time_s = 0.0;   // min(stamp, receipt): staleness counts from here, never from the future
  };
  void add_voltage(const std::string& axis, std::uint32_t seq, double voltage_v);
  void add_reading(const std::string& axis, std::uint32_t seq, double position_nm);  // valid readings only
  void add_fused(const std::string& axis, std::uint32_t seq, double fused_nm);  // an axis' estimate after its update
  // Keeps the last kAuxKept values of each signal, ordered by stamp.
  void add_aux(const std::string& name, double value, double stamp_s, double time_s);
  const std::deque<Report>* voltages(const std::string& axis) const;
  const std::deque<Report>* readings(const std::string& axis) const;
  const std::deque<Report>* fused(const std::string& axis) const;
  // The newest value stamped at or before `stamp_s`; the oldest kept when all are newer; nullptr before any.
  const Aux* aux(const std::string& name, double stamp_s) const;
  static constexpr std::size_t kAuxKept = 256;

 private:
  std::map<std::string, std::deque<Report>> voltages_, readings_, fused_;
  std::map<std::string, std::deque<Aux>> aux_;
};

// Feeds one axis' model. Throws std::runtime_error for a model it cannot feed (time_s on another clock, ground
// truth or the own position as an input).
class InputFeeder {
 public:
  InputFeeder(const models::Model& model, const std::string& own_axis, const AuxFeedOptions& options);

  std::size_t size() const { return sources_.size(); }
  const std::vector<models::InputSource>& sources() const { return sources_; }
  // Fills `out` (size()) for `sample` at time `now_s`. false: a cross-axis value may still come (call again when
  // one arrives); `give_up` declares it lost instead.
  bool fill(const LiveInputs& live, const io::PairedSample& sample, double now_s, bool give_up, double* out);

  // Per input: in fallback now, and why (for diagnostics).
  struct State {
    bool fallback = false;
    std::string status;
    double fed = 0.0;
    std::uint64_t fallback_samples = 0;
  };
  const std::vector<State>& states() const { return states_; }
  bool any_fallback() const;

 private:
  std::vector<models::InputSource> sources_;
  std::vector<State> states_;
  std::vector<double> neutral_, ramp_from_, ramp_start_;
  std::vector<char> ever_fed_, ramping_;
  AuxFeedOptions o_;
  std::string own_axis_;
};

// The value an input is fed before any fresh one, and while the ideal line is computed: for an augmented model, the
// training value of the first term on that signal (a linear or play term's regressor is then 0, a gain's factor 1);
// otherwise 0.
double neutral_input(const models::Model& model, const std::string& name);

}  // namespace piezo::compensation
