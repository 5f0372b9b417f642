// piezo_predictor: model-based prediction, drift forecast and feedforward compensation (docs/predictor.md).
#include <ros/ros.h>

#include "piezo_compensation/ros/predictor.h"

int main(int argc, char** argv) {
  ros::init(argc, argv, "piezo_predictor");
  ros::NodeHandle nh, pnh("~");
  try {
    piezo::predictor::PredictorNode node(nh, pnh);
    ros::spin();
  } catch (const std::exception& e) {
    ROS_FATAL("piezo_predictor: %s", e.what());
    return 1;
  }
  return 0;
}
