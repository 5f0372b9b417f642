// The estimator's cost per encoder sample per axis (docs/estimation.md): the error filter's step with the quantised
// reading model on a coarse axis (250 nm steps, σ 21 nm: a walk with crossings, then a hold that flickers) and on a
// dithered one (20 nm steps, σ 20 nm), the moment-matched update alone, and one whole compensator sample + command
// on the shipped coarse-stage model (Preisach + Prony creep) with the estimator and the hold trim active. The
// filter's state is a fixed-size object: its size is the `state_bytes` counter.
#include <benchmark/benchmark.h>

#include <cmath>
#include <random>
#include <vector>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/estimation/quantised_reading.h"
#include "piezo_compensation/models/model_file.h"

using namespace piezo;

namespace {

struct Readings {
  std::vector<double> p, y;
};

// 2^16 samples: a 3-min walk of ±3 µm (a new target every 4 s), then a hold, readings quantised to step_nm.
const Readings& readings(double step_nm) {
  static std::vector<std::pair<double, Readings>> cache;
  for (const auto& [q, r] : cache)
    if (q == step_nm) return r;
  std::mt19937 rng(7);
  std::normal_distribution<double> g(0.0, 21.0);
  std::uniform_real_distribution<double> u(-3000.0, 3000.0);
  Readings r;
  double x = 0.0, target = 0.0;
  for (std::size_t i = 0; i < (1u << 16); ++i) {
    if (i < 2000 && i % 44 == 0) target = u(rng);
    x += std::clamp(target - x, -300.0, 300.0);
    r.p.push_back(x - 40.0);
    const double noisy = x + g(rng);
    r.y.push_back(step_nm > 0 ? step_nm * std::nearbyint(noisy / step_nm) : noisy);
  }
  cache.emplace_back(step_nm, std::move(r));
  return cache.back().second;
}

void filter_steps(benchmark::State& state, double step_nm, double sigma_nm) {
  estimation::NoiseModel nm;
  nm.step_nm = step_nm;
  nm.noise_sigma_nm = sigma_nm;
  nm.reading_sigma_nm = std::sqrt(sigma_nm * sigma_nm + step_nm * step_nm / 12.0);
  nm.q_rest_nm2_per_s = 0.2;
  nm.q_motion_nm = 0.3;
  nm.q_fast_nm = 0.05;
  nm.initial_sigma_nm = 300.0;
  estimation::ErrorFilter f(nm, 1.0 / 11.0);
  const Readings& r = readings(step_nm);
  std::size_t i = 0;
  for (auto _ : state) {
    f.step(r.p[i], r.y[i], true);
    benchmark::DoNotOptimize(f.fused_nm());
    if (++i == r.p.size()) i = 0;
  }
  state.counters["state_bytes"] = static_cast<double>(sizeof(estimation::ErrorFilter));
  state.counters["sigma_nm"] = f.sigma_nm();
}

void BM_FilterStep_Coarse250nm(benchmark::State& state) { filter_steps(state, 250.0, 21.0); }
BENCHMARK(BM_FilterStep_Coarse250nm)->Unit(benchmark::kMicrosecond);

void BM_FilterStep_Dithered20nm(benchmark::State& state) { filter_steps(state, 20.0, 20.0); }
BENCHMARK(BM_FilterStep_Dithered20nm)->Unit(benchmark::kMicrosecond);

void BM_QuantisedUpdate(benchmark::State& state) {
  double m = 0.0;
  for (auto _ : state) {
    m = 0.999 * m + 1.0;  // the prior mean wanders across the cell and out of it
    const estimation::ReadingUpdate u = estimation::quantised_update(m, 400.0, 250.0, 21.0, 250.0);
    benchmark::DoNotOptimize(u.mean_nm);
  }
}
BENCHMARK(BM_QuantisedUpdate)->Unit(benchmark::kMicrosecond);

// One axis' whole sample on the shipped coarse-stage model: model step, filter, hold trim, inverse.
void BM_CompensatorSample_CoarseModel(benchmark::State& state) {
  models::ModelPtr m = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_coarse_a.yaml");
  compensation::AxisCompensatorConfig cfg;
  cfg.hold_trim.settle_s = 0.0;
  compensation::AxisCompensator c(std::move(m), compensation::IdealLine{125.0, 0.0}, cfg);
  c.on_sample(0.0, 0.0, true);
  c.set_intended_position_nm(3000.0);
  double v = 0.0;
  std::size_t k = 0;
  for (auto _ : state) {
    const double y = ((++k / 7) % 2) ? 3000.0 : 3250.0;  // flicker between two levels
    c.on_sample(v, y, true);
    v = c.command(true).send_v;
  }
  state.counters["trim_nm"] = c.hold_trim().trim_nm();
}
BENCHMARK(BM_CompensatorSample_CoarseModel)->Unit(benchmark::kMicrosecond);

}  // namespace

BENCHMARK_MAIN();
