#include "piezo_compensation/ros/interfaces.h"

namespace piezo {

std::vector<const params::NodeInterface*> node_interfaces() {
  return {&mm3e::driver_interface(),        &mm3e::sim_interface(),        &predictor::predictor_interface(),
          &ros_nodes::recorder_interface(), &monitor::monitor_interface(), &predictor::demo_interface()};
}

// What an operator sets for a rig; everything else keeps its default on an MM3E.
const std::vector<StandardParam>& standard_params() {
  static const std::vector<StandardParam> list = {
      {"mm3e_driver", "transport",
       "socketcan for a real controller; udp only for the simulated device on a kernel without CAN"},
      {"mm3e_driver", "interface", "the CAN interface the controller is wired to (ip link shows it)"},
      {"mm3e_driver", "min_voltage_v",
       "must not be below the amplifier's and the piezo's rated minimum: nothing lower is ever sent"},
      {"mm3e_driver", "max_voltage_v",
       "must not exceed the amplifier's and the piezo's rated maximum: nothing higher is ever sent"},
      {"mm3e_driver", "slew_rate_v_per_s", "bounds how fast any commander can move the stage"},
      {"mm3e_driver", "command_timeout_s",
       "how long an axis follows a commander that went silent before it is held"},
      {"mm3e_driver", "protocol/base_node_id",
       "must match the controller's node ID, or the driver hears nothing"},
      {"mm3e_sim", "simulator_config",
       "the physics the rehearsal runs on: the built-in MM3E or a stage file"},
      {"mm3e_sim", "effects",
       "switches on effects the model was not fitted with, to see what the residual loop finds"},
      {"mm3e_sim", "seed", "another seed is another recording of the same device"},
      {"piezo_predictor", "axes", "the axes of this manipulator that have a model and are compensated"},
      {"piezo_predictor", "model_file", "one model per axis, fitted on that axis' recording of this rig"},
      {"piezo_predictor", "compensation",
       "start with the feedforward on, or switch it on later with ~set_compensation"},
      {"piezo_predictor", "voltage_min_v",
       "keep inside the driver's limits, so the inverse never asks for a clamped voltage"},
      {"piezo_predictor", "voltage_max_v",
       "keep inside the driver's limits, so the inverse never asks for a clamped voltage"},
      {"piezo_predictor", "sample_rate_hz",
       "the controller's report rate, when it differs from the model file's"},
      {"piezo_predictor", "hold_trim",
       "holds a parked tip on the fused estimate where the model alone drifts"},
      {"piezo_predictor", "watch_noise_floor_nm",
       "the noise floor piezo eval printed for this axis: switches on the warning that the model no longer "
       "matches"},
      {"piezo_predictor", "aux_topics", "where a model's extra inputs (a temperature) come from"},
      {"piezo_predictor", "resume_from",
       "a restarted node continues the run before instead of starting its models at rest"},
      {"piezo_recorder", "protocol", "which recording: noise, the 41-h plan, a creep evaluation, ..."},
      {"piezo_recorder", "protocol_params",
       "a shorter or different protocol (a one-hour first recording, another scenario count)"},
      {"piezo_recorder", "seed", "another seed gives a recording the model was not fitted on"},
      {"piezo_recorder", "out", "where the bag goes; a disk with room for the whole protocol"},
      {"piezo_recorder", "resume", "continue a recording stopped by Ctrl-C, a crash or a power cut"},
      {"piezo_recorder", "axes", "the axes driven and recorded"},
      {"piezo_monitor", "axes", "the axes charted"},
      {"piezo_monitor", "window_s", "how much history each chart shows"},
      {"piezo_monitor", "encoder_resolution_nm", "the encoder step per axis, for the noise-floor band"},
      {"piezo_demo", "scenario", "which demonstration runs"},
      {"piezo_demo", "model_file", "the model the predictor runs, so both use the same ideal line"},
  };
  return list;
}

}  // namespace piezo
