#include "piezo_compensation/can/codec.h"

#include <linux/can/error.h>

#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <stdexcept>

namespace piezo::can {

const char* to_string(DeviceState state) {
  switch (state) {
    case DeviceState::kBoot: return "boot";
    case DeviceState::kOperational: return "operational";
    case DeviceState::kHalted: return "halted";
    case DeviceState::kFault: return "fault";
  }
  return "unknown";
}

const char* to_string(DecodeError error) {
  switch (error) {
    case DecodeError::kNone: return "ok";
    case DecodeError::kUnknownId: return "unknown identifier";
    case DecodeError::kRemoteFrame: return "remote frame";
    case DecodeError::kWrongIdFormat: return "wrong identifier format";
    case DecodeError::kBadLength: return "bad length";
    case DecodeError::kBadField: return "bad field";
  }
  return "unknown";
}

namespace {

constexpr std::uint8_t kVoltageDlc = 8, kEncoderDlc = 8, kCommandDlc = 8, kHeartbeatDlc = 4, kSyncDlc = 1;

std::string hex(std::uint32_t v) {
  char b[16];
  std::snprintf(b, sizeof b, "0x%X", v);
  return b;
}

// Multi-byte fields in the configured byte order.
void put(std::uint8_t* p, std::uint32_t v, int bytes, ByteOrder order) {
  for (int i = 0; i < bytes; ++i) {
    const int shift = order == ByteOrder::kLittle ? 8 * i : 8 * (bytes - 1 - i);
    p[i] = static_cast<std::uint8_t>(v >> shift);
  }
}
std::uint32_t get(const std::uint8_t* p, int bytes, ByteOrder order) {
  std::uint32_t v = 0;
  for (int i = 0; i < bytes; ++i) {
    const int shift = order == ByteOrder::kLittle ? 8 * i : 8 * (bytes - 1 - i);
    v |= static_cast<std::uint32_t>(p[i]) << shift;
  }
  return v;
}

std::int32_t to_counts(double value, double lsb, const char* what) {
  if (!std::isfinite(value)) throw std::invalid_argument(std::string(what) + " is not finite");
  const double counts = std::round(value / lsb);
  if (counts > 2147483647.0 || counts < -2147483648.0)
    throw std::invalid_argument(std::string(what) + " does not fit the int32 field");
  return static_cast<std::int32_t>(counts);
}

void check_axis(int axis) {
  if (axis < 0 || axis >= kAxisCount) throw std::invalid_argument("axis index " + std::to_string(axis) + " is not 0..2");
}

std::string describe_error(const can_frame& f) {
  const std::uint32_t cls = f.can_id & CAN_ERR_MASK;
  std::string s;
  auto add = [&s](const std::string& part) { s += (s.empty() ? "" : "; ") + part; };
  if (cls & CAN_ERR_TX_TIMEOUT) add("tx timeout");
  if (cls & CAN_ERR_LOSTARB) add("lost arbitration");
  if (cls & CAN_ERR_CRTL) {
    std::string c;
    const std::uint8_t d = f.data[1];
    if (d & CAN_ERR_CRTL_RX_OVERFLOW) c += " rx overflow";
    if (d & CAN_ERR_CRTL_TX_OVERFLOW) c += " tx overflow";
    if (d & CAN_ERR_CRTL_RX_WARNING) c += " rx warning";
    if (d & CAN_ERR_CRTL_TX_WARNING) c += " tx warning";
    if (d & CAN_ERR_CRTL_RX_PASSIVE) c += " rx error passive";
    if (d & CAN_ERR_CRTL_TX_PASSIVE) c += " tx error passive";
    if (d & CAN_ERR_CRTL_ACTIVE) c += " back to error active";
    add("controller:" + (c.empty() ? std::string(" unspecified") : c));
  }
  if (cls & CAN_ERR_PROT) add("protocol violation");
  if (cls & CAN_ERR_TRX) add("transceiver");
  if (cls & CAN_ERR_ACK) add("no ack");
  if (cls & CAN_ERR_BUSOFF) add("bus-off");
  if (cls & CAN_ERR_BUSERROR) add("bus error");
  if (cls & CAN_ERR_RESTARTED) add("controller restarted");
  if (s.empty()) s = "error frame without class bits";
  return s;
}

}  // namespace

Codec::Codec(const ProtocolConfig& config) : config_(config) { validate(config_); }

std::uint32_t Codec::command_id(int axis) const {
  return config_.command_function_id + config_.base_node_id + axis * config_.node_id_stride;
}
std::uint32_t Codec::voltage_id(int axis) const {
  return config_.voltage_function_id + config_.base_node_id + axis * config_.node_id_stride;
}
std::uint32_t Codec::encoder_id(int axis) const {
  return config_.encoder_function_id + config_.base_node_id + axis * config_.node_id_stride;
}
std::uint32_t Codec::heartbeat_id() const { return config_.heartbeat_function_id + config_.base_node_id; }
std::uint32_t Codec::sync_id() const { return config_.sync_function_id + config_.base_node_id; }

namespace {
can_frame make_frame(std::uint32_t id, bool extended, std::uint8_t dlc) {
  can_frame f;
  std::memset(&f, 0, sizeof f);
  f.can_id = extended ? (id | CAN_EFF_FLAG) : id;
  f.can_dlc = dlc;
  return f;
}

// Voltage and encoder reports share one payload (decoded together too): counts (4 bytes), the 24-bit
// sequence (3 bytes), the flag byte.
void put_report(can_frame& f, std::int32_t counts, std::uint32_t sequence, bool fault, ByteOrder order) {
  put(f.data, static_cast<std::uint32_t>(counts), 4, order);
  put(f.data + 4, sequence % kSequenceModulo, 3, order);
  f.data[7] = fault ? kReportFlagFault : 0;
}
}  // namespace

can_frame Codec::encode(const CommandFrame& m) const {
  check_axis(m.axis);
  can_frame f = make_frame(command_id(m.axis), config_.extended_ids, kCommandDlc);
  put(f.data, static_cast<std::uint32_t>(to_counts(m.voltage_v, config_.voltage_lsb_v, "command voltage")), 4,
      config_.byte_order);
  put(f.data + 4, m.counter, 4, config_.byte_order);
  return f;
}

can_frame Codec::encode_command(const CommandFrame& m, double lo_v, double hi_v) const {
  if (!(m.voltage_v >= lo_v && m.voltage_v <= hi_v))
    throw std::invalid_argument("command voltage " + std::to_string(m.voltage_v) + " V is outside [" +
                                std::to_string(lo_v) + ", " + std::to_string(hi_v) + "] V");
  const double lsb = config_.voltage_lsb_v;
  double counts = std::round(m.voltage_v / lsb);
  if (counts * lsb > hi_v) counts = std::floor(hi_v / lsb);
  if (counts * lsb < lo_v) counts = std::ceil(lo_v / lsb);
  CommandFrame inside = m;
  inside.voltage_v = counts * lsb;
  const can_frame f = encode(inside);
  const DecodeResult r = decode(f);
  const auto* back = std::get_if<CommandFrame>(&r.message_value);
  if (!r.ok() || !back || !(back->voltage_v >= lo_v && back->voltage_v <= hi_v))
    throw std::invalid_argument("command voltage " + std::to_string(m.voltage_v) +
                                " V has no encoding inside the limits (voltage_lsb_v too coarse?)");
  return f;
}

can_frame Codec::encode(const VoltageReport& m) const {
  check_axis(m.axis);
  can_frame f = make_frame(voltage_id(m.axis), config_.extended_ids, kVoltageDlc);
  put_report(f, to_counts(m.voltage_v, config_.voltage_lsb_v, "reported voltage"), m.sequence, m.fault,
             config_.byte_order);
  return f;
}

can_frame Codec::encode(const EncoderReport& m) const {
  check_axis(m.axis);
  can_frame f = make_frame(encoder_id(m.axis), config_.extended_ids, kEncoderDlc);
  put_report(f, to_counts(m.position_m, config_.position_lsb_m, "encoder position"), m.sequence, !m.valid,
             config_.byte_order);
  return f;
}

can_frame Codec::encode(const Heartbeat& m) const {
  can_frame f = make_frame(heartbeat_id(), config_.extended_ids, kHeartbeatDlc);
  f.data[0] = static_cast<std::uint8_t>(m.state);
  f.data[1] = m.fault_flags;
  put(f.data + 2, m.counter, 2, config_.byte_order);
  return f;
}

can_frame Codec::encode(const SyncFrame& m) const {
  can_frame f = make_frame(sync_id(), config_.extended_ids, kSyncDlc);
  f.data[0] = m.counter;
  return f;
}

can_frame Codec::encode(const BusError& m) {
  can_frame f;
  std::memset(&f, 0, sizeof f);
  f.can_id = CAN_ERR_FLAG | (m.error_class & CAN_ERR_MASK);
  f.can_dlc = CAN_ERR_DLC;
  std::memcpy(f.data, m.data, CAN_ERR_DLC);
  return f;
}

namespace {
// An error frame (CAN_ERR_FLAG, DLC 8) as the bus state it reports.
BusError bus_error_of(const can_frame& f) {
  BusError e;
  e.error_class = f.can_id & CAN_ERR_MASK;
  e.bus_off = e.error_class & CAN_ERR_BUSOFF;
  e.restarted = e.error_class & CAN_ERR_RESTARTED;
  e.error_passive = (e.error_class & CAN_ERR_CRTL) && (f.data[1] & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE));
  std::memcpy(e.data, f.data, CAN_ERR_DLC);
  e.description = describe_error(f);
  return e;
}
}  // namespace

