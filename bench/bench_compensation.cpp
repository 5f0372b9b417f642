// Compensation speed: the 30-min drift forecast (19,800 steps at 11 Hz, target ≤ 20 ms) and one inverse,
// on the package's fitted `linear` kind (fitted here on data from the test PI + creep plant) and on the
// small test models.
#include <benchmark/benchmark.h>

#include <cmath>

#include "../test/unit/test_compensation_models.h"
#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/compensation/inverse.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/models/start_state.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/training/fitters.h"

using namespace piezo;

namespace {

// A random-walk excitation of the PI + creep test plant, as training data for the linear kind.
io::Dataset plant_data(std::size_t n) {
  auto plant = test::make_pi_creep(11.0);
  plant->reset(0.0, 0.0);
  io::Dataset d;
  auto& ax = d.add_axis("c");
  std::uint64_t s = 12345;
  double v = 0.0;
  for (std::size_t i = 0; i < n; ++i) {
    s = s * 6364136223846793005ull + 1442695040888963407ull;
    v = std::clamp(v + ((s >> 33) % 2001 / 1000.0 - 1.0) * 4.0, -80.0, 80.0);
    const models::ModelInput in{v, nullptr};
    const double x = plant->predict(in);
    plant->commit(in, x);
    d.time_s.push_back(static_cast<double>(i) / 11.0);
    ax.voltage_v.push_back(v);
    ax.position_nm.push_back(x);
  }
  return d;
}

models::ModelPtr fitted_linear() {
  static const io::Dataset train = plant_data(6000), val = plant_data(2000);
  for (const auto& k : models::model_kind_names())
    if (k == "linear" && training::fitter("linear")) {
      training::FitRequest req;
      req.train = &train;
      req.validation = &val;
      req.axis = "c";
      models::ModelPtr m = training::fit_model("linear", req);
      m->reset(0.0, 0.0);
      return m;
    }
  return nullptr;
}

void forecast(benchmark::State& state, models::Model& m) {
  for (auto _ : state) {
    auto f = compensation::forecast_drift(m, 20.0, {1.0, 60.0, 1800.0}, 11.0);
    if (!f.ok) state.SkipWithError(f.error.c_str());
    benchmark::DoNotOptimize(f.drift_nm.data());
  }
  state.counters["steps"] = 19800;
}

void BM_DriftForecast30min_Linear(benchmark::State& state) {
  auto m = fitted_linear();
  if (!m) {
    state.SkipWithError("model kind 'linear' is not available in this build");
    return;
  }
  forecast(state, *m);
}
BENCHMARK(BM_DriftForecast30min_Linear)->Unit(benchmark::kMillisecond);

void BM_DriftForecast30min_TestLinearCreep(benchmark::State& state) {
  test::LinearCreepModel m(12.0, 2.0, 300.0, 11.0);
  m.reset(0.0, 0.0);
  forecast(state, m);
}
BENCHMARK(BM_DriftForecast30min_TestLinearCreep)->Unit(benchmark::kMillisecond);

void BM_DriftForecast30min_TestPiCreep(benchmark::State& state) {
  auto m = test::make_pi_creep();
  m->reset(0.0, 0.0);
  forecast(state, *m);
}
BENCHMARK(BM_DriftForecast30min_TestPiCreep)->Unit(benchmark::kMillisecond);

void BM_Inverse_Linear(benchmark::State& state) {
  auto m = fitted_linear();
  if (!m) {
    state.SkipWithError("model kind 'linear' is not available in this build");
    return;
  }
  double t = 0.0;
  for (auto _ : state) {
    auto r = compensation::invert(*m, t, {});
    benchmark::DoNotOptimize(r.voltage_v);
    t = t > 400.0 ? -400.0 : t + 7.0;
  }
}
BENCHMARK(BM_Inverse_Linear)->Unit(benchmark::kMicrosecond);

void BM_Inverse_TestPiCreep(benchmark::State& state) {
  auto m = test::make_pi_creep();
  m->reset(0.0, 0.0);
  double t = 0.0;
  for (auto _ : state) {
    auto r = compensation::invert(*m, t, {});
    benchmark::DoNotOptimize(r.voltage_v);
    t = t > 400.0 ? -400.0 : t + 7.0;
  }
}
BENCHMARK(BM_Inverse_TestPiCreep)->Unit(benchmark::kMicrosecond);

// The estimator's cost per encoder sample: one filter step, and one whole compensator sample + command
// with the estimator and the hold trim active on the shipped foreign-stage model (Preisach + Prony creep).
void BM_ErrorFilterStep(benchmark::State& state) {
  estimation::NoiseModel nm;
  nm.reading_sigma_nm = 20.8;
  nm.q_rest_nm2_per_s = 0.01;
  nm.q_motion_nm = 0.08;
  nm.q_fast_nm = 0.02;
  nm.initial_sigma_nm = 200;
  estimation::ErrorFilter f(nm, 1.0 / 11.0);
  double p = 0.0, y = 3.0;
  for (auto _ : state) {
    p += 0.01;
    y = -y;
    f.step(p, p + y, true);
    benchmark::DoNotOptimize(f.fused_nm());
  }
}
BENCHMARK(BM_ErrorFilterStep)->Unit(benchmark::kNanosecond);

void BM_CompensatorSampleWithTrim_ForeignModel(benchmark::State& state) {
  models::ModelPtr m = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_foreign_c.yaml");
  compensation::AxisCompensatorConfig cfg;
  cfg.hold_trim.settle_s = 0.0;
  compensation::AxisCompensator c(std::move(m), compensation::IdealLine{12.5, 0.0}, cfg);
  c.on_sample(0.0, 0.0, true);
  c.set_intended_position_nm(300.0);
  double v = 0.0, y = 5.0;
  for (auto _ : state) {
    y = -y;
    c.on_sample(v, 300.0 + y, true);
    v = c.command(true).send_v;
  }
  state.counters["trim_nm"] = c.hold_trim().trim_nm();
}
BENCHMARK(BM_CompensatorSampleWithTrim_ForeignModel)->Unit(benchmark::kMicrosecond);

// The start-up state estimate (models/start_state.h) the compensator runs once, inline, when its window is full
// (the predictor's ~start_estimate_s): the shipped foreign-stage model (Preisach + Prony creep, 10 creep states) on
// that stage's recording (seed 202) cut 20 min in, mid-motion, with a window of 30 s and 300 s at 11 Hz. Every
// candidate history is streamed through the window; the counter gives how many.
void BM_StartEstimate_ForeignModel(benchmark::State& state) {
  static const models::ModelPtr m =
      models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_foreign_c.yaml");
  static const io::Dataset rec = [] {
    const io::Dataset d = sim::simulate_stage(
        sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_foreign_hold_stage.yaml"), 202, 1800.0);
    return d.slice(1200 * 11, d.size());
  }();
  models::StartOptions o;
  o.window_s = static_cast<double>(state.range(0));
  o.voltage_min_v = -80.0;
  o.voltage_max_v = 80.0;
  std::size_t candidates = 0;
  for (auto _ : state) {
    const models::StartEstimate e = models::estimate_start(*m, rec, "c", o);
    candidates = e.candidates;
    benchmark::DoNotOptimize(e.offset_nm);
  }
  state.counters["candidates"] = static_cast<double>(candidates);
}
BENCHMARK(BM_StartEstimate_ForeignModel)->Arg(30)->Arg(300)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
