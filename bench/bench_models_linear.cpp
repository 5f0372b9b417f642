// Linear-model inference per sample (target ≤ 0.5 µs) and the lasso path with CV on ~1 M samples (target ≤ 10 s).
#include <benchmark/benchmark.h>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/lasso.h"
#include "../test/unit/test_models_data.h"

using namespace piezo;

namespace {
void inference(benchmark::State& state, const features::FeatureSpec& spec) {
  features::FeatureSpec s = spec;
  s.mean.assign(s.size(), 0.1);
  s.scale.assign(s.size(), 2.0);
  models::LinearModel m(s, 11.0, Eigen::VectorXd::Constant(s.size(), 0.01), 1.0);
  const auto v = testdata::random_walk_v(1 << 16, 1);
  m.reset(v[0], 0);
  std::size_t i = 0;
  for (auto _ : state) {
    const models::ModelInput in{v[i & 0xffff], nullptr};
    const double y = m.predict(in);
    m.commit(in, y);
    benchmark::DoNotOptimize(y);
    ++i;
  }
  state.SetItemsProcessed(state.iterations());
}
void BM_LinearStepStudyFeatures(benchmark::State& s) { inference(s, features::study_features()); }
void BM_LinearStepCandidateFeatures(benchmark::State& s) { inference(s, features::candidate_features()); }
BENCHMARK(BM_LinearStepStudyFeatures);
BENCHMARK(BM_LinearStepCandidateFeatures);

void BM_LassoPathCV(benchmark::State& state) {
  const std::size_t n = static_cast<std::size_t>(state.range(0));
  models::CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {30, 1500};
  cp.gains_nm_per_v = {1.0, 0.7};
  models::PiCreepModel gen({0, 10, 20, 30, 40}, {8, 2, 1, 0.6, 0.3}, 0, cp, 11.0);
  const auto v = testdata::random_walk_v(n, 2, 0.0005);
  const io::Dataset d = testdata::make_dataset(gen, v, 11.0, 20.79, 3);
  const features::FeatureSpec cand = features::candidate_features();
  for (auto _ : state) {
    const auto sel = training::run_lasso(cand, d, "c");
    benchmark::DoNotOptimize(sel.path.index_1se);
  }
  state.counters["samples"] = double(n);
  state.counters["features"] = double(cand.size());
}
BENCHMARK(BM_LassoPathCV)->Arg(1000000)->Unit(benchmark::kSecond)->Iterations(1);
}  // namespace

BENCHMARK_MAIN();
