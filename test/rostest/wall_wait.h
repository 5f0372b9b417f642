// Shared waits of the rostest checkers: they return as soon as their condition holds, so a loaded host only makes
// a test slower and only a failing run pays the deadline.
#pragma once

#include <ros/ros.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <initializer_list>
#include <string>
#include <vector>

namespace piezo::test {

// Polls pred() every poll_s of wall time until it holds (true) or timeout_s pass (false; pred() is asked once more
// at the deadline). spin: ros::spinOnce() before each poll, for checkers without a spinner thread of their own.
template <typename Pred>
bool wall_wait(Pred pred, double timeout_s, double poll_s, bool spin = false) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout_s);
  while (ros::ok()) {
    if (spin) ros::spinOnce();
    if (pred()) return true;
    if (ros::WallTime::now() >= end) return false;
    ros::WallDuration(poll_s).sleep();
  }
  return false;
}

// The node is on the master (true too when the master cannot be asked, so a caller waiting for it to leave waits).
inline bool node_registered(const std::string& node) {
  std::vector<std::string> nodes;
  return !ros::master::getNodes(nodes) || std::find(nodes.begin(), nodes.end(), node) != nodes.end();
}

// A YAML/JSON file another process writes, once it is complete: a map with every one of `keys` (false while it is
// missing, half written or without them).
inline bool load_complete_yaml(const std::string& path, std::initializer_list<const char*> keys, YAML::Node& out) {
  try {
    out = YAML::LoadFile(path);
    if (!out.IsMap()) return false;
    for (const char* k : keys)
      if (!out[k]) return false;
    return true;
  } catch (const std::exception&) {
    return false;
  }
}

}  // namespace piezo::test
