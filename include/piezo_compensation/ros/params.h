// The one parameter layer every node uses: each read checks the type and the range and throws
// std::invalid_argument naming the fully resolved parameter, so a bad launch stops with one clear line.
// A ParamReader also remembers which private names the node asked for, so warn_unknown() can point at a
// typo (`~voltge_max_v`) that would otherwise be ignored silently.
//
// Each node declares its interface once, as a NodeInterface: every private parameter (type, unit, default, range,
// meaning), every topic and every service. The node reads its parameters through that table (ParamReader's
// one-argument reads) and names its topics and services through it (NodeInterface::topic_name / service_name check
// the message type), and `piezo ros-interface` writes docs/ros_interface.md from the same tables.
#pragma once

#include <ros/ros.h>

#include <cstddef>
#include <set>
#include <string>
#include <vector>

namespace piezo::params {

enum class ParamType { kNumber, kInteger, kFlag, kText, kNumbers, kTexts, kMap };

// One private parameter. `unit` is "" for a dimensionless or non-numeric value; `constraint` is a further rule the
// node checks against other parameters ("< voltage_max_v"); `default_text` replaces the printed default where it is
// not a plain value (a required parameter, a map).
struct ParamDef {
  std::string name;
  ParamType type = ParamType::kNumber;
  std::string unit;
  double number = 0.0;
  bool flag = false;
  std::string text;
  std::vector<double> numbers;
  std::vector<std::string> texts;
  double min = 0.0, max = 0.0;             // number, integer, each entry of a list of numbers
  std::size_t min_count = 0, max_count = 0;  // lists
  std::vector<std::string> allowed;          // text, each entry of a list of texts ("" = any)
  std::string constraint, default_text, meaning;

  ParamDef& rule(const std::string& c) { constraint = c; return *this; }
  ParamDef& shown_as(const std::string& d) { default_text = d; return *this; }
  std::string type_name() const;     // "double", "int", "bool", "string", "double[]", "string[]", "map"
  std::string default_string() const;
  std::string range_string() const;  // "[-80, 80]", "one of: a, b", "1..3 entries, each one of: a, b, c"
};

ParamDef number(const std::string& name, const std::string& unit, double fallback, double min, double max,
                const std::string& meaning);
ParamDef integer(const std::string& name, const std::string& unit, int fallback, int min, int max,
                 const std::string& meaning);
ParamDef flag(const std::string& name, bool fallback, const std::string& meaning);
ParamDef text(const std::string& name, const std::string& fallback, const std::string& meaning,
              const std::vector<std::string>& allowed = {});
ParamDef numbers(const std::string& name, const std::string& unit, const std::vector<double>& fallback, double min,
                 double max, std::size_t min_count, std::size_t max_count, const std::string& meaning);
ParamDef texts(const std::string& name, const std::vector<std::string>& fallback, const std::vector<std::string>& allowed,
               std::size_t min_count, std::size_t max_count, const std::string& meaning);
// A value the node reads itself (a map, or one of several shapes); `shape` is printed as its type.
ParamDef structured(const std::string& name, const std::string& unit, const std::string& shape,
                    const std::string& default_text, const std::string& meaning);

struct TopicDef {
  enum class Direction { kPublishes, kSubscribes };
  std::string name;  // relative to the node's namespace; "<axis>/voltage" once per axis
  std::string type;  // "piezo_compensation/AxisVoltage"
  Direction direction = Direction::kPublishes;
  std::string meaning;
  std::string for_axis(const std::string& axis) const;
};

struct ServiceDef {
  std::string name;  // "~name": private (on the node's private handle); else relative to the node's namespace
  std::string type;  // "std_srvs/SetBool"
  std::string meaning;
  bool called = false;  // a service of another node this node calls (not one it provides)
};

struct NodeInterface {
  std::string node;     // the executable
  std::string summary;  // one line
  std::vector<ParamDef> params;
  std::vector<TopicDef> topics;
  std::vector<ServiceDef> services;

  // The entry of that name; std::logic_error when the table has none (a node reading a name it does not declare).
  const ParamDef& param(const std::string& name) const;
  const TopicDef& topic(const std::string& name) const;
  const ServiceDef& service(const std::string& name) const;

  // The topic's name (for `axis` when it is per axis), checked against the message type the caller uses.
  template <typename M>
  std::string topic_name(const std::string& name, const std::string& axis = "") const {
    const TopicDef& t = topic(name);
    check_type(t.name, t.type, ros::message_traits::datatype<M>());
    return t.for_axis(axis);
  }
  // A private service ("~halt") is named without its "~", for the node's private handle.
  template <typename S>
  std::string service_name(const std::string& name) const {
    const ServiceDef& s = service(name);
    check_type(s.name, s.type, ros::service_traits::datatype<S>());
    return s.name.rfind('~', 0) == 0 ? s.name.substr(1) : s.name;
  }

 private:
  void check_type(const std::string& name, const std::string& declared, const std::string& used) const;
};

class ParamReader {
 public:
  explicit ParamReader(const ros::NodeHandle& nh) : nh_(nh) {}
  // Reads through the node's table: the one-argument reads below take the type, default and range from it.
  ParamReader(const ros::NodeHandle& nh, const NodeInterface& table) : nh_(nh), table_(&table) {}

  double number(const std::string& name);
  // `fallback` instead of the table's default: a default that depends on another parameter (the table's
  // constraint says which).
  double number(const std::string& name, double fallback);
  int integer(const std::string& name);
  int integer(const std::string& name, int fallback);
  bool flag(const std::string& name);
  std::string text(const std::string& name);
  std::vector<double> numbers(const std::string& name);
  std::vector<double> numbers(const std::string& name, const std::vector<double>& fallback);
  std::vector<std::string> texts(const std::string& name);
  // A structured entry the caller reads itself: marks it known and returns its definition.
  const ParamDef& structured(const std::string& name);
  const NodeInterface& table() const;

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

  const ParamDef& def(const std::string& name, ParamType type) const;

  ros::NodeHandle nh_;
  const NodeInterface* table_ = nullptr;
  std::set<std::string> read_;
};

}  // namespace piezo::params
