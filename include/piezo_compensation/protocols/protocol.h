// Data-collection protocols of the reference study as pure voltage programs: no I/O, no clock.
// Random access by sample index, so an interrupted recording resumes exactly where it stopped.
#pragma once

#include <yaml-cpp/yaml.h>

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/io/holds.h"

namespace piezo::protocols {

// Phase codes, also written as the `phase` column of CSV data.
enum class Phase : int {
  kExcite = 0,   // voltage moving (random walk, creep history)
  kHold = 1,     // voltage constant to observe creep
  kSettle = 2,   // waiting before a measurement (noise protocol)
  kRecord = 3,   // measuring at constant voltage (noise protocol)
  kSweep = 4,    // hysteresis sweep
};
static_assert(static_cast<int>(Phase::kHold) == io::kHoldPhase, "io::find_holds reads the hold phase code");
const char* phase_name(Phase p);
// Inverse of phase_name; throws std::invalid_argument listing the valid names.
Phase phase_from_name(const std::string& name);

struct ProtocolSample {
  std::array<double, 3> voltage_v{};  // a, b, c
  int segment = 0;                    // scenario / series index
  Phase phase = Phase::kExcite;
};

class Protocol {
 public:
  virtual ~Protocol() = default;
  virtual std::string name() const = 0;
  virtual std::size_t size() const = 0;               // number of samples
  virtual ProtocolSample at(std::size_t i) const = 0; // sample i (0 ≤ i < size())
  virtual double sample_rate_hz() const = 0;
  // Everything needed to regenerate it: {protocol, sample_rate_hz, seed, parameters (complete, merged)}.
  virtual YAML::Node parameters() const = 0;

  // Samples [begin, end) as a voltage-only data set (positions 0), with segment and phase columns.
  io::Dataset program(std::size_t begin = 0, std::size_t end = SIZE_MAX) const;
};

// Names: "noise", "random_walk", "sweep", "creep", "plan" (three random walks + creep set), "sawtooth".
// `params` is the map of that protocol's overrides (null = defaults; shape of config/protocols.yaml[name]); throws
// std::invalid_argument naming a bad key as "<name>.<key>". Segments and phases per protocol: docs/simulator.md.
std::unique_ptr<Protocol> make_protocol(const std::string& name, const YAML::Node& params, double sample_rate_hz,
                                        std::uint64_t seed);
std::vector<std::string> protocol_names();

// The built-in defaults of every protocol, keyed by name (mirrored by config/protocols.yaml).
YAML::Node default_protocol_parameters();
// Loads a protocols file shaped like config/protocols.yaml and returns the map for `name` (empty node if the
// file has no entry for it). Throws std::invalid_argument naming the file on a read error.
YAML::Node load_protocol_parameters(const std::string& yaml_path, const std::string& name);

}  // namespace piezo::protocols
