#include "piezo_compensation/can/protocol.h"

#include <linux/can.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstdio>
#include <stdexcept>

namespace piezo::can {

int axis_index(const std::string& name) { return io::axis_index_or_none(name); }

namespace {

void require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("protocol." + what);
}

}  // namespace

void validate(const ProtocolConfig& c) {
  const std::uint32_t max_id = c.extended_ids ? CAN_EFF_MASK : 0x7FFu;
  require(c.node_id_stride >= 1, "node_id_stride must be >= 1");
  // Coarser than 10 mV and a rounded set point could differ from the slew-limited one by more than the ramp.
  require(std::isfinite(c.voltage_lsb_v) && c.voltage_lsb_v > 0 && c.voltage_lsb_v <= 0.01,
          "voltage_lsb_v must be in (0, 0.01] V");
  require(std::isfinite(c.position_lsb_m) && c.position_lsb_m > 0, "position_lsb_m must be a finite value > 0");
  require(std::isfinite(c.encoder_rate_hz) && c.encoder_rate_hz > 0 && c.encoder_rate_hz <= 10000,
          "encoder_rate_hz must be in (0, 10000]");
  require(std::isfinite(c.heartbeat_period_s) && c.heartbeat_period_s > 0 && c.heartbeat_period_s <= 3600,
          "heartbeat_period_s must be in (0, 3600]");
  // ±80 V must fit the int32 voltage field with room to spare.
  require(1000.0 / c.voltage_lsb_v < 2147483647.0, "voltage_lsb_v is too small: ±1000 V must fit an int32");
  const std::uint32_t last_node = c.base_node_id + (kAxisCount - 1) * c.node_id_stride;
  const std::uint32_t functions[] = {c.command_function_id, c.voltage_function_id, c.encoder_function_id,
                                     c.heartbeat_function_id, c.sync_function_id};
  const char* names[] = {"command_function_id", "voltage_function_id", "encoder_function_id",
                         "heartbeat_function_id", "sync_function_id"};
  for (int f = 0; f < 5; ++f)
    require(functions[f] + last_node <= max_id, std::string(names[f]) + " + node IDs exceed the " +
                                                    (c.extended_ids ? "29" : "11") + "-bit identifier range");
  // Every identifier must be unique, or the codec could not tell frames apart.
  std::uint32_t ids[3 * kAxisCount + 2];
  std::string owners[3 * kAxisCount + 2];
  int n = 0;
  for (int f = 0; f < 3; ++f)
    for (int a = 0; a < kAxisCount; ++a) {
      owners[n] = std::string(names[f]) + " (axis " + kAxisNames[a] + ")";
      ids[n++] = functions[f] + c.base_node_id + a * c.node_id_stride;
    }
  owners[n] = names[3];
  ids[n++] = c.heartbeat_function_id + c.base_node_id;
  owners[n] = names[4];
  ids[n++] = c.sync_function_id + c.base_node_id;
  for (int i = 0; i < n; ++i)
    for (int j = i + 1; j < n; ++j)
      if (ids[i] == ids[j]) {
        char hex[16];
        std::snprintf(hex, sizeof hex, "0x%X", ids[i]);
        throw std::invalid_argument("protocol." + owners[j] + " and " + owners[i] + " give the same identifier " +
                                    hex + " (check the function IDs, base_node_id and node_id_stride)");
      }
}

ProtocolConfig protocol_from_yaml(const YAML::Node& node) {
  ProtocolConfig c;
  if (!node || node.IsNull()) {
    validate(c);
    return c;
  }
  if (!node.IsMap()) throw std::invalid_argument("protocol: expected a map of fields");
  auto get_u32 = [&](const char* key, std::uint32_t& out) {
    if (!node[key]) return;
    try {
      const long long v = node[key].as<long long>();
      if (v < 0 || v > 0x1FFFFFFFLL) throw std::invalid_argument("");
      out = static_cast<std::uint32_t>(v);
    } catch (const std::exception&) {
      throw std::invalid_argument(std::string("protocol.") + key + " must be an integer in [0, 0x1FFFFFFF]");
    }
  };
  auto get_double = [&](const char* key, double& out) {
    if (!node[key]) return;
    try {
      out = node[key].as<double>();
    } catch (const std::exception&) {
      throw std::invalid_argument(std::string("protocol.") + key + " must be a number");
    }
  };
  get_u32("base_node_id", c.base_node_id);
  get_u32("node_id_stride", c.node_id_stride);
  get_u32("command_function_id", c.command_function_id);
  get_u32("voltage_function_id", c.voltage_function_id);
  get_u32("encoder_function_id", c.encoder_function_id);
  get_u32("heartbeat_function_id", c.heartbeat_function_id);
  get_u32("sync_function_id", c.sync_function_id);
  if (node["extended_ids"]) {
    try {
      c.extended_ids = node["extended_ids"].as<bool>();
    } catch (const std::exception&) {
      throw std::invalid_argument("protocol.extended_ids must be true or false");
    }
  }
  if (node["byte_order"]) {
    if (!node["byte_order"].IsScalar()) throw std::invalid_argument("protocol.byte_order must be \"little\" or \"big\"");
    const std::string order = node["byte_order"].Scalar();
    if (order == "little")
      c.byte_order = ByteOrder::kLittle;
    else if (order == "big")
      c.byte_order = ByteOrder::kBig;
    else
      throw std::invalid_argument("protocol.byte_order must be \"little\" or \"big\", got \"" + order + "\"");
  }
  get_double("voltage_lsb_v", c.voltage_lsb_v);
  get_double("position_lsb_m", c.position_lsb_m);
  get_double("encoder_rate_hz", c.encoder_rate_hz);
  get_double("heartbeat_period_s", c.heartbeat_period_s);
  validate(c);
  return c;
}

ProtocolConfig load_protocol_config(const std::string& path) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const std::exception& e) {
    throw std::invalid_argument("cannot read protocol config " + path + ": " + e.what());
  }
  if (!root.IsMap() && !root.IsNull()) throw std::invalid_argument(path + ": expected a map with a protocol: section");
  try {
    return protocol_from_yaml(root["protocol"]);
  } catch (const YAML::Exception& e) {  // anything the field checks did not name
    throw std::invalid_argument(path + ": protocol: " + e.what());
  }
}

}  // namespace piezo::can
