#include "piezo_compensation/sim/stage.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"

namespace piezo::sim {

namespace {
[[noreturn]] void stage_error(const std::string& where, const std::string& what) {
  throw std::invalid_argument(where + ": " + what);
}
double number(const YAML::Node& n, const std::string& where) {
  double v = 0.0;
  try {
    v = n.as<double>();
  } catch (const YAML::Exception&) {
    stage_error(where, "expected a number");
  }
  if (!std::isfinite(v)) stage_error(where, "must be finite");
  return v;
}
}  // namespace

StageConfig load_stage(const std::string& yaml_path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(yaml_path);
  } catch (const YAML::Exception& e) {
    throw std::invalid_argument(yaml_path + ": cannot read stage file: " + e.what());
  }
  if (!root.IsMap()) stage_error(yaml_path, "expected a map (description, simulator, protocol, ...)");
  StageConfig s;
  s.path = yaml_path;
  for (const auto& kv : root) {
    const std::string key = kv.first.as<std::string>();
    const std::string where = yaml_path + ": " + key;
    if (key == "description") {
      s.description = kv.second.as<std::string>();
    } else if (key == "simulator") {
      s.simulator = simulator_config_from_yaml(kv.second, where);
    } else if (key == "protocol") {
      if (!kv.second.IsScalar()) stage_error(where, "expected a protocol name");
      s.protocol = kv.second.as<std::string>();
      const auto names = protocols::protocol_names();
      if (std::find(names.begin(), names.end(), s.protocol) == names.end()) stage_error(where, "unknown protocol");
    } else if (key == "protocol_parameters") {
      if (!kv.second.IsMap()) stage_error(where, "expected a map of protocol overrides");
      s.protocol_parameters = kv.second;
    } else if (key == "voltage_offset_v") {
      s.voltage_offset_v = number(kv.second, where);
    } else if (key == "duration_s") {
      s.duration_s = number(kv.second, where);
      if (s.duration_s <= 0.0) stage_error(where, "must be > 0");
    } else if (key == "axes") {
      if (!kv.second.IsSequence() || kv.second.size() == 0) stage_error(where, "expected a non-empty list of " + io::axis_names_list());
      s.axes.clear();
      for (const auto& a : kv.second) {
        const std::string name = a.as<std::string>();
        if (io::axis_index_or_none(name) < 0) stage_error(where, "axes must be among " + io::axis_names_list() + ", got '" + name + "'");
        if (std::find(s.axes.begin(), s.axes.end(), name) != s.axes.end()) stage_error(where, "axis '" + name + "' twice");
        s.axes.push_back(name);
      }
    } else {
      stage_error(where, "unknown key (valid: description, simulator, protocol, protocol_parameters, voltage_offset_v, "
                 "duration_s, axes)");
    }
  }
  return s;
}

io::Dataset simulate_stage(const StageConfig& stage, std::uint64_t seed, double duration_s) {
  if (duration_s <= 0.0) duration_s = stage.duration_s;
  YAML::Node params = stage.protocol_parameters ? YAML::Clone(stage.protocol_parameters) : YAML::Node();
  if (duration_s > 0.0 && stage.protocol == "random_walk") params["duration_s"] = duration_s;
  const double rate = stage.simulator.sample_rate_hz;
  const auto protocol = protocols::make_protocol(stage.protocol, params, rate, seed);
  std::size_t n = protocol->size();
  if (duration_s > 0.0) n = std::min(n, static_cast<std::size_t>(std::llround(duration_s * rate)));
  if (n < 2) throw std::invalid_argument(stage.path + ": the stage's duration gives fewer than 2 samples");
  io::Dataset program = protocol->program(0, n);
  std::vector<io::AxisSeries> axes;
  for (auto& a : program.axes)
    if (std::find(stage.axes.begin(), stage.axes.end(), a.name) != stage.axes.end()) {
      for (auto& v : a.voltage_v) v += stage.voltage_offset_v;
      axes.push_back(std::move(a));
    }
  program.axes = std::move(axes);
  ManipulatorSimulator simulator(stage.simulator, seed);
  io::Dataset data = simulator.run(program);
  data.source = "stage " + stage.path + " (protocol " + stage.protocol + ")";
  return data;
}

}  // namespace piezo::sim
