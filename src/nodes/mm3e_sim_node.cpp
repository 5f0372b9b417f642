// mm3e_sim: simulated MM3E controller on the CAN protocol, backed by the simulator (docs/driver.md).
#include <ros/ros.h>

#include "piezo_compensation/ros/mm3e_sim.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "mm3e_sim");
  ros::NodeHandle nh, pnh("~");
  try {
    piezo::mm3e::SimNode node(nh, pnh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL("mm3e_sim: %s", e.what());
    return 1;
  }
  return 0;
}
