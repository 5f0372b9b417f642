// The MM3E CAN protocol as data: identifiers, payload scaling and byte order (docs/can_protocol.md,
// config/mm3e.yaml). Everything the codec does is driven by this struct, so the team can match the real
// controller by editing YAML, not code.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "piezo_compensation/io/axes.h"

namespace YAML {
class Node;
}

namespace piezo::can {

using io::kAxisCount;   // the axes are named once, in io/axes.h
using io::kAxisNames;

// Returns 0..2 for "a".."c", -1 otherwise.
int axis_index(const std::string& name);

enum class ByteOrder { kLittle, kBig };

struct ProtocolConfig {
  // Node ID of axis a; axis i uses base_node_id + i * node_id_stride. The heartbeat and SYNC use base_node_id.
  std::uint32_t base_node_id = 0x10;
  std::uint32_t node_id_stride = 1;
  // Function codes, added to the node ID (CANopen style).
  std::uint32_t command_function_id = 0x200;    // driver → device: voltage set point
  std::uint32_t voltage_function_id = 0x180;    // device → driver: applied voltage report
  std::uint32_t encoder_function_id = 0x280;    // device → driver: encoder reading
  std::uint32_t heartbeat_function_id = 0x700;  // device → driver: state and fault flags
  // driver → device, synchronous mode only: "take the next sample now" (CANopen SYNC, + base_node_id so two
  // manipulators on one bus stay independent)
  std::uint32_t sync_function_id = 0x080;
  bool extended_ids = false;                    // 29-bit identifiers instead of 11-bit
  ByteOrder byte_order = ByteOrder::kLittle;
  double voltage_lsb_v = 1e-4;   // [V] per count of the int32 voltage fields
  double position_lsb_m = 1e-9;  // [m] per count of the int32 position field
  double encoder_rate_hz = 11.0;      // [Hz] rate of voltage and encoder reports per axis
  double heartbeat_period_s = 1.0;    // [s] device heartbeat period
};

// Throws std::invalid_argument naming the offending field (e.g. "protocol.voltage_lsb_v must be > 0").
void validate(const ProtocolConfig& config);

// Reads the fields present in `node` (missing ones keep their defaults), then validates. Field names are
// those of the struct; byte_order is "little" or "big". Throws std::invalid_argument naming the field.
ProtocolConfig protocol_from_yaml(const YAML::Node& node);

// Loads the `protocol:` section of a YAML file such as config/mm3e.yaml.
ProtocolConfig load_protocol_config(const std::string& path);

}  // namespace piezo::can
