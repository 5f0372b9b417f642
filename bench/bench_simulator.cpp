// Simulator throughput: the target is ≥ 1,000,000 samples/s per axis on one core, i.e. the study's
// 26 h of 11 Hz data in about a second. items_per_second below counts axis-samples.
#include <benchmark/benchmark.h>

#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

using namespace piezo;

namespace {

const io::Dataset& program() {  // 1 h of three-axis random walk (39,600 samples)
  static const io::Dataset p =
      protocols::make_protocol("random_walk", YAML::Load("{duration_s: 3600}"), 11.0, 1)->program();
  return p;
}

void BM_SimulatorRun(benchmark::State& state, bool all_effects) {
  auto cfg = sim::default_simulator_config();
  if (all_effects)
    for (const auto& e : sim::effect_names()) sim::enable_effect(cfg, e);
  const io::Dataset& p = program();
  for (auto _ : state) {
    sim::ManipulatorSimulator s(cfg, 1);
    io::Dataset d = s.run(p);
    benchmark::DoNotOptimize(d.axes[2].position_nm.data());
  }
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(p.size()) * 3);
  state.counters["axis_samples_per_s"] =
      benchmark::Counter(static_cast<double>(state.iterations()) * p.size() * 3, benchmark::Counter::kIsRate);
}
BENCHMARK_CAPTURE(BM_SimulatorRun, default_physics, false)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_SimulatorRun, all_effects_on, true)->Unit(benchmark::kMillisecond);

void BM_SimulatorStep(benchmark::State& state) {
  sim::ManipulatorSimulator s(sim::default_simulator_config(), 1);
  double v = 0.0;
  for (auto _ : state) {
    v = v > 80.0 ? -80.0 : v + 0.37;
    benchmark::DoNotOptimize(s.step({v, -v, 0.5 * v}, 1.0 / 11.0));
  }
  state.SetItemsProcessed(state.iterations() * 3);
}
BENCHMARK(BM_SimulatorStep);

void BM_ProtocolPlan(benchmark::State& state) {  // building the full 41 h plan
  for (auto _ : state) {
    auto p = protocols::make_protocol("plan", YAML::Node(), 11.0, 1);
    benchmark::DoNotOptimize(p->size());
  }
}
BENCHMARK(BM_ProtocolPlan)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
