// The residual loop's validator on hand-made data: how far a low-pass time constant may be refined. In
// milliseconds, without a simulation.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>

#include "piezo_compensation/analysis/residual/residual_context.h"
#include "piezo_compensation/analysis/residual/residual_validation.h"

namespace pd = piezo::analysis::detail;

namespace {

// 1 Hz, a random-walk voltage on axis c; the residual is 5 nm/V × lowpass(V, 400 s) (memory the base lacks)
// plus white noise σ 1 nm; with switch_at > 0, lowpass(V, 100 s) before that row and lowpass(V, 400 s) after.
struct Slow {
  piezo::io::Dataset data;
  pd::Context c;
  explicit Slow(std::size_t n, std::size_t switch_at = 0) {
    std::mt19937_64 rng(3);
    std::normal_distribution<double> g(0.0, 1.0);
    data.time_s.resize(n);
    data.add_axis("c");
    auto& ax = data.axis("c");
    ax.voltage_v.resize(n);
    ax.position_nm.resize(n);
    const double a = std::exp(-1.0 / 400.0), a100 = std::exp(-1.0 / 100.0);
    double v = 0.0, lp = 0.0, lp100 = 0.0;
    for (std::size_t i = 0; i < n; ++i) {
      data.time_s[i] = static_cast<double>(i);
      v = std::clamp(v + 2.0 * g(rng), -80.0, 80.0);
      lp = a * lp + (1 - a) * v;
      lp100 = a100 * lp100 + (1 - a100) * v;
      ax.voltage_v[i] = v;
      ax.position_nm[i] = 5.0 * (i < switch_at ? lp100 : lp) + g(rng);
    }
    c.data = &data;
    c.axis = "c";
    c.fs = 1.0;
    c.voltage = ax.voltage_v;
    c.measured = ax.position_nm;
    c.x_base.assign(n, 0.0);
    c.noise_sigma_nm = 1.0;
  }
  // The missing-memory low-pass as the grid chose it (100 s), refined by the validator's score.
  double refined_tau(std::size_t n_fit, bool finalise = false) const {
    const piezo::analysis::AcceptanceThresholds t;
    const pd::Validator v(c, n_fit, t, nullptr);
    piezo::analysis::FamilyScore s;
    s.family = "missing_memory";
    s.best.terms = {pd::make_term("missing_memory", "linear", piezo::models::kSignalVoltage, 0.0, 100.0)};
    v.score(s, {}, v.validate({}), false);
    if (finalise) v.finalise_time_constants(s, {});
    return s.best.terms[0].time_constant_s;
  }
};

}  // namespace

// With a validation part of 2000 s the refinement finds the 400-s memory (4 × the grid's 100 s).
TEST(ResidualValidation, ATimeConstantTheValidationSeesIsRefined) {
  const Slow d(8000);
  EXPECT_NEAR(d.refined_tau(6000), 400.0, 60.0);
  EXPECT_NEAR(d.refined_tau(6000, true), 400.0, 60.0);
}

// With 300 s of validation the refinement stops at half of it (150 s): a longer τ is one the validation rows
// cannot judge. Refined again over all rows for the model, it stays there.
TEST(ResidualValidation, RefinementStopsAtHalfTheValidationPart) {
  const Slow d(1200);
  const double tau = d.refined_tau(900);
  EXPECT_GT(tau, 100.0);
  EXPECT_LE(tau, 150.0 + 1e-9);
  EXPECT_LE(d.refined_tau(900, true), 150.0 + 1e-9);
}

// Under a 200-s validation part nothing longer than the grid's choice is tried (shorter ones still are, down to a
// quarter of it: the 400-s truth keeps it at 100 s).
TEST(ResidualValidation, AGridChoiceLongerThanTheValidationCanSeeIsNotRefinedUpwards) {
  const Slow d(400);
  EXPECT_NEAR(d.refined_tau(300), 100.0, 1e-9);
}

// Over all of TRAIN the accepted effect's τ moves towards what the validation rows add, but within √2 of the
// validated τ: the fit part has a 100-s memory, the validation part a 400-s one. The decision (fit part) finds
// ~100 s; refined over all rows it would go further, and stops at √2 × that.
TEST(ResidualValidation, TheAcceptedTimeConstantMovesAtMostRootTwoOverAllOfTrain) {
  const Slow d(8000, 6000);
  const double decided = d.refined_tau(6000), final_tau = d.refined_tau(6000, true);
  EXPECT_NEAR(decided, 100.0, 25.0);
  EXPECT_GT(final_tau, 1.05 * decided);
  EXPECT_LE(final_tau, std::sqrt(2.0) * decided * (1 + 1e-9));
}

// The grid itself: with a cap (Context::max_time_constant_s, half the validation part, set by the loop) no variant
// of missing_memory's grid (10 … 3000 s) has a longer time constant, and the best one is chosen among the rest; with
// none over the cap the family is unavailable with the reason.
TEST(ResidualValidation, NoGridVariantHasATimeConstantTheValidationCannotJudge) {
  Slow d(1200);
  const std::vector<double> residual = d.c.measured, position = d.c.measured;
  piezo::analysis::ResidualOptions o;
  o.permutations = 0;
  std::mt19937_64 rng(1);
  const pd::Level level;
  const auto full = pd::score_family(piezo::analysis::Family::kMissingMemory, d.c, {}, level, residual, position, o, rng);
  d.c.max_time_constant_s = 150.0;
  const auto capped = pd::score_family(piezo::analysis::Family::kMissingMemory, d.c, {}, level, residual, position, o, rng);
  ASSERT_TRUE(capped.available);
  EXPECT_LT(capped.variants, full.variants);
  for (const auto& t : capped.best.terms) EXPECT_LE(t.time_constant_s, 150.0);
  d.c.max_time_constant_s = 5.0;  // under the grid's shortest (10 s)
  const auto none = pd::score_family(piezo::analysis::Family::kMissingMemory, d.c, {}, level, residual, position, o, rng);
  EXPECT_FALSE(none.available);
  EXPECT_NE(none.note.find("longer than half the validation part"), std::string::npos) << none.note;
}
