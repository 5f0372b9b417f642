// The residual loop's acceptance rules, the paired block test and the step finder on hand-made scores and
// vectors: each rule's pass and refusal in milliseconds, without a simulation.
#include <gtest/gtest.h>

#include <random>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/analysis/residual/residual_acceptance.h"
#include "piezo_compensation/analysis/residual/residual_families.h"
#include "piezo_compensation/training/fit_common.h"

namespace pa = piezo::analysis;

namespace {

// A significant family that removes 30 % of the systematic error (5 nm), clearly better, no worse in a half.
pa::FamilyScore good(const std::string& family, const std::string& signal = "") {
  pa::FamilyScore s;
  s.family = family;
  s.p_value = 1e-10;
  s.explained_variance = 0.2;
  s.significant = true;
  s.validation_gain = 0.012;  // ≈ 1 % of MAE: what a real 5 nm effect shows under 21 nm noise
  s.validation_gain_halves = {0.01, 0.014};
  s.removed_fraction = 0.3;
  s.removed_nm = 5.0;
  s.clearly_better = true;
  s.block_mae = {16.0, 16.2, 15.9, 16.1, 16.0, 16.3};
  if (!signal.empty()) s.best.labels["signal"] = signal;
  return s;
}

pa::AcceptanceRound round_of() {
  pa::AcceptanceRound r;
  r.block_noise_nm = 1.2;  // 21 nm over 30 s at 11 Hz
  r.systematic_nm = 9.0;
  r.block_mae = {17.0, 17.2, 16.9, 17.1, 17.0, 17.3};
  return r;
}

const pa::AcceptanceThresholds kT;

}  // namespace

TEST(ValidationPrefers, ClearlyLowerOverBlocks) {
  std::vector<double> a(1000), b(1000);
  for (std::size_t i = 0; i < a.size(); ++i) a[i] = 10.0 + (i % 7) * 0.1, b[i] = a[i] + 0.5;
  EXPECT_TRUE(piezo::training::validation_prefers(a, b, 100));
  EXPECT_FALSE(piezo::training::validation_prefers(b, a, 100));
}
TEST(ValidationPrefers, NoisyDifferenceIsNotClear) {
  // Lower on average by 0.1 with a block-to-block scatter of ±2: not > 2 SE.
  std::vector<double> a(1000, 10.0), b(1000, 10.0);
  for (std::size_t i = 0; i < a.size(); ++i) b[i] += 0.1 + ((i / 100) % 2 ? 2.0 : -2.0);
  EXPECT_FALSE(piezo::training::validation_prefers(a, b, 100));
}
TEST(ValidationPrefers, UnderFourBlocksTheLowerMeanDecides) {
  std::vector<double> a(250, 10.0), b(250, 10.001);
  EXPECT_TRUE(piezo::training::validation_prefers(a, b, 100));
  EXPECT_FALSE(piezo::training::validation_prefers(b, a, 100));
}
TEST(ResidualAcceptance, BlocksPreferMatchesValidationPrefers) {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int trial = 0; trial < 20; ++trial) {
    std::vector<double> a(800), b(800);
    for (std::size_t i = 0; i < a.size(); ++i) a[i] = 10 + g(rng), b[i] = 10.1 + g(rng);
    std::vector<double> ma(8, 0.0), mb(8, 0.0);
    for (std::size_t i = 0; i < a.size(); ++i) ma[i / 100] += a[i] / 100, mb[i / 100] += b[i] / 100;
    EXPECT_EQ(pa::blocks_prefer(ma, mb), piezo::training::validation_prefers(a, b, 100)) << trial;
  }
}

