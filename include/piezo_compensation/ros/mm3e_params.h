// Start-up parameter reading shared by mm3e_driver and mm3e_sim: every read checks type and range and
// throws std::invalid_argument naming the fully resolved parameter, so a bad launch stops with one clear line.
#pragma once

#include <ros/ros.h>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/can/protocol.h"
#include "piezo_compensation/can/transport.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::mm3e {

// The ~protocol/<field> entries for every field of can::ProtocolConfig (docs/can_protocol.md), shared by the
// driver's and the simulated device's interface tables.
std::vector<params::ParamDef> protocol_params();
// ~transport, ~interface, ~udp_host, ~udp_local_port, ~udp_remote_port with the node's default ports.
std::vector<params::ParamDef> transport_params(int default_local_port, int default_remote_port);

// Reads the ~protocol entries through the reader's table, then validates.
can::ProtocolConfig read_protocol(params::ParamReader& reader);

struct TransportParams {
  std::string kind = "socketcan";  // socketcan | udp | nanocontrol (the driver and the simulated device build that one)
  std::string interface = "can0";
  std::string host = "127.0.0.1";
  int local_port = 0;
  int remote_port = 0;
  std::string describe() const;   // "can0" or "udp 127.0.0.1:47100"
};
// The transport entries of transport_params(), through the reader's table.
TransportParams read_transport(params::ParamReader& reader);

std::function<std::unique_ptr<can::Transport>()> transport_factory(const TransportParams& params,
                                                                   const std::vector<can_filter>& filters);

}  // namespace piezo::mm3e
