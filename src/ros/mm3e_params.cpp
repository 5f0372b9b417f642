#include "piezo_compensation/ros/mm3e_params.h"

#include "piezo_compensation/ros/params.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::mm3e {

std::vector<params::ParamDef> protocol_params() {
  const can::ProtocolConfig d;
  const int max_id = 0x1FFFFFFF;
  const auto id = [&](const char* name, std::uint32_t v, int min, const char* meaning) {
    return params::integer(std::string("protocol/") + name, "", static_cast<int>(v), min, max_id, meaning);
  };
  return {
      id("base_node_id", d.base_node_id, 0, "node ID of axis a; axis i = base_node_id + i × node_id_stride"),
      id("node_id_stride", d.node_id_stride, 1, "node ID step from one axis to the next"),
      id("command_function_id", d.command_function_id, 0, "driver → device voltage set point, id = this + node ID"),
      id("voltage_function_id", d.voltage_function_id, 0, "device → driver applied voltage, id = this + node ID"),
      id("encoder_function_id", d.encoder_function_id, 0, "device → driver encoder reading, id = this + node ID"),
      id("heartbeat_function_id", d.heartbeat_function_id, 0, "device → driver heartbeat, id = this + base_node_id"),
      id("sync_function_id", d.sync_function_id, 0,
         "driver → device \"sample now\" in synchronous mode, id = this + base_node_id"),
      params::flag("protocol/extended_ids", d.extended_ids, "29-bit identifiers instead of 11-bit"),
      params::text("protocol/byte_order", d.byte_order == can::ByteOrder::kBig ? "big" : "little",
                   "byte order of every multi-byte field", {"little", "big"}),
      params::number("protocol/voltage_lsb_v", "V", d.voltage_lsb_v, 1e-9, 0.01, "voltage per count of the int32 voltage fields"),
      params::number("protocol/position_lsb_m", "m", d.position_lsb_m, 1e-15, 1e-3, "position per count of the int32 position field"),
      params::number("protocol/encoder_rate_hz", "Hz", d.encoder_rate_hz, 0.01, 10000.0, "voltage and encoder report rate per axis"),
      params::number("protocol/heartbeat_period_s", "s", d.heartbeat_period_s, 0.001, 3600.0, "device heartbeat period"),
  };
}

std::vector<params::ParamDef> transport_params(int default_local_port, int default_remote_port) {
  return {
      params::text("transport", "socketcan",
                   "socketcan (a real bus or vcan), udp (the same frames over loopback, for kernels without CAN) or "
                   "nanocontrol (a Kleindiek NanoControl's serial line protocol, docs/nanocontrol.md)",
                   {"socketcan", "udp", "nanocontrol"}),
      params::text("interface", "can0", "SocketCAN interface (socketcan only)").rule("1..15 characters"),
      params::text("udp_host", "127.0.0.1", "IPv4 address of both UDP ends (udp only)"),
      params::integer("udp_local_port", "port", default_local_port, 1, 65535, "this node receives frames here (udp only)"),
      params::integer("udp_remote_port", "port", default_remote_port, 1, 65535,
                      "the other end receives frames here (udp only)").rule("≠ udp_local_port with udp"),
  };
}

can::ProtocolConfig read_protocol(params::ParamReader& r) {
  can::ProtocolConfig c;
  const auto id = [&](const char* name) { return static_cast<std::uint32_t>(r.integer(std::string("protocol/") + name)); };
  c.base_node_id = id("base_node_id");
  c.node_id_stride = id("node_id_stride");
  c.command_function_id = id("command_function_id");
  c.voltage_function_id = id("voltage_function_id");
  c.encoder_function_id = id("encoder_function_id");
  c.heartbeat_function_id = id("heartbeat_function_id");
  c.sync_function_id = id("sync_function_id");
  c.extended_ids = r.flag("protocol/extended_ids");
  c.byte_order = r.text("protocol/byte_order") == "big" ? can::ByteOrder::kBig : can::ByteOrder::kLittle;
  c.voltage_lsb_v = r.number("protocol/voltage_lsb_v");
  c.position_lsb_m = r.number("protocol/position_lsb_m");
  c.encoder_rate_hz = r.number("protocol/encoder_rate_hz");
  c.heartbeat_period_s = r.number("protocol/heartbeat_period_s");
  try {
    can::validate(c);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("parameters " + r.resolved("protocol") + ": " + e.what());
  }
  return c;
}

std::string TransportParams::describe() const {
  if (kind == "nanocontrol") return "nanocontrol";
  return kind == "udp" ? "udp " + host + ":" + std::to_string(local_port) : interface;
}

TransportParams read_transport(params::ParamReader& r) {
  TransportParams t;
  t.kind = r.text("transport");
  t.interface = r.text("interface");
  if (t.interface.empty() || t.interface.size() > 15)
    throw std::invalid_argument("parameter " + r.resolved("interface") + " must be 1..15 characters");
  t.host = r.text("udp_host");
  t.local_port = r.integer("udp_local_port");
  t.remote_port = r.integer("udp_remote_port");
  if (t.kind == "udp" && t.local_port == t.remote_port)
    throw std::invalid_argument("parameters " + r.resolved("udp_local_port") + " and udp_remote_port must differ");
  return t;
}

std::function<std::unique_ptr<can::Transport>()> transport_factory(const TransportParams& params,
                                                                   const std::vector<can_filter>& filters) {
  if (params.kind == "nanocontrol")  // a serial port, not frames: nanocontrol::make_transport / the pseudo-terminal
    throw std::logic_error("transport_factory: nanocontrol has no CAN frame transport");
  if (params.kind == "udp") {
    can::UdpOptions o;
    o.host = params.host;
    o.local_port = params.local_port;
    o.remote_port = params.remote_port;
    o.filters = filters;
    return [o] { return can::make_udp_transport(o); };
  }
  can::SocketCanOptions o;
  o.interface = params.interface;
  o.filters = filters;
  return [o] { return can::make_socketcan_transport(o); };
}

}  // namespace piezo::mm3e
