// The one parameter layer every node uses (issue 15): each read checks the type and the range and throws
// std::invalid_argument naming the fully resolved parameter, so a bad launch stops with one clear line.
// A ParamReader also remembers which private names the node asked for, so warn_unknown() can point at a
// typo (`~voltge_max_v`) that would otherwise be ignored silently.
#pragma once

#include <ros/ros.h>

#include <set>
#include <string>
#include <vector>

namespace piezo::params {

class ParamReader {
 public:
  explicit ParamReader(const ros::NodeHandle& nh) : nh_(nh) {}

  // A number (int or double on the server) in [min, max].
  double number(const std::string& name, double fallback, double min, double max);
  // An integer in [min, max]; a double is refused (no silent truncation).
  int integer(const std::string& name, int fallback, int min, int max);
  bool flag(const std::string& name, bool fallback);
  // A string; when `allowed` is not empty it must be one of them.
  std::string text(const std::string& name, const std::string& fallback, const std::vector<std::string>& allowed = {});
  // A list of numbers, each in [min, max], with min_count..max_count entries.
  std::vector<double> numbers(const std::string& name, const std::vector<double>& fallback, double min, double max,
                              std::size_t min_count, std::size_t max_count);
  // A list of strings (each one of `allowed` when that is not empty), with min_count..max_count entries and no
  // repeats. A single string where a list is expected is refused, not read as a one-element list.
  std::vector<std::string> texts(const std::string& name, const std::vector<std::string>& fallback,
                                 const std::vector<std::string>& allowed, std::size_t min_count,
                                 std::size_t max_count);

  // Marks a name as known without reading it (read elsewhere, e.g. by a library).
  void known(const std::string& name) { read_.insert(first_component(name)); }

  // Private parameters present on the server under this node's namespace that were never asked for.
  std::vector<std::string> unknown() const;
  // ROS_WARN once per unknown private parameter; returns how many there were.
  std::size_t warn_unknown(const std::string& node_name) const;

  const ros::NodeHandle& handle() const { return nh_; }
  std::string resolved(const std::string& name) const { return nh_.resolveName(name); }

 private:
  static std::string first_component(const std::string& name);
  bool fetch(const std::string& name, XmlRpc::XmlRpcValue& value);

  ros::NodeHandle nh_;
  std::set<std::string> read_;
};

}  // namespace piezo::params
