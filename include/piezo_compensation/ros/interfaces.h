// Every node's interface table (ros/params.h: NodeInterface), each defined beside the node's wrapper and used by it
// to read its parameters and name its topics and services. `piezo ros-interface` writes docs/ros_interface.md from
// them and the launch files.
#pragma once

#include <string>
#include <vector>

#include "piezo_compensation/ros/params.h"

namespace piezo {

namespace mm3e {
const params::NodeInterface& driver_interface();  // src/ros/mm3e_driver.cpp
const params::NodeInterface& sim_interface();     // src/ros/mm3e_sim.cpp
}  // namespace mm3e
namespace predictor {
const params::NodeInterface& predictor_interface();  // src/ros/predictor_params.cpp
const params::NodeInterface& demo_interface();       // src/ros/demo_interface.cpp (the node: src/nodes/piezo_demo_node.cpp)
}  // namespace predictor
namespace ros_nodes {
const params::NodeInterface& recorder_interface();  // src/ros/recorder.cpp
}  // namespace ros_nodes
namespace monitor {
const params::NodeInterface& monitor_interface();  // src/ros/monitor.cpp
}  // namespace monitor

// In the order of the reference: the driver, the simulated device, the predictor, the recorder, the monitor, the demo.
std::vector<const params::NodeInterface*> node_interfaces();

// A parameter the reference lists as standard (every other one is advanced), with one line of why an operator sets
// it. `piezo ros-interface` fails when one names a parameter its node does not declare.
struct StandardParam {
  std::string node, name, why;
};
const std::vector<StandardParam>& standard_params();

}  // namespace piezo
