// The estimator on physics it was not identified on (docs/estimation.md, "Physics the identification did not
// see"). A Preisach model with creep is fitted on the coarse development stage's axis a (250 nm encoder steps,
// seed 201, 4 h), its noise model identified there from a cold start 900 s into a walk of another seed (202, 3 h,
// as `piezo track --identify-on` does); then it tracks, from a cold start 900 s into a walk, the foreign coarse
// stage (config/stages/mm3e_coarse_foreign.yaml: a wider loop of another shape, stronger and shifted creep, a 5 %
// longer stroke) against the truth. From 5 min on: fused MAE, worst hold end (30-min holds' last 5 s), and the
// share of rows with the truth within ±2σ. Slow (a fit and an identification: about a minute).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <string>

#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/compensation/track.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/sim/stage.h"

namespace {

using namespace piezo;

const std::string kSrc = PIEZO_SOURCE_DIR;

// The rows from `from_s` on: the recording starts there, the model and the filter cold.
io::Dataset from_time(const io::Dataset& d, double from_s) {
  std::size_t i = 0;
  while (i < d.size() && d.time_s[i] < from_s) ++i;
  return d.slice(i, d.size());
}

TEST(EstimatorOnAForeignStage, SigmaCoversTheTruthFromAColdStart) {
  const sim::StageConfig dev = sim::load_stage(kSrc + "/config/stages/mm3e_coarse_stage.yaml");
  const io::Dataset fit = sim::simulate_stage(dev, 201, 4.0 * 3600.0);
  models::ModelPtr model = analysis::fit_axis_model(fit, fit.size() * 4 / 5, "a", "preisach_creep_prony", 1, false);
  const io::Dataset id = from_time(sim::simulate_stage(dev, 202, 900.0 + 3.0 * 3600.0), 900.0);
  const estimation::NoiseModel nm = analysis::identify_estimator(*model, id, "a");
  ASSERT_TRUE(nm.fuse) << nm.describe();
  model->meta.estimator = nm.to_yaml();
  std::printf("identified on the development stage: %s\n", nm.describe().c_str());

  const sim::StageConfig foreign = sim::load_stage(kSrc + "/config/stages/mm3e_coarse_foreign.yaml");
  const io::Dataset test = from_time(sim::simulate_stage(foreign, 302, 900.0 + 5.5 * 3600.0), 900.0);
  const compensation::TrackResult r = compensation::track_recording(std::move(model), test, "a");
  ASSERT_TRUE(r.fusing) << r.estimator;
  ASSERT_GE(r.holds.size(), 5u);
  for (const auto& h : r.holds)
    std::printf("hold at %.0f s (%.1f V): model MAE %.1f | fused MAE %.2f end %.2f, 1σ %.2f, within 2σ %.1f %%\n",
                h.start_s, h.voltage_v, h.model_mae_nm, h.fused_mae_nm, h.fused_end_nm, h.mean_sigma_nm,
                100.0 * h.within_2sigma);
  std::printf("foreign stage from 5 min: model MAE %.1f nm, fused MAE %.2f nm, worst hold end %.2f nm, truth within "
              "±2σ %.1f %%\n", r.all_model_mae_nm, r.all_fused_mae_nm, r.worst_fused_end_nm, 100.0 * r.all_within_2sigma);
  EXPECT_LE(r.all_fused_mae_nm, 25.0);
  EXPECT_LE(r.worst_fused_end_nm, 40.0);
  // honest: neither over-confident nor so wide that the band says little
  EXPECT_GE(r.all_within_2sigma, 0.90);
  EXPECT_LE(r.all_within_2sigma, 0.97);
}

}  // namespace
