// Pure frame codec for the MM3E protocol (layouts in docs/can_protocol.md). No I/O, no clocks, no state:
// the same object encodes on one side and decodes on the other, and the fuzz target drives decode().
#pragma once

#include <linux/can.h>
#include <linux/can/error.h>

#include <cstdint>
#include <string>
#include <variant>
#include <vector>

#include "piezo_compensation/can/protocol.h"

namespace piezo::can {

// Driver → device: voltage set point of one axis.
struct CommandFrame {
  int axis = 0;
  double voltage_v = 0.0;
  std::uint32_t counter = 0;  // driver's command counter (device echoes nothing; for candump readers)
};

constexpr std::uint8_t kReportFlagFault = 0x01;   // voltage: amplifier fault; encoder: reading invalid
constexpr std::uint32_t kSequenceModulo = 1u << 24;  // wire sequence counters are 24 bit

// Device → driver: voltage applied to one axis.
struct VoltageReport {
  int axis = 0;
  double voltage_v = 0.0;
  std::uint32_t sequence = 0;  // 24-bit wire counter
  bool fault = false;
};

// Device → driver: encoder reading of one axis.
struct EncoderReport {
  int axis = 0;
  double position_m = 0.0;
  std::uint32_t sequence = 0;  // 24-bit wire counter
  bool valid = true;
};

enum class DeviceState : std::uint8_t { kBoot = 0, kOperational = 1, kHalted = 2, kFault = 3 };
const char* to_string(DeviceState state);

// Device → driver: heartbeat with the controller's state.
struct Heartbeat {
  DeviceState state = DeviceState::kOperational;
  std::uint8_t fault_flags = 0;  // bit i: axis i faulted; bit 7: over-temperature
  std::uint16_t counter = 0;
};

// Driver → device, synchronous mode only: the controller takes its next sample when this arrives instead of
// on its own clock (CANopen SYNC; DLC 1, a wrapping counter so candump readers see lost SYNCs).
struct SyncFrame {
  std::uint8_t counter = 0;
};

// A SocketCAN error frame (CAN_ERR_FLAG), as the kernel reports bus problems.
struct BusError {
  std::uint32_t error_class = 0;  // CAN_ERR_* bits of can_id
  bool bus_off = false;
  bool error_passive = false;  // controller reports RX/TX error passive
  bool restarted = false;      // controller restarted after bus-off
  std::uint8_t data[CAN_ERR_DLC] = {};
  std::string description;     // "bus-off; controller: tx error passive"
};

using Message = std::variant<CommandFrame, VoltageReport, EncoderReport, Heartbeat, SyncFrame, BusError>;

enum class DecodeError {
  kNone,
  kUnknownId,      // not one of this device's identifiers (another node on the bus)
  kRemoteFrame,    // RTR frame: the protocol has none
  kWrongIdFormat,  // 29-bit id where 11-bit is configured or the other way round
  kBadLength,      // DLC does not match the frame type (or exceeds 8)
  kBadField,       // reserved bits set, unknown device state
};
const char* to_string(DecodeError error);

struct DecodeResult {
  DecodeError error = DecodeError::kNone;
  std::string message;  // one line naming what was wrong (empty when ok)
  Message message_value;
  bool ok() const { return error == DecodeError::kNone; }
};

class Codec {
 public:
  // Validates the config (std::invalid_argument naming the field).
  explicit Codec(const ProtocolConfig& config);

  const ProtocolConfig& config() const { return config_; }

  // Encoders throw std::invalid_argument for an axis outside 0..2, a non-finite value or one that does not
  // fit the int32 field; they never produce a frame from NaN.
  can_frame encode(const CommandFrame& m) const;
  // The command frame the driver writes: the voltage rounds to a count inside [lo_v, hi_v] (towards the
  // inside when the nearest count is outside), and the frame is decoded again to check it. Throws
  // std::invalid_argument when the value or the encoded one is not within [lo_v, hi_v].
  can_frame encode_command(const CommandFrame& m, double lo_v, double hi_v) const;
  can_frame encode(const VoltageReport& m) const;
  can_frame encode(const EncoderReport& m) const;
  can_frame encode(const Heartbeat& m) const;
  can_frame encode(const SyncFrame& m) const;
  static can_frame encode(const BusError& m);  // error frame (for the simulated device's fault injection)

  // Never throws; any 16-byte input is accepted.
  DecodeResult decode(const can_frame& frame) const noexcept;

  // Identifiers, for filters and candump readers.
  std::uint32_t command_id(int axis) const;
  std::uint32_t voltage_id(int axis) const;
  std::uint32_t encoder_id(int axis) const;
  std::uint32_t heartbeat_id() const;
  std::uint32_t sync_id() const;

  // Kernel filters (id, mask) for what the driver receives (reports + heartbeat) or the device receives
  // (commands and SYNC). Masks include CAN_EFF_FLAG and CAN_RTR_FLAG so only data frames of the right format pass.
  std::vector<can_filter> driver_filters() const;
  std::vector<can_filter> device_filters() const;

 private:
  ProtocolConfig config_;
};

// Unwraps 24-bit wire counters into a 32-bit sequence and counts gaps and reordering.
class SequenceTracker {
 public:
  struct Update {
    std::uint32_t sequence = 0;  // unwrapped (wraps at 2^32)
    std::uint32_t dropped = 0;   // frames missing before this one
    bool out_of_order = false;   // the same counter again (a repeated frame)
    bool restarted = false;      // any step back: the controller restarted its counter; re-anchored there
    bool first = false;          // the first since construction or reset(): nothing to compare it with
  };
  Update update(std::uint32_t wire_sequence);
  void reset() { started_ = false; }

 private:
  bool started_ = false;
  std::uint32_t last_ = 0;  // unwrapped
};

// Bytes of a frame as candump prints them ("123#DEADBEEF"), for logs and tests.
std::string to_candump(const can_frame& frame);
// Parses cansend syntax ("123#DEADBEEF", "12345678#00", "123#R"); throws std::invalid_argument.
can_frame from_candump(const std::string& text);

}  // namespace piezo::can
