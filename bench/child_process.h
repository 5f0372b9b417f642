// Child processes for the benchmarks that run ROS nodes (rosmaster, mm3e_driver, piezo_predictor): started with
// an argument vector in their own process group, output to a log file; stopped with SIGINT, SIGKILL after 5 s.
#pragma once

#include <ros/ros.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

namespace piezo::bench {

inline pid_t spawn(const std::vector<std::string>& args, const std::string& log) {
  const pid_t pid = fork();
  if (pid == 0) {
    setpgid(0, 0);
    if (FILE* f = std::fopen(log.c_str(), "w")) {
      dup2(fileno(f), 1);
      dup2(fileno(f), 2);
    }
    std::vector<char*> argv;
    for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
    argv.push_back(nullptr);
    execvp(argv[0], argv.data());
    _exit(127);
  }
  return pid;
}

inline void stop(pid_t pid) {
  if (pid <= 0) return;
  kill(pid, SIGINT);
  for (int i = 0; i < 50; ++i) {
    if (waitpid(pid, nullptr, WNOHANG) == pid) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  kill(pid, SIGKILL);
  waitpid(pid, nullptr, 0);
}

// A rosmaster of the benchmark's own on 127.0.0.1:port (logs in log_dir), and ros::init of this process as
// `name` against it. Returns the master's pid, or -1 (master stopped again) when it did not come up in 10 s.
inline pid_t start_private_master(const std::string& name, int port, const std::string& log_dir, int& argc,
                                  char** argv) {
  setenv("ROS_MASTER_URI", ("http://127.0.0.1:" + std::to_string(port)).c_str(), 1);
  setenv("ROS_IP", "127.0.0.1", 1);
  unsetenv("ROS_HOSTNAME");
  setenv("ROS_LOG_DIR", log_dir.c_str(), 1);
  const pid_t pid = spawn({"rosmaster", "--core", "-p", std::to_string(port)}, log_dir + "/rosmaster.log");
  ros::init(argc, argv, name, ros::init_options::NoSigintHandler | ros::init_options::AnonymousName);
  for (int i = 0; i < 100 && !ros::master::check(); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  if (ros::master::check()) return pid;
  std::fprintf(stderr, "%s: rosmaster did not start (log in %s)\n", name.c_str(), log_dir.c_str());
  stop(pid);
  return -1;
}

}  // namespace piezo::bench