DecodeResult Codec::decode(const can_frame& f) const noexcept {
  DecodeResult r;
  auto fail = [&r](DecodeError e, std::string msg) {
    r.error = e;
    r.message = std::move(msg);
    return r;
  };
  try {
    if (f.can_id & CAN_ERR_FLAG) {
      if (f.can_dlc != CAN_ERR_DLC)
        return fail(DecodeError::kBadLength, "error frame with DLC " + std::to_string(f.can_dlc) + " (expected 8)");
      r.message_value = bus_error_of(f);
      return r;
    }
    const bool extended = f.can_id & CAN_EFF_FLAG;
    const std::uint32_t id = extended ? (f.can_id & CAN_EFF_MASK) : (f.can_id & CAN_SFF_MASK);
    // Identify the frame type first, so a frame of another node is "unknown", not "malformed".
    enum { kNoMatch, kCmd, kVolt, kEnc, kHb, kSync } type = kNoMatch;
    int axis = -1;
    for (int a = 0; a < kAxisCount && type == kNoMatch; ++a) {
      if (id == command_id(a)) type = kCmd, axis = a;
      else if (id == voltage_id(a)) type = kVolt, axis = a;
      else if (id == encoder_id(a)) type = kEnc, axis = a;
    }
    if (type == kNoMatch && id == heartbeat_id()) type = kHb;
    if (type == kNoMatch && id == sync_id()) type = kSync;
    if (type == kNoMatch) return fail(DecodeError::kUnknownId, "identifier " + hex(id) + " is not this device's");
    if (extended != config_.extended_ids)
      return fail(DecodeError::kWrongIdFormat, "identifier " + hex(id) + (extended ? " is 29-bit" : " is 11-bit") +
                                                   " but the protocol uses " +
                                                   (config_.extended_ids ? "29-bit" : "11-bit") + " identifiers");
    if (f.can_id & CAN_RTR_FLAG)
      return fail(DecodeError::kRemoteFrame, "remote (RTR) frame " + hex(id) + ": the protocol has none");
    const std::uint8_t expected = type == kHb ? kHeartbeatDlc : type == kSync ? kSyncDlc : 8;
    if (f.can_dlc != expected)
      return fail(DecodeError::kBadLength, "frame " + hex(id) + " has DLC " + std::to_string(f.can_dlc) +
                                               " (expected " + std::to_string(expected) + ")");
    const ByteOrder order = config_.byte_order;
    switch (type) {
      case kCmd: {
        CommandFrame m;
        m.axis = axis;
        m.voltage_v = static_cast<std::int32_t>(get(f.data, 4, order)) * config_.voltage_lsb_v;
        m.counter = get(f.data + 4, 4, order);
        r.message_value = m;
        return r;
      }
      case kVolt:
      case kEnc: {
        if (f.data[7] & ~kReportFlagFault)
          return fail(DecodeError::kBadField, "frame " + hex(id) + " sets reserved flag bits " + hex(f.data[7]));
        const auto counts = static_cast<std::int32_t>(get(f.data, 4, order));
        const std::uint32_t seq = get(f.data + 4, 3, order);
        if (type == kVolt) {
          VoltageReport m;
          m.axis = axis;
          m.voltage_v = counts * config_.voltage_lsb_v;
          m.sequence = seq;
          m.fault = f.data[7] & kReportFlagFault;
          r.message_value = m;
        } else {
          EncoderReport m;
          m.axis = axis;
          m.position_m = counts * config_.position_lsb_m;
          m.sequence = seq;
          m.valid = !(f.data[7] & kReportFlagFault);
          r.message_value = m;
        }
        return r;
      }
      case kHb: {
        if (f.data[0] > static_cast<std::uint8_t>(DeviceState::kFault))
          return fail(DecodeError::kBadField, "heartbeat has unknown device state " + std::to_string(f.data[0]));
        Heartbeat m;
        m.state = static_cast<DeviceState>(f.data[0]);
        m.fault_flags = f.data[1];
        m.counter = static_cast<std::uint16_t>(get(f.data + 2, 2, order));
        r.message_value = m;
        return r;
      }
      case kSync: {
        SyncFrame m;
        m.counter = f.data[0];
        r.message_value = m;
        return r;
      }
      case kNoMatch: break;
    }
    return fail(DecodeError::kUnknownId, "identifier " + hex(id) + " is not this device's");
  } catch (const std::exception& e) {  // only std::bad_alloc can get here
    r.error = DecodeError::kBadField;
    r.message.clear();
    return r;
  }
}

