// Internal to protocols/: the generator implementations behind make_protocol.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <memory>
#include <string>

#include "piezo_compensation/protocols/protocol.h"

namespace piezo::protocols {

// Deep copy of `defaults` with `overrides` applied; an override key that is not in the defaults, or of the wrong
// shape, throws std::invalid_argument naming "<where>.<key>".
YAML::Node merge_parameters(const YAML::Node& defaults, const YAML::Node& overrides, const std::string& where);

// `params` are complete (merged with the defaults).
std::unique_ptr<Protocol> make_generated(const std::string& name, const YAML::Node& params, double sample_rate_hz,
                                         std::uint64_t seed);

}  // namespace piezo::protocols
