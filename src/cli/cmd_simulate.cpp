// `piezo simulate`: a protocol run against the simulated MM3E, written as CSV or bag.
#include <cmath>
#include <iostream>
#include <sstream>

#include "args.h"
#include "command.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/sim/stage.h"

namespace piezo::cli {
namespace {

std::vector<std::string> split_axes(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (io::axis_index_or_none(item) < 0)
      throw UsageError("simulate: --axes takes a comma-separated subset of " + io::axis_names_list() + ", got '" + item + "'");
    for (const auto& x : out)
      if (x == item) throw UsageError("simulate: axis '" + item + "' given twice in --axes");
    out.push_back(item);
  }
  if (out.empty()) throw UsageError("simulate: --axes is empty");
  return out;
}

int run(int argc, char** argv) {
  std::string names;
  for (const auto& n : protocols::protocol_names()) names += (names.empty() ? "" : ", ") + n;
  std::string effects;
  for (const auto& e : sim::effect_names()) effects += (effects.empty() ? "" : ", ") + e;
  Args args("simulate",
            "Run a data-collection protocol against the simulated MM3E and write the data set (measured and true\n"
            "positions, voltages, segment/phase markers, temperature_c when thermal drift is on) as CSV or bag.\n"
            "Protocols: " + names + ".\nEffects: " + effects + ".");
  args.option("stage", "YAML", "a stage file (config/stages/*.yaml): simulator, protocol, offset and axes in one;\n"
              "--duration, --seed and --effect still apply, the other options must not be given")
      .option("protocol", "NAME", "protocol to run (required without --stage)")
      .required("out", "FILE", "output file: .bag or .csv")
      .option("duration", "T", "length (30, 90min, 26h): sets random_walk's duration_s, truncates the other protocols")
      .option("seed", "N", "seed for the protocol and the simulator", "1")
      .option("effect", "NAME", "switch on an extra effect", "", true)
      .option("config", "YAML", "simulator parameters (default: built-in = config/simulator.yaml)")
      .option("protocol-config", "YAML", "protocol parameters (default: built-in = config/protocols.yaml)")
      .option("axes", "LIST", "axes to drive and write; the others are held at 0 V", "a,b,c");
  if (!args.parse(argc, argv)) return 0;
  const long seed_l = args.integer("seed");
  if (seed_l < 0) throw UsageError("simulate: --seed must be >= 0");
  const auto seed = static_cast<std::uint64_t>(seed_l);
  double duration_s = -1.0;
  if (args.has("duration")) {
    duration_s = args.seconds("duration");
    if (!(duration_s > 0.0) || !std::isfinite(duration_s)) throw UsageError("simulate: --duration must be > 0");
  }
  const std::string out = args.str("out");

  if (args.has("stage")) {
    for (const char* o : {"protocol", "config", "protocol-config"})
      if (args.has(o)) throw UsageError(std::string("simulate: --") + o + " cannot be combined with --stage");
    sim::StageConfig stage = sim::load_stage(args.str("stage"));
    for (const auto& e : args.list("effect")) sim::enable_effect(stage.simulator, e);
    const io::Dataset data = sim::simulate_stage(stage, seed, duration_s);
    ros_io::write_data(out, data);
    std::cout << out << ": " << data.source << ", " << data.size() << " samples at " << stage.simulator.sample_rate_hz
              << " Hz (" << data.size() / stage.simulator.sample_rate_hz << " s), seed " << seed << "\n";
    return 0;
  }
  if (!args.has("protocol")) throw UsageError("simulate: give --protocol NAME or --stage FILE");

  sim::SimulatorConfig cfg =
      args.has("config") ? sim::load_simulator_config(args.str("config")) : sim::default_simulator_config();
  for (const auto& e : args.list("effect")) sim::enable_effect(cfg, e);
  const std::string name = args.str("protocol");

  YAML::Node params = args.has("protocol-config") ? protocols::load_protocol_parameters(args.str("protocol-config"), name)
                                                  : YAML::Node();
  if (duration_s > 0.0 && name == "random_walk") params["duration_s"] = duration_s;
  const auto protocol = protocols::make_protocol(name, params, cfg.sample_rate_hz, seed);
  std::size_t n = protocol->size();
  if (duration_s > 0.0) n = std::min(n, static_cast<std::size_t>(std::llround(duration_s * cfg.sample_rate_hz)));
  if (n < 2) throw UsageError("simulate: --duration gives fewer than 2 samples");

  io::Dataset program = protocol->program(0, n);
  const auto keep = split_axes(args.str("axes"));
  std::vector<io::AxisSeries> axes;
  for (const auto& a : program.axes)
    for (const auto& k : keep)
      if (a.name == k) axes.push_back(a);
  program.axes = axes;

  sim::ManipulatorSimulator simulator(cfg, seed);
  io::Dataset data = simulator.run(program);
  data.source = "protocol " + name;
  ros_io::write_data(out, data);

  std::cout << out << ": " << name << ", " << data.size() << " samples at " << cfg.sample_rate_hz << " Hz ("
            << data.size() / cfg.sample_rate_hz / 3600.0 << " h), seed " << seed << ", axes";
  for (const auto& a : data.axes) std::cout << " " << a.name;
  const auto on = sim::enabled_effects(cfg);
  std::cout << ", effects:";
  for (const auto& e : on) std::cout << " " << e;
  if (on.empty()) std::cout << " none";
  std::cout << "\n";
  return 0;
}

const Register reg("simulate", "run a protocol against the simulated MM3E, write CSV or bag", run);
}  // namespace
}  // namespace piezo::cli
