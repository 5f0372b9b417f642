#include "piezo_compensation/ros/mm3e_params.h"

#include "piezo_compensation/ros/params.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::mm3e {

// The typed, ranged reads are the shared parameter layer's (ros/params.h); these keep the driver's call sites.
double param_double(const ros::NodeHandle& nh, const std::string& name, double fallback, double min, double max) {
  return params::ParamReader(nh).number(name, fallback, min, max);
}

int param_int(const ros::NodeHandle& nh, const std::string& name, int fallback, int min, int max) {
  return params::ParamReader(nh).integer(name, fallback, min, max);
}

bool param_bool(const ros::NodeHandle& nh, const std::string& name, bool fallback) {
  return params::ParamReader(nh).flag(name, fallback);
}

std::string param_string(const ros::NodeHandle& nh, const std::string& name, const std::string& fallback,
                         const std::vector<std::string>& allowed) {
  return params::ParamReader(nh).text(name, fallback, allowed);
}

can::ProtocolConfig read_protocol(params::ParamReader& r) {
  can::ProtocolConfig c;
  const int max_id = 0x1FFFFFFF;
  c.base_node_id = r.integer("protocol/base_node_id", c.base_node_id, 0, max_id);
  c.node_id_stride = r.integer("protocol/node_id_stride", c.node_id_stride, 1, max_id);
  c.command_function_id = r.integer("protocol/command_function_id", c.command_function_id, 0, max_id);
  c.voltage_function_id = r.integer("protocol/voltage_function_id", c.voltage_function_id, 0, max_id);
  c.encoder_function_id = r.integer("protocol/encoder_function_id", c.encoder_function_id, 0, max_id);
  c.heartbeat_function_id = r.integer("protocol/heartbeat_function_id", c.heartbeat_function_id, 0, max_id);
  c.sync_function_id = r.integer("protocol/sync_function_id", c.sync_function_id, 0, max_id);
  c.extended_ids = r.flag("protocol/extended_ids", c.extended_ids);
  c.byte_order = r.text("protocol/byte_order", "little", {"little", "big"}) == "big" ? can::ByteOrder::kBig
                                                                                      : can::ByteOrder::kLittle;
  c.voltage_lsb_v = r.number("protocol/voltage_lsb_v", c.voltage_lsb_v, 1e-9, 0.01);
  c.position_lsb_m = r.number("protocol/position_lsb_m", c.position_lsb_m, 1e-15, 1e-3);
  c.encoder_rate_hz = r.number("protocol/encoder_rate_hz", c.encoder_rate_hz, 0.01, 10000.0);
  c.heartbeat_period_s = r.number("protocol/heartbeat_period_s", c.heartbeat_period_s, 0.001, 3600.0);
  try {
    can::validate(c);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("parameters " + r.resolved("protocol") + ": " + e.what());
  }
  return c;
}

can::ProtocolConfig read_protocol(const ros::NodeHandle& pnh) {
  params::ParamReader r(pnh);
  return read_protocol(r);
}

std::string TransportParams::describe() const {
  return kind == "udp" ? "udp " + host + ":" + std::to_string(local_port) : interface;
}

TransportParams read_transport(params::ParamReader& r, int default_local_port, int default_remote_port) {
  TransportParams t;
  t.kind = r.text("transport", "socketcan", {"socketcan", "udp"});
  t.interface = r.text("interface", "can0");
  if (t.interface.empty() || t.interface.size() > 15)
    throw std::invalid_argument("parameter " + r.resolved("interface") + " must be 1..15 characters");
  t.host = r.text("udp_host", "127.0.0.1");
  t.local_port = r.integer("udp_local_port", default_local_port, 1, 65535);
  t.remote_port = r.integer("udp_remote_port", default_remote_port, 1, 65535);
  if (t.kind == "udp" && t.local_port == t.remote_port)
    throw std::invalid_argument("parameters " + r.resolved("udp_local_port") + " and udp_remote_port must differ");
  return t;
}

TransportParams read_transport(const ros::NodeHandle& pnh, int default_local_port, int default_remote_port) {
  params::ParamReader r(pnh);
  return read_transport(r, default_local_port, default_remote_port);
}

std::function<std::unique_ptr<can::Transport>()> transport_factory(const TransportParams& params,
                                                                   const std::vector<can_filter>& filters) {
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
