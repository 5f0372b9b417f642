#include "piezo_compensation/ros/interfaces.h"

namespace piezo {

std::vector<const params::NodeInterface*> node_interfaces() {
  return {&mm3e::driver_interface(),        &mm3e::sim_interface(),       &predictor::predictor_interface(),
          &ros_nodes::recorder_interface(), &monitor::monitor_interface(), &predictor::demo_interface()};
}

}  // namespace piezo
