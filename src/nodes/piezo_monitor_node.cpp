// piezo_monitor: per-axis strip charts of predicted vs measured position as rviz markers (docs/predictor.md).
#include <ros/ros.h>

#include "piezo_compensation/ros/monitor.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "piezo_monitor");
  ros::NodeHandle nh, pnh("~");
  try {
    piezo::monitor::MonitorNode node(nh, pnh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL("piezo_monitor: %s", e.what());
    return 1;
  }
  return 0;
}
