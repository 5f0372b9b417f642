// A simulated stage: a simulator configuration, a protocol with its overrides and a voltage offset, read from
// one YAML file (config/stages/*.yaml). Builds data only: no fit or evaluation reads these settings.
#pragma once

#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/sim/simulator_config.h"

namespace piezo::sim {

struct StageConfig {
  std::string path;                   // file it was read from (for messages)
  std::string description;
  SimulatorConfig simulator;          // `simulator:` (shaped like config/simulator.yaml; omitted keys = defaults)
  std::string protocol = "random_walk";
  YAML::Node protocol_parameters;     // `protocol_parameters:` overrides (shape of config/protocols.yaml[protocol])
  double voltage_offset_v = 0.0;      // added to the protocol's program (its walks are centred on 0 V)
  double duration_s = 0.0;            // > 0: random_walk's duration_s, the other protocols are truncated to it
  std::vector<std::string> axes{"c"}; // axes driven and written; the others are held at 0 V
};

// Throws std::invalid_argument naming the file and the bad key.
StageConfig load_stage(const std::string& yaml_path);

// Runs the stage's protocol (seed for both protocol and simulator); duration_s > 0 overrides the stage's.
io::Dataset simulate_stage(const StageConfig& stage, std::uint64_t seed, double duration_s = 0.0);

}  // namespace piezo::sim
