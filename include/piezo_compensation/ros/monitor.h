// piezo_monitor: the operator's strip chart in rviz (docs/predictor.md, "Monitor"). Subscribes to each axis'
// <axis>/prediction (measured, predicted, intended, drift forecast, compensation state, model) and publishes
// the charts of analysis/evaluation/strip_chart.h as one MarkerArray in a fixed chart frame, so rviz needs no plugin.
#pragma once

#include <ros/ros.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/analysis/evaluation/strip_chart.h"

namespace piezo::monitor {

class MonitorNode {
 public:
  MonitorNode(ros::NodeHandle nh, ros::NodeHandle pnh);

 private:
  void publish(const ros::WallTimerEvent&);

  ros::NodeHandle nh_;
  std::string frame_id_;
  std::vector<std::string> axes_;
  std::vector<std::unique_ptr<analysis::StripChart>> charts_;
  std::vector<ros::Subscriber> subs_;
  ros::Publisher pub_;
  ros::WallTimer timer_;
  tf2_ros::StaticTransformBroadcaster static_tf_;
};

}  // namespace piezo::monitor