TEST(ResidualAcceptance, Significance) {
  pa::FamilyScore s = good("aux_signal");
  EXPECT_TRUE(pa::rule_significance(s, kT).pass);
  s.p_value = 0.02;
  EXPECT_FALSE(pa::rule_significance(s, kT).pass);
  s = good("aux_signal");
  s.explained_variance = 0.005;
  EXPECT_FALSE(pa::rule_significance(s, kT).pass);
  s = good("aux_signal");
  s.available = false;
  EXPECT_FALSE(pa::rule_significance(s, kT).pass);
}
// The case: 1 % of MAE, but 30 % of the systematic error and 5 nm, far above a 30-s mean's 1.2 nm.
TEST(ResidualAcceptance, SizeAcceptsARealSmallEffectUnderNoise) {
  const pa::Verdict v = pa::rule_size(good("aux_gain", "temperature_c"), kT, round_of());
  EXPECT_TRUE(v.pass) << v.reason;
}
TEST(ResidualAcceptance, SizeRefusesASmallShareOrWhatTheNoiseHides) {
  pa::FamilyScore s = good("aux_signal");
  s.removed_fraction = 0.05;
  EXPECT_FALSE(pa::rule_size(s, kT, round_of()).pass);
  s = good("aux_signal");
  s.removed_nm = 1.0;  // below one 30-s mean's noise
  const pa::Verdict v = pa::rule_size(s, kT, round_of());
  EXPECT_FALSE(v.pass);
  EXPECT_EQ(v.rule, pa::AcceptanceRule::kSize);
}
TEST(ResidualAcceptance, LinesInTimeNeedALargerShare) {
  pa::FamilyScore s = good("time_drift");
  s.removed_fraction = 0.4;
  EXPECT_FALSE(pa::rule_size(s, kT, round_of()).pass);
  s.removed_fraction = 0.7;
  EXPECT_TRUE(pa::rule_size(s, kT, round_of()).pass);
}
TEST(ResidualAcceptance, ClearlyBetterUnlessLarge) {
  pa::FamilyScore s = good("aux_signal");
  s.removed_fraction = 0.15;
  EXPECT_TRUE(pa::rule_clearly_better(s, kT).pass);
  s.clearly_better = false;
  EXPECT_FALSE(pa::rule_clearly_better(s, kT).pass);
  s.removed_fraction = 0.5;  // large enough to be its own evidence
  EXPECT_TRUE(pa::rule_clearly_better(s, kT).pass);
}
TEST(ResidualAcceptance, HoldGuard) {
  pa::FamilyScore s = good("aux_signal");
  pa::AcceptanceRound r = round_of();
  s.hold_validation_gain = -0.01;
  EXPECT_TRUE(pa::rule_hold_guard(s, kT, r).pass) << "no holds in the validation part";
  r.validation_has_holds = true;
  EXPECT_FALSE(pa::rule_hold_guard(s, kT, r).pass);
  s.hold_validation_gain = -0.004;
  EXPECT_TRUE(pa::rule_hold_guard(s, kT, r).pass);
}
TEST(ResidualAcceptance, HalvesRefuseALineInTimeThatLosesAHalf) {
  pa::FamilyScore s = good("time_drift");
  s.validation_gain_halves = {0.05, -0.001};
  EXPECT_FALSE(pa::rule_halves(s, kT).pass);
  // Another family loses a half within its noise: kept; clearly worse there: refused.
  s.family = "cross_axis_gain";
  EXPECT_TRUE(pa::rule_halves(s, kT).pass);
  s.half_clearly_worse = true;
  EXPECT_FALSE(pa::rule_halves(s, kT).pass);
}
TEST(ResidualAcceptance, GainMustClearlyBeatTheAdditiveOnTheSameSignal) {
  pa::FamilyScore gain = good("aux_gain", "temperature_c"), add = good("aux_signal", "temperature_c");
  add.removed_nm = 4.0, add.block_mae = {16.5, 16.7, 16.4, 16.6, 16.5, 16.8};
  EXPECT_TRUE(pa::rule_gain_vs_additive(gain, add, kT).pass);  // 25 vs 16 nm², clearly lower blocks
  add.removed_nm = 4.9;                                        // 25 < 1.2 × 24 nm²
  EXPECT_FALSE(pa::rule_gain_vs_additive(gain, add, kT).pass);
  add.removed_nm = 4.0, add.block_mae = gain.block_mae;        // no paired difference
  EXPECT_FALSE(pa::rule_gain_vs_additive(gain, add, kT).pass);
}
TEST(ResidualAcceptance, OperatingPointMustWinByTheMargin) {
  pa::FamilyScore op = good("voltage_nonlinearity"), phys = good("aux_signal", "temperature_c");
  op.removed_nm = 5.5;  // 30 nm² < 1.5 × 25 nm²
  op.block_mae = {15.0, 15.2, 14.9, 15.1, 15.0, 15.3};
  EXPECT_FALSE(pa::rule_operating_point(op, phys, kT).pass);
  op.removed_nm = 6.5;  // 42 nm²
  EXPECT_TRUE(pa::rule_operating_point(op, phys, kT).pass);
}
TEST(ResidualAcceptance, ChooseEffectKeepsTheBestAndReportsTheCompetitors) {
  std::vector<pa::FamilyScore> ranking = {good("aux_signal", "temperature_c"), good("aux_gain", "temperature_c"),
                                          good("voltage_nonlinearity"), good("time_drift")};
  ranking[0].removed_nm = 4.0, ranking[0].removed_fraction = 0.2;
  ranking[0].block_mae = {16.5, 16.7, 16.4, 16.6, 16.5, 16.8};
  ranking[2].removed_nm = 5.2, ranking[2].removed_fraction = 0.32;  // not 1.5 × the gain's
  ranking[3].removed_fraction = 0.1;                                // a line in time, too small
  std::vector<pa::FamilyScore> competitors;
  const int w = pa::choose_effect(ranking, kT, round_of(), &competitors);
  ASSERT_EQ(w, 1);
  EXPECT_EQ(ranking[1].verdict, "kept");
  EXPECT_NE(ranking[2].verdict.find("operating point"), std::string::npos) << ranking[2].verdict;
  EXPECT_NE(ranking[3].verdict.find("size"), std::string::npos) << ranking[3].verdict;
  EXPECT_EQ(competitors.size(), 2u);  // aux_signal and voltage_nonlinearity passed their own rules
}
TEST(ResidualAcceptance, NothingPassesNothingChosen) {
  std::vector<pa::FamilyScore> ranking = {good("aux_signal")};
  ranking[0].clearly_better = false;
  ranking[0].removed_fraction = 0.2;
  EXPECT_EQ(pa::choose_effect(ranking, kT, round_of()), -1);
  EXPECT_NE(ranking[0].verdict.find("clearly better"), std::string::npos);
}