std::vector<can_filter> Codec::driver_filters() const {
  const canid_t format = config_.extended_ids ? CAN_EFF_FLAG : 0;
  const canid_t mask = (config_.extended_ids ? CAN_EFF_MASK : CAN_SFF_MASK) | CAN_EFF_FLAG | CAN_RTR_FLAG;
  std::vector<can_filter> out;
  for (int a = 0; a < kAxisCount; ++a) {
    out.push_back({voltage_id(a) | format, mask});
    out.push_back({encoder_id(a) | format, mask});
  }
  out.push_back({heartbeat_id() | format, mask});
  return out;
}

std::vector<can_filter> Codec::device_filters() const {
  const canid_t format = config_.extended_ids ? CAN_EFF_FLAG : 0;
  const canid_t mask = (config_.extended_ids ? CAN_EFF_MASK : CAN_SFF_MASK) | CAN_EFF_FLAG | CAN_RTR_FLAG;
  std::vector<can_filter> out;
  for (int a = 0; a < kAxisCount; ++a) out.push_back({command_id(a) | format, mask});
  out.push_back({sync_id() | format, mask});
  return out;
}

SequenceTracker::Update SequenceTracker::update(std::uint32_t wire) {
  Update u;
  wire %= kSequenceModulo;
  if (!started_) {
    started_ = true;
    last_ = wire;
    u.sequence = wire;
    u.first = true;
    return u;
  }
  // Forward distance on the 24-bit circle; more than half the circle back counts as "behind".
  const std::uint32_t last_wire = last_ % kSequenceModulo;
  const std::uint32_t forward = (wire - last_wire) % kSequenceModulo;
  if (forward != 0 && forward < kSequenceModulo / 2) {
    last_ += forward;
    u.sequence = last_;
    u.dropped = forward - 1;
    return u;
  }
  if (forward == 0) {  // the same frame again (CAN may repeat a frame after an error in its last bits)
    u.sequence = last_;
    u.out_of_order = true;
    return u;
  }
  // Any step back: one device never reorders its own frames on a CAN bus, so the controller restarted its
  // counter (or something else is sending in its name). Re-anchor there.
  last_ = wire;
  u.sequence = wire;
  u.restarted = true;
  return u;
}

