// piezo_recorder: runs a data-collection protocol through the driver and records it into a bag.
// Exit code: 0 protocol complete, 130 interrupted (bag valid, resumable), 1 failure (bag valid, one message).
#include <ros/callback_queue.h>
#include <ros/ros.h>

#include <atomic>
#include <csignal>

#include "piezo_compensation/ros/recorder.h"

namespace {
std::atomic<int> g_signal{0};
extern "C" void on_signal(int sig) { g_signal = sig; }
}  // namespace

int main(int argc, char** argv) {
  // our own handler: Ctrl-C must close and merge the bag before the node goes down
  ros::init(argc, argv, "piezo_recorder", ros::init_options::NoSigintHandler);
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  ros::NodeHandle nh, pnh("~");
  std::unique_ptr<piezo::ros_nodes::Recorder> recorder;
  try {
    recorder = std::make_unique<piezo::ros_nodes::Recorder>(nh, piezo::ros_nodes::RecorderOptions::from_params(pnh));
  } catch (const std::exception& e) {
    ROS_FATAL("piezo_recorder: %s", e.what());
    ros::shutdown();
    return 2;
  }
  while (ros::ok() && !recorder->done()) {
    ros::getGlobalCallbackQueue()->callAvailable(ros::WallDuration(0.05));
    if (const int sig = g_signal.exchange(0))
      recorder->request_stop(sig == SIGINT ? "interrupted (SIGINT)" : "terminated (SIGTERM)");
  }
  if (!recorder->done()) recorder->request_stop("ROS shut down");
  const int code = recorder->exit_code();
  recorder.reset();
  ros::shutdown();
  return code;
}
