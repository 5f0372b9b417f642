// piezo_demo's interface table (the node's main is src/nodes/piezo_demo_node.cpp; the table lives in the wrapper
// library so `piezo ros-interface` lists it with the others).
#include <sstream>

#include "piezo_compensation/compensation/demo_scenario.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/predictor.h"

namespace piezo::predictor {

const params::NodeInterface& demo_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    const compensation::CreepDemoOptions d, ht = compensation::hold_trim_demo_defaults();
    const compensation::MovesDemoOptions mv;
    const std::vector<std::string> axes(io::kAxisNames.begin(), io::kAxisNames.end());
    const auto ht_default = [&](double v) {
      std::ostringstream os;
      os << "hold_trim: default " << v;
      return os.str();
    };
    std::string ht_scenarios;
    for (int k : ht.scenarios) ht_scenarios += (ht_scenarios.empty() ? "" : ", ") + std::to_string(k);
    NodeInterface n;
    n.node = "piezo_demo";
    n.summary = "the demo's scenario runner (scripts/demo): one axis through a scenario twice, one intent per sample, "
                "scored against the true position";
    n.params = {
        text("scenario", "sawtooth",
             "sawtooth (deviation from the ideal line), creep (drift while holding), hold_trim (the held error "
             "with the hold trim off, then on) or tracking_trim (moves and holds with the tracking trim off, then on)",
             {"sawtooth", "creep", "hold_trim", "tracking_trim"}),
        text("axis", "c", "the axis driven", axes),
        text("model_file", "", "the predictor's model of that axis (the same ideal line)").rule("required"),
        text("out_prefix", "demo", "writes <prefix>.csv (every sample) and <prefix>.json (the metrics)"),
        number("score_last_s", "s", d.score_last_s, 1e-3, 1e6, "hold_trim: each hold scored over its last this many seconds")
            .rule(ht_default(ht.score_last_s)),
        number("hold_s", "s", d.hold_s, 1e-3, 1e6, "length of each hold")
            .rule(ht_default(ht.hold_s) + "; tracking_trim: default " + std::to_string(static_cast<int>(mv.hold_s))),
        integer("moves", "", mv.moves, 1, 1000, "tracking_trim: moves to random targets per pass"),
        integer("moves_seed", "", mv.seed, 0, 1 << 30, "tracking_trim: seed of the targets and rates"),
        number("hold_score_from_s", "s", mv.hold_score_from_s, 0.0, 1e6,
               "tracking_trim: each hold scored from this far into it").rule("< hold_s"),
        number("creep_history_s", "s", d.history_s, 1e-3, 1e6, "the history before each hold (the creep protocol's)")
            .rule(ht_default(ht.history_s)),
        integer("creep_seed", "", d.seed, 0, 1 << 30, "creep protocol seed").rule(ht_default(ht.seed)),
        numbers("creep_scenarios", "", std::vector<double>(d.scenarios.begin(), d.scenarios.end()), 0, 1000, 1, 100,
                "creep protocol segments (0-based, integers) to run")
            .rule("integers; hold_trim: default [" + ht_scenarios + "]"),
        number("ideal_line_hold_s", "s", PredictorSettings().ideal_line_hold_s, 0.0, 1e6,
               "hold at the voltage limits that defines the ideal line (as the predictor's)"),
        number("progress_period_s", "s", 10.0, 0.1, 3600.0, "a progress line with the ETA this often (wall)"),
        flag("lockstep", false,
             "the device samples once per command: the next intent goes out once the predictor's prediction of the "
             "sample is in (sim.launch lockstep:=true command_on_sample:=false)"),
        texts("hold_axes", {}, axes, 0, 2, "other axes given one constant intent each at the start").rule("not axis"),
        numbers("hold_axes_v", "V", {}, -1000.0, 1000.0, 0, 2, "the voltage intent of each hold_axes entry")
            .rule("one per hold_axes entry"),
    };
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/intended", "piezo_compensation/IntendedMotion", D::kPublishes, "the scenario's voltage intent, one per sample"},
        {"<axis>/encoder", "piezo_compensation/EncoderPosition", D::kSubscribes, "measured position"},
        {"<axis>/true_position", "piezo_compensation/EncoderPosition", D::kSubscribes, "the simulated device's true position (scored)"},
        {"<axis>/voltage", "piezo_compensation/AxisVoltage", D::kSubscribes, "applied voltage"},
        {"<axis>/prediction", "piezo_compensation/Prediction", D::kSubscribes, "the predictor's output (fused estimate, hold trim)"},
    };
    n.services = {
        {"predictor/set_compensation", "std_srvs/SetBool", "compensation off for the first pass, on for the second", true},
        {"predictor/set_hold_trim", "std_srvs/SetBool",
         "hold_trim: the hold trim off for the first pass, on for the second (tracking_trim: on in both)", true},
        {"predictor/set_tracking_trim", "std_srvs/SetBool",
         "tracking_trim: the tracking trim off for the warm-up and the first pass, on for the second", true},
    };
    return n;
  }();
  return t;
}

}  // namespace piezo::predictor