std::string to_candump(const can_frame& f) {
  char buf[64];
  int n;
  if (f.can_id & CAN_ERR_FLAG)
    n = std::snprintf(buf, sizeof buf, "%08X#", f.can_id & (CAN_ERR_MASK | CAN_ERR_FLAG));
  else if (f.can_id & CAN_EFF_FLAG)
    n = std::snprintf(buf, sizeof buf, "%08X#", f.can_id & CAN_EFF_MASK);
  else
    n = std::snprintf(buf, sizeof buf, "%03X#", f.can_id & CAN_SFF_MASK);
  std::string s(buf, n);
  if (f.can_id & CAN_RTR_FLAG) return s + "R";
  const int len = f.can_dlc > 8 ? 8 : f.can_dlc;
  for (int i = 0; i < len; ++i) {
    std::snprintf(buf, sizeof buf, "%02X", f.data[i]);
    s += buf;
  }
  return s;
}

can_frame from_candump(const std::string& text) {
  const auto hash = text.find('#');
  if (hash == std::string::npos || (hash != 3 && hash != 8))
    throw std::invalid_argument("\"" + text + "\": expected <3 or 8 hex digits>#<data>");
  can_frame f;
  std::memset(&f, 0, sizeof f);
  std::uint32_t id = 0;
  for (std::size_t i = 0; i < hash; ++i) {
    if (!std::isxdigit(static_cast<unsigned char>(text[i]))) throw std::invalid_argument("\"" + text + "\": bad identifier");
    id = id * 16 + std::stoul(text.substr(i, 1), nullptr, 16);
  }
  if (hash == 3) {
    if (id > CAN_SFF_MASK) throw std::invalid_argument("\"" + text + "\": 11-bit identifier above 0x7FF");
    f.can_id = id;
  } else {
    f.can_id = (id & CAN_EFF_MASK) | CAN_EFF_FLAG;
  }
  std::string data = text.substr(hash + 1);
  if (data == "R") {
    f.can_id |= CAN_RTR_FLAG;
    return f;
  }
  std::string digits;
  for (char c : data)
    if (c != '.') digits += c;
  if (digits.size() % 2 != 0 || digits.size() > 16) throw std::invalid_argument("\"" + text + "\": bad data length");
  for (std::size_t i = 0; i < digits.size(); i += 2) {
    if (!std::isxdigit(static_cast<unsigned char>(digits[i])) || !std::isxdigit(static_cast<unsigned char>(digits[i + 1])))
      throw std::invalid_argument("\"" + text + "\": bad data byte");
    f.data[i / 2] = static_cast<std::uint8_t>(std::stoul(digits.substr(i, 2), nullptr, 16));
  }
  f.can_dlc = static_cast<std::uint8_t>(digits.size() / 2);
  return f;
}

}  // namespace piezo::can