TEST(ResidualFamilies, TableTraits) {
  EXPECT_EQ(pa::family_table().size(), pa::residual_family_names().size());
  EXPECT_TRUE(pa::is_gain_family("aux_gain"));
  EXPECT_EQ(pa::additive_counterpart("cross_axis_gain"), "cross_axis");
  EXPECT_EQ(pa::additive_counterpart("aux_signal"), "");
  EXPECT_TRUE(pa::extrapolates_in_time("time_gain"));
  EXPECT_TRUE(pa::is_operating_point_family("missing_memory"));
  EXPECT_FALSE(pa::is_operating_point_family("periodic_disturbance"));
  EXPECT_THROW(pa::traits_of("nonsense"), std::invalid_argument);
  for (const auto& t : pa::family_table()) EXPECT_EQ(&pa::traits_of(t.name), &pa::traits(t.id));
}

TEST(ResidualSteps, FindsTwoStepsInNoise) {
  const double fs = 11.0;
  const std::size_t n = static_cast<std::size_t>(7200 * fs), B = 330;
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 21.0);
  std::vector<double> r(n), t(n);
  for (std::size_t i = 0; i < n; ++i) {
    t[i] = 1000.0 + static_cast<double>(i) / fs;
    r[i] = g(rng) + (t[i] >= 2500.0 ? 60.0 : 0.0) + (t[i] >= 6000.0 ? -40.0 : 0.0);
  }
  std::vector<double> bm;
  std::vector<std::size_t> first;
  for (std::size_t b = 0; b + B <= n; b += B) {
    double s = 0;
    for (std::size_t i = b; i < b + B; ++i) s += r[i];
    bm.push_back(s / B);
    first.push_back(b);
  }
  const auto steps = pa::find_steps(r, {}, t, bm, first, B, 21.0, 6.0, 5);
  ASSERT_EQ(steps.size(), 2u);
  EXPECT_NEAR(steps[0].time_s, 2500.0, 30.0);
  EXPECT_NEAR(steps[0].size_nm, 60.0, 6.0);
  EXPECT_NEAR(steps[1].time_s, 6000.0, 30.0);
  EXPECT_NEAR(steps[1].size_nm, -40.0, 6.0);
}
TEST(ResidualSteps, NoStepInNoiseOrASlowRamp) {
  const double fs = 11.0;
  const std::size_t n = static_cast<std::size_t>(7200 * fs), B = 330;
  std::mt19937_64 rng(6);
  std::normal_distribution<double> g(0.0, 21.0);
  std::vector<double> r(n), t(n), bm;
  std::vector<std::size_t> first;
  for (std::size_t i = 0; i < n; ++i) t[i] = static_cast<double>(i) / fs, r[i] = g(rng) + 20.0 * std::sin(t[i] / 1200.0);
  for (std::size_t b = 0; b + B <= n; b += B) {
    double s = 0;
    for (std::size_t i = b; i < b + B; ++i) s += r[i];
    bm.push_back(s / B);
    first.push_back(b);
  }
  EXPECT_TRUE(pa::find_steps(r, {}, t, bm, first, B, 21.0, 6.0, 5).empty());
}
