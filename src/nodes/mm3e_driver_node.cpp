// mm3e_driver: the MM3E driver over SocketCAN or UDP (docs/driver.md).
#include <ros/ros.h>

#include "piezo_compensation/ros/mm3e_driver.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "mm3e_driver");
  ros::NodeHandle nh, pnh("~");
  try {
    piezo::mm3e::DriverNode node(nh, pnh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL("mm3e_driver: %s", e.what());
    return 1;
  }
  return 0;
}
