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

can::ProtocolConfig read_protocol(const ros::NodeHandle& pnh) {
  can::ProtocolConfig c;
  const ros::NodeHandle p(pnh, "protocol");
  const int max_id = 0x1FFFFFFF;
  c.base_node_id = param_int(p, "base_node_id", c.base_node_id, 0, max_id);
  c.node_id_stride = param_int(p, "node_id_stride", c.node_id_stride, 1, max_id);
  c.command_function_id = param_int(p, "command_function_id", c.command_function_id, 0, max_id);
  c.voltage_function_id = param_int(p, "voltage_function_id", c.voltage_function_id, 0, max_id);
  c.encoder_function_id = param_int(p, "encoder_function_id", c.encoder_function_id, 0, max_id);
  c.heartbeat_function_id = param_int(p, "heartbeat_function_id", c.heartbeat_function_id, 0, max_id);
  c.sync_function_id = param_int(p, "sync_function_id", c.sync_function_id, 0, max_id);
  c.extended_ids = param_bool(p, "extended_ids", c.extended_ids);
  c.byte_order = param_string(p, "byte_order", "little", {"little", "big"}) == "big" ? can::ByteOrder::kBig
                                                                                    : can::ByteOrder::kLittle;
  c.voltage_lsb_v = param_double(p, "voltage_lsb_v", c.voltage_lsb_v, 1e-9, 1.0);
  c.position_lsb_m = param_double(p, "position_lsb_m", c.position_lsb_m, 1e-15, 1e-3);
  c.encoder_rate_hz = param_double(p, "encoder_rate_hz", c.encoder_rate_hz, 0.01, 10000.0);
  c.heartbeat_period_s = param_double(p, "heartbeat_period_s", c.heartbeat_period_s, 0.001, 3600.0);
  try {
    can::validate(c);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument("parameters " + p.getNamespace() + ": " + e.what());
  }
  return c;
}

std::string TransportParams::describe() const {
  return kind == "udp" ? "udp " + host + ":" + std::to_string(local_port) : interface;
}

TransportParams read_transport(const ros::NodeHandle& pnh, int default_local_port, int default_remote_port) {
  TransportParams t;
  t.kind = param_string(pnh, "transport", "socketcan", {"socketcan", "udp"});
  t.interface = param_string(pnh, "interface", "can0");
  if (t.interface.empty() || t.interface.size() > 15)
    throw std::invalid_argument("parameter " + pnh.resolveName("interface") + " must be 1..15 characters");
  t.host = param_string(pnh, "udp_host", "127.0.0.1");
  t.local_port = param_int(pnh, "udp_local_port", default_local_port, 1, 65535);
  t.remote_port = param_int(pnh, "udp_remote_port", default_remote_port, 1, 65535);
  if (t.kind == "udp" && t.local_port == t.remote_port)
    throw std::invalid_argument("parameters " + pnh.resolveName("udp_local_port") + " and udp_remote_port must differ");
  return t;
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
