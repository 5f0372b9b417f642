// `piezo record`: a data-collection protocol run offline against the simulator at full speed, into a bag or
// CSV, with the recorder's summary. Interruptible and resumable like the recorder node: the output is
// rewritten atomically at checkpoints, and a sidecar FILE.record.yaml remembers protocol, seed and effects.
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>

#include <yaml-cpp/yaml.h>

#include "args.h"
#include "command.h"
#include "plot_script.h"
#include "piezo_compensation/analysis/evaluation/recording_summary.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/data_file.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

namespace fs = std::filesystem;

namespace piezo::cli {
namespace {

std::atomic<bool> g_stop{false};
extern "C" void on_signal(int) { g_stop = true; }

// Everything that determines the recording, so a resume regenerates exactly the same samples.
struct Spec {
  std::string protocol;
  YAML::Node params{YAML::NodeType::Map};
  std::uint64_t seed = 1;
  double rate_hz = 11.0;
  std::size_t samples = 0;  // samples to record (protocol size, or cut by --duration)
  std::vector<std::string> effects;
  std::string simulator_config;  // YAML file, "" = built-in defaults
};

YAML::Node spec_yaml(const Spec& s, std::size_t done, bool complete) {
  YAML::Node n;
  n["protocol"] = s.protocol;
  n["parameters"] = s.params;
  n["seed"] = s.seed;
  n["sample_rate_hz"] = s.rate_hz;
  n["samples"] = s.samples;
  n["effects"] = s.effects;
  n["simulator_config"] = s.simulator_config;
  n["samples_done"] = done;
  n["complete"] = complete;
  return n;
}

Spec spec_from_yaml(const YAML::Node& n, const std::string& where) {
  Spec s;
  try {
    s.protocol = n["protocol"].as<std::string>();
    s.params = n["parameters"] ? n["parameters"] : YAML::Node(YAML::NodeType::Map);
    s.seed = n["seed"].as<std::uint64_t>();
    s.rate_hz = n["sample_rate_hz"].as<double>();
    s.samples = n["samples"].as<std::size_t>();
    if (n["effects"]) s.effects = n["effects"].as<std::vector<std::string>>();
    s.simulator_config = n["simulator_config"] ? n["simulator_config"].as<std::string>() : "";
  } catch (const YAML::Exception& e) {
    throw io::DataError(where + ": not a record sidecar (" + e.what() + ")");
  }
  return s;
}

std::string with_ext_tmp(const std::string& out) {
  // keep the extension: write_data dispatches on it
  const fs::path p(out);
  return (p.parent_path() / ("." + p.stem().string() + ".tmp-" + std::to_string(::getpid()) + p.extension().string()))
      .string();
}

// Atomic: a crash while writing leaves the previous checkpoint intact.
void write_checkpoint(const std::string& out, const io::Dataset& data, const Spec& spec, bool complete) {
  const std::string tmp = with_ext_tmp(out);
  try {
    ros_io::write_data(tmp, data);
  } catch (...) {
    std::error_code ec;
    fs::remove(tmp, ec);
    throw;
  }
  fs::rename(tmp, out);
  const std::string side = out + ".record.yaml";
  const std::string side_tmp = side + ".tmp";
  {
    std::ofstream f(side_tmp);
    f << "# piezo record: what produced " << fs::path(out).filename().string() << " (used by --resume)\n"
      << spec_yaml(spec, data.size(), complete) << "\n";
    if (!f) throw io::DataError(side + ": cannot write (disk full?)");
  }
  fs::rename(side_tmp, side);
}

sim::SimulatorConfig simulator_config(const Spec& spec) {
  sim::SimulatorConfig cfg =
      spec.simulator_config.empty() ? sim::default_simulator_config() : sim::load_simulator_config(spec.simulator_config);
  for (const auto& e : spec.effects) sim::enable_effect(cfg, e);
  sim::validate(cfg);
  return cfg;
}

// program() rows with their segment/phase columns kept on the simulated data.
io::Dataset simulate_block(sim::ManipulatorSimulator& simulator, const io::Dataset& program) {
  io::Dataset out = simulator.run(program);
  if (out.segment.size() != out.size()) out.segment = program.segment;
  if (out.phase.size() != out.size()) out.phase = program.phase;
  return out;
}

// --resume: the sidecar's spec (checked against --protocol and --seed) and the data recorded so far.
Spec resumed_spec(const Args& args, const std::string& out, const std::string& sidecar, io::Dataset& data) {
  if (!fs::exists(sidecar))
    throw UsageError("record: --resume: " + sidecar + " is missing, so the protocol that made " + out + " is unknown");
  YAML::Node side;
  try {
    side = YAML::LoadFile(sidecar);
  } catch (const YAML::Exception& e) {
    throw io::DataError(sidecar + ": " + e.what());
  }
  Spec spec = spec_from_yaml(side, sidecar);
  if (args.has("protocol") && args.str("protocol") != spec.protocol)
    throw UsageError("record: --resume: " + out + " holds protocol '" + spec.protocol + "', not '" +
                     args.str("protocol") + "'");
  if (args.has("seed") && static_cast<std::uint64_t>(args.integer("seed")) != spec.seed)
    throw UsageError("record: --resume: " + out + " was recorded with seed " + std::to_string(spec.seed));
  data = ros_io::read_data(out);
  return spec;
}

// A new recording: protocol, seed, parameter overrides, effects and simulator config from the options.
Spec new_spec(const Args& args, const std::string& out) {
  if (!args.has("protocol")) throw UsageError("record: missing required option --protocol NAME (see --help)");
  if (fs::exists(out) && !args.flag("force") && !args.flag("resume"))
    throw UsageError("record: " + out + " exists; --resume to continue it or --force to overwrite");
  Spec spec;
  spec.protocol = args.str("protocol");
  spec.seed = static_cast<std::uint64_t>(args.integer("seed"));
  if (args.has("params")) {
    YAML::Node p;
    try {
      p = YAML::LoadFile(args.str("params"));
    } catch (const YAML::Exception& e) {
      throw UsageError("record: --params " + args.str("params") + ": " + e.what());
    }
    if (p[spec.protocol] && p[spec.protocol].IsMap()) p = p[spec.protocol];
    if (!p.IsMap()) throw UsageError("record: --params " + args.str("params") + ": expected a YAML map");
    spec.params = p;
  }
  for (const auto& kv : args.list("set")) {
    const auto eq = kv.find('=');
    if (eq == std::string::npos || eq == 0) throw UsageError("record: --set expects KEY=VALUE, got '" + kv + "'");
    spec.params[kv.substr(0, eq)] = YAML::Load(kv.substr(eq + 1));
  }
  for (const auto& e : args.list("effect")) spec.effects.push_back(e);
  if (args.has("simulator-config")) {
    spec.simulator_config = fs::absolute(args.str("simulator-config")).string();
  } else {
    // The package's config/simulator.yaml (source tree or install space, never the current directory);
    // without it the built-in defaults, which are the same physics.
    try {
      spec.simulator_config = find_package_file("config/simulator.yaml").string();
    } catch (const std::runtime_error&) {
    }
  }
  return spec;
}

// A new recording's spec completed from its protocol: the full parameter set (so the sidecar alone regenerates it)
// and the number of samples (cut by --duration).
void complete_new_spec(const Args& args, const protocols::Protocol& protocol, Spec& spec) {
  const YAML::Node full = protocol.parameters();
  spec.params = full["parameters"] && full["parameters"].IsMap() ? full["parameters"] : full;
  spec.samples = protocol.size();
  if (args.has("duration")) {
    const double d = args.seconds("duration");
    if (!(d > 0.0)) throw UsageError("record: --duration must be > 0 s");
    spec.samples = std::min(spec.samples, static_cast<std::size_t>(std::llround(d * spec.rate_hz)));
  }
}

// Resuming: the file must be exactly the first samples of this protocol; the simulator is replayed to the state
// after them (it is deterministic by seed). Returns the samples done.
std::size_t replay_recorded(const Spec& spec, const protocols::Protocol& protocol, const std::string& out,
                            io::Dataset& data, sim::ManipulatorSimulator& simulator) {
  const std::size_t done = data.size();
  if (done > spec.samples)
    throw io::DataError(out + ": holds " + std::to_string(done) + " samples, more than the " +
                        std::to_string(spec.samples) + " of the recording");
  if (done > 0) {
    // the file must be exactly the first `done` samples of this protocol: same times and voltages
    const io::Dataset head = protocol.program(0, done);
    // a bag may come back without the marker columns; they are the program's anyway
    if (data.segment.size() != done) data.segment = head.segment;
    if (data.phase.size() != done) data.phase = head.phase;
    const auto match = analysis::compare_voltages(data, head, 1e-6);
    const double dt = std::fabs(data.time_s.back() - head.time_s.back());
    if (match.mismatched > 0 || dt > 0.01 / spec.rate_hz)
      throw io::DataError(out + ": does not continue protocol '" + spec.protocol + "' (row " +
                          std::to_string(match.first_mismatch + 2) + " differs from the program)");
    const io::Dataset replay = simulate_block(simulator, head);
    double max_diff = 0.0;
    for (const auto& a : data.axes)
      if (replay.has_axis(a.name))
        for (std::size_t i = 0; i < done; ++i)
          max_diff = std::max(max_diff, std::fabs(a.position_nm[i] - replay.axis(a.name).position_nm[i]));
    if (max_diff > 1e-3)
      std::cerr << "record: warning: replaying the simulator differs from " << out << " by up to " << max_diff
                << " nm (simulator changed since?); continuing from the replayed state\n";
  }
  std::cerr << "record: resuming " << out << " at sample " << done << " of " << spec.samples << "\n";
  return done;
}

// Simulates blocks of 10 min until the recording is complete or a signal stops it, with progress lines and
// checkpoints at least every `checkpoint_s` of wall time. Returns the samples done.
std::size_t record_blocks(const Spec& spec, const protocols::Protocol& protocol, sim::ManipulatorSimulator& simulator,
                          const std::string& out, double checkpoint_s, bool quiet, std::size_t done, io::Dataset& data) {
  const std::size_t block = std::max<std::size_t>(1, static_cast<std::size_t>(600.0 * spec.rate_hz));
  using clock = std::chrono::steady_clock;
  const auto t_start = clock::now();
  auto t_checkpoint = t_start;
  auto t_progress = t_start;
  const std::size_t done_at_start = done;
  while (done < spec.samples && !g_stop) {
    const std::size_t end = std::min(spec.samples, done + block);
    io::Dataset part = simulate_block(simulator, protocol.program(done, end));
    if (data.empty())
      data = std::move(part);
    else
      data.append(part);
    done = end;
    const auto now = clock::now();
    if (!quiet && (now - t_progress > std::chrono::seconds(2) || done == spec.samples)) {
      const double el = std::chrono::duration<double>(now - t_start).count();
      const double per_s = (done - done_at_start) / std::max(el, 1e-9);
      std::fprintf(stderr, "record: %5.1f %%  %zu / %zu samples  ETA %.1f s\n", 100.0 * done / spec.samples, done,
                   spec.samples, (spec.samples - done) / std::max(per_s, 1e-9));
      t_progress = now;
    }
    if (done < spec.samples && std::chrono::duration<double>(now - t_checkpoint).count() >= checkpoint_s) {
      write_checkpoint(out, data, spec, false);
      t_checkpoint = now;
    }
  }
  return done;
}

int run(int argc, char** argv) {
  Args args("record",
            "Run a data-collection protocol against the simulator at full speed and write the data (bag or CSV),\n"
            "then print the recording summary (samples, duration, gaps; encoder noise sigma for `noise`).\n"
            "Ctrl-C stops after the current block and leaves a valid file; --resume continues it exactly\n"
            "(the simulator is replayed deterministically up to the last recorded sample).\n"
            "Protocols: noise, random_walk, sweep, creep, plan, sawtooth (parameters: config/protocols.yaml).");
  args.option("protocol", "NAME", "protocol to run (taken from FILE.record.yaml with --resume)")
      .option("duration", "T", "record only the first T of the protocol (30, 30s, 90min, 26h)")
      .option("seed", "N", "seed of protocol and simulator", "1")
      .option("effect", "NAME", "switch on an extra simulator effect", "", true)
      .option("params", "FILE.yaml", "protocol parameter overrides (a map, or a map keyed by protocol name)")
      .option("set", "KEY=VALUE", "one protocol parameter override (YAML value)", "", true)
      .option("rate", "HZ", "sample rate [Hz] (default: the simulator's encoder rate)")
      .option("simulator-config", "FILE.yaml", "simulator parameters (default: config/simulator.yaml)")
      .required("out", "FILE.bag|FILE.csv", "output data file")
      .option("resume", "", "continue an interrupted recording in --out")
      .option("force", "", "overwrite an existing --out")
      .option("checkpoint", "T", "rewrite the output at least every T of wall time (60, 5min)", "60")
      .option("quiet", "", "no progress lines");
  if (!args.parse(argc, argv)) return 0;
  const std::string out = args.str("out");
  const std::string sidecar = out + ".record.yaml";

  io::Dataset data;
  const bool resuming = args.flag("resume") && fs::exists(out);
  Spec spec = resuming ? resumed_spec(args, out, sidecar, data) : new_spec(args, out);
  sim::SimulatorConfig cfg;
  try {
    cfg = simulator_config(spec);
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("record: ") + e.what());
  }
  if (!resuming) spec.rate_hz = args.has("rate") ? args.num("rate") : cfg.sample_rate_hz;
  if (!(spec.rate_hz > 0.0) || !std::isfinite(spec.rate_hz))
    throw UsageError("record: --rate must be a positive number of Hz");
  std::unique_ptr<protocols::Protocol> protocol;
  try {
    protocol = protocols::make_protocol(spec.protocol, spec.params, spec.rate_hz, spec.seed);
  } catch (const std::invalid_argument& e) {
    throw UsageError(std::string("record: ") + e.what());
  }
  if (!resuming) complete_new_spec(args, *protocol, spec);
  if (spec.samples < 2) throw UsageError("record: fewer than 2 samples to record");
  if (spec.samples > protocol->size())
    throw io::DataError(sidecar + ": asks for " + std::to_string(spec.samples) + " samples but protocol '" +
                        spec.protocol + "' has " + std::to_string(protocol->size()));

  sim::ManipulatorSimulator simulator(cfg, spec.seed);
  const std::size_t done_at_start = resuming ? replay_recorded(spec, *protocol, out, data, simulator) : 0;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  const auto t_start = std::chrono::steady_clock::now();
  const std::size_t done = record_blocks(spec, *protocol, simulator, out, args.seconds("checkpoint"),
                                         args.flag("quiet"), done_at_start, data);
  data.source = out;
  if (done > done_at_start || !resuming) write_checkpoint(out, data, spec, done == spec.samples);
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();

  const io::Dataset program = protocol->program(0, data.size());
  const auto summary = analysis::summarize(data, spec.protocol, &program, 1e-6);
  std::cout << format_summary(summary);
  std::cout << "  written: " << out << " (" << (done - done_at_start) << " new samples in " << wall_s << " s)\n";
  if (done < spec.samples) {
    std::cerr << "record: interrupted at sample " << done << " of " << spec.samples << "; " << out
              << " is valid, continue with --resume\n";
    return 130;
  }
  return 0;
}

const Register reg("record", "run a data-collection protocol against the simulator into a bag/CSV (resumable)", run);

}  // namespace
}  // namespace piezo::cli
