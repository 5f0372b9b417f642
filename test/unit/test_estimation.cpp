// The error filter (estimation/error_filter.h), its identification, the hold trim (compensation/hold_trim.h) and
// the compensator that joins them, on hand-made series with a known truth. Milliseconds to a few seconds.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/hold_trim.h"
#include "piezo_compensation/compensation/track.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "test_compensation_models.h"

namespace {

using piezo::estimation::ErrorFilter;
using piezo::estimation::NoiseModel;

constexpr double kDt = 1.0 / 11.0;

double quantise(double x, double q) { return q > 0 ? q * std::round(x / q) : x; }

// A model prediction that moves in steps with holds, a truth = prediction + slow random walk + a fast error that
// follows each move and settles, and readings of it with noise and a 20 nm step (dithered).
struct Series {
  std::vector<double> p, truth, y;
};
Series make_series(std::size_t n, std::uint32_t seed, double q_rest, double q_motion, double hold_s = 300.0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> u(-400.0, 400.0);
  Series s;
  double p = 0, target = 0, slow = 5.0, fast = 0.0;
  const double phi = std::exp(-kDt / 20.0);
  const std::size_t hold_n = static_cast<std::size_t>(hold_s / kDt);
  for (std::size_t i = 0; i < n; ++i) {
    if (i % hold_n == 0) target = u(rng);
    const double dp = std::clamp(target - p, -40.0, 40.0);  // a move takes a few samples
    p += dp;
    slow += std::sqrt(q_rest * kDt + q_motion * std::abs(dp)) * g(rng);
    fast = phi * fast + std::sqrt(0.5 * std::abs(dp)) * g(rng);
    s.p.push_back(p);
    s.truth.push_back(p + slow + fast);
    s.y.push_back(quantise(p + slow + fast + 20.0 * g(rng), 20.0));
  }
  return s;
}

NoiseModel identified(const Series& s) {
  piezo::estimation::IdentifyOptions o;
  o.dt_s = kDt;
  o.reading_sigma_nm = std::sqrt(400.0 + 400.0 / 12.0);
  o.step_nm = 20.0;
  o.max_evaluations = 200;
  return piezo::estimation::identify_noise_model(s.p, s.y, o);
}

TEST(ErrorFilter, IdentifiesTheVarianceRatesAndIsHonest) {
  const Series train = make_series(40000, 1, 0.02, 0.05);
  const NoiseModel m = identified(train);
  ASSERT_TRUE(m.fuse);
  EXPECT_GT(m.q_rest_nm2_per_s, 0.005);  // true 0.02 nm²/s
  EXPECT_LT(m.q_rest_nm2_per_s, 0.08);
  // on another run of the same process: the truth within ±2σ on ≥ 93 % of samples, and not by a huge σ
  const Series test = make_series(40000, 2, 0.02, 0.05);
  const auto t = piezo::estimation::run_filter(m, kDt, test.p, test.y);
  std::size_t in = 0;
  double sig = 0, err = 0;
  for (std::size_t i = 100; i < test.p.size(); ++i) {
    const double e = std::abs(t.fused_nm[i] - test.truth[i]);
    in += e <= 2.0 * t.sigma_nm[i];
    sig += t.sigma_nm[i], err += e;
  }
  const double n = test.p.size() - 100.0;
  EXPECT_GE(in / n, 0.93);
  EXPECT_LT(sig / n, 6.0);
  EXPECT_LT(err / n, 5.0);  // the readings alone: 20.8 nm
  std::printf("identified: %s; within 2σ %.1f %%, mean σ %.2f nm, MAE %.2f nm\n", m.describe().c_str(),
              100.0 * in / n, sig / n, err / n);
}

TEST(ErrorFilter, ReachesTheAveragingLimitInALongHold) {
  NoiseModel m;
  m.reading_sigma_nm = 21.0;
  m.step_nm = 20.0;
  m.q_rest_nm2_per_s = 1e-6;
  m.initial_sigma_nm = 50.0;
  ErrorFilter f(m, kDt);
  std::mt19937 rng(3);
  std::normal_distribution<double> g(0.0, 21.0);
  const double offset = 12.0;  // the model is 12 nm off and the stage parked
  for (int i = 0; i < 660; ++i) f.step(100.0, quantise(100.0 + offset + g(rng), 20.0), true);
  // one minute of readings at 11 Hz: σ/√N = 21/√660 = 0.82 nm
  EXPECT_NEAR(f.sigma_nm(), 21.0 / std::sqrt(660.0), 0.05);
  EXPECT_NEAR(f.fused_nm(), 112.0, 3.0 * f.sigma_nm());
}

TEST(ErrorFilter, LostReadingsPredictOnlyAndTheCovarianceGrows) {
  NoiseModel m;
  m.reading_sigma_nm = 21.0;
  m.q_rest_nm2_per_s = 0.5;
  m.initial_sigma_nm = 30.0;
  ErrorFilter f(m, kDt);
  for (int i = 0; i < 500; ++i) f.step(0.0, 10.0, true);
  const double before = f.sigma_nm(), est = f.fused_nm();
  double last = before;
  for (int i = 0; i < 100; ++i) {
    f.step(0.0, NAN, false);
    EXPECT_GT(f.sigma_nm(), last);
    last = f.sigma_nm();
  }
  EXPECT_EQ(f.samples_since_reading(), 100u);
  EXPECT_DOUBLE_EQ(f.fused_nm(), est);  // nothing new learnt, nothing forgotten
  f.step(0.0, 10.0, true);
  EXPECT_LT(f.sigma_nm(), last);
  EXPECT_EQ(f.samples_since_reading(), 0u);
}

// The consistency guard: a filter identified on small errors, parked for 10 min, then the model's error jumps by
// 10 nm (a move whose error is larger than any it was identified on). Without the guard the tight covariance
// averages the jump in over many minutes; with it the mean innovation trips the test and the estimate follows.
TEST(ErrorFilter, ConsistencyGuardFollowsAnUnexpectedJump) {
  std::size_t trips = 0;
  double err_after_60s[2];
  for (int guard = 0; guard < 2; ++guard) {
    NoiseModel m;
    m.reading_sigma_nm = 21.0;
    m.q_rest_nm2_per_s = 1e-6;
    m.initial_sigma_nm = 30.0;
    m.adapt_k = guard ? 3.0 : 0.0;
    ErrorFilter f(m, kDt);
    std::mt19937 rng(11);
    std::normal_distribution<double> g(0.0, 21.0);
    for (int i = 0; i < 6600; ++i) f.step(0.0, g(rng), true);
    const std::size_t false_trips = f.adaptations();
    std::printf("guard %d: %zu trips on 10 min of consistent readings\n", guard, false_trips);
    EXPECT_LE(false_trips, 2u);  // each window is tested at every sample, so a false trip is likelier than 1 in 370
    for (int i = 0; i < 660; ++i) f.step(0.0, 10.0 + g(rng), true);
    err_after_60s[guard] = std::abs(f.fused_nm() - 10.0);
    trips = f.adaptations() - false_trips;
  }
  EXPECT_GT(err_after_60s[0], 6.0);  // unguarded: most of the jump still missing after a minute
  EXPECT_LT(err_after_60s[1], 3.0);
  EXPECT_GE(trips, 1u);
}

// A model file identified before the quantised reading model declared a coarse axis model-only (fuse: false, no
// noise σ before the quantiser): it keeps loading, stays model-only (never worse than feedforward) and says so.
TEST(ErrorFilter, AnOldModelOnlyFileLoadsModelOnlyAndSaysToReidentify) {
  const YAML::Node old = YAML::Load(
      "{fuse: false, reading_sigma_nm: 72.168783648703226, step_nm: 250, q_rest_nm2_per_s: 0, q_motion_nm: 0,"
      " q_fast_nm: 0, fast_tau_s: 30, initial_sigma_nm: 122.2, model_sigma_nm: 49.3}");
  const NoiseModel m = NoiseModel::from_yaml(old, "mm3e_sim_a.yaml");
  EXPECT_FALSE(m.fuse);
  EXPECT_NE(m.describe().find("re-identify"), std::string::npos) << m.describe();
  std::vector<double> p(3000), y(3000);
  std::mt19937 rng(4);
  std::normal_distribution<double> g(0.0, 21.0);
  for (std::size_t i = 0; i < p.size(); ++i) p[i] = 1000.0 * std::sin(i / 300.0), y[i] = quantise(p[i] + 30 + g(rng), 250.0);
  const auto t = piezo::estimation::run_filter(m, kDt, p, y);
  for (std::size_t i = 0; i < p.size(); ++i) ASSERT_EQ(t.fused_nm[i], p[i]);
  // and an old fused file (c) gets its σ before the quantiser from its reading σ less the step's rounding
  const NoiseModel c = NoiseModel::from_yaml(
      YAML::Load("{reading_sigma_nm: 20.8, step_nm: 20, q_rest_nm2_per_s: 0.01, q_motion_nm: 0.07, q_fast_nm: 0,"
                 " fast_tau_s: 60, initial_sigma_nm: 170, model_sigma_nm: 85}"),
      "mm3e_foreign_c.yaml");
  EXPECT_NEAR(c.noise_sigma_nm, std::sqrt(20.8 * 20.8 - 400.0 / 12.0), 1e-9);
}

TEST(NoiseModelFile, RoundTripsAndNamesABadKey) {
  NoiseModel m;
  m.reading_sigma_nm = 20.8;
  m.step_nm = 20;
  m.q_rest_nm2_per_s = 0.01;
  m.q_motion_nm = 0.2;
  m.q_fast_nm = 0.5;
  m.fast_tau_s = 20;
  m.initial_sigma_nm = 40;
  const NoiseModel r = NoiseModel::from_yaml(YAML::Load(YAML::Dump(m.to_yaml())), "m.yaml");
  EXPECT_EQ(r.q_motion_nm, 0.2);
  EXPECT_EQ(r.fast_tau_s, 20);
  YAML::Node bad = m.to_yaml();
  bad["q_rest_nm2_per_s"] = "fast";
  try {
    NoiseModel::from_yaml(bad, "m.yaml");
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("estimator.q_rest_nm2_per_s"), std::string::npos) << e.what();
  }
  bad = m.to_yaml();
  bad.remove("reading_sigma_nm");
  EXPECT_THROW(NoiseModel::from_yaml(bad, "m.yaml"), std::invalid_argument);
  bad = m.to_yaml();
  bad["fast_tau_s"] = -1.0;
  EXPECT_THROW(NoiseModel::from_yaml(bad, "m.yaml"), std::invalid_argument);
}

using piezo::compensation::HoldTrim;
using piezo::compensation::HoldTrimOptions;
using piezo::compensation::TrimState;

TEST(HoldTrim, WaitsForTheSettleTimeThenIntegratesBoundedAndSlewLimited) {
  HoldTrimOptions o;
  o.settle_s = 5.0;
  o.time_constant_s = 10.0;
  o.max_nm = 8.0;
  o.slew_nm_per_s = 0.5;
  HoldTrim t(o, kDt);
  t.on_new_intent();
  for (int i = 0; i < 54; ++i) {  // < 5 s
    t.step(100.0, 130.0, 1.0, true, 0, true, true);
    EXPECT_EQ(t.trim_nm(), 0.0);
    EXPECT_NE(t.state(), TrimState::kActive);
  }
  double last = 0.0;
  for (int i = 0; i < 2000; ++i) {
    t.step(100.0, 130.0, 1.0, true, 0, true, true);  // 30 nm too far: the trim goes negative
    EXPECT_EQ(t.state(), TrimState::kActive);
    EXPECT_LE(std::abs(t.trim_nm() - last), 0.5 * kDt + 1e-12);  // slew
    last = t.trim_nm();
  }
  EXPECT_DOUBLE_EQ(t.trim_nm(), -8.0);  // bound
  t.on_new_intent();  // a new intent cancels it at once
  EXPECT_EQ(t.trim_nm(), 0.0);
  EXPECT_EQ(t.state(), TrimState::kMoving);
}

// An estimate that cannot tell the error from zero does not move the tip: the trim integrates only the part of
// |intended − fused| beyond deadband_sigma × the fused σ (a coarse axis' estimate in a hold that does not flicker
// wanders within its σ, and a trim chasing it walks the tip towards a level's edge).
TEST(HoldTrim, ActsOnlyOnTheErrorBeyondTheFusedSigma) {
  HoldTrimOptions o;
  o.settle_s = 0.0;
  o.time_constant_s = 100.0;
  o.deadband_sigma = 1.0;
  HoldTrim t(o, kDt);
  for (int i = 0; i < 1000; ++i) t.step(100.0, 104.0, 8.0, true, 0, true, true);  // 4 nm off at 1σ 8 nm
  EXPECT_EQ(t.state(), TrimState::kActive);
  EXPECT_EQ(t.trim_nm(), 0.0);
  t.step(100.0, 130.0, 8.0, true, 0, true, true);  // 30 nm off: the 22 nm beyond 1σ, over τ
  EXPECT_NEAR(t.trim_nm(), -22.0 / 100.0 * kDt, 1e-12);
  t.step(100.0, 130.0, std::nan(""), true, 0, true, true);  // no σ: no band
  EXPECT_NEAR(t.trim_nm(), -(22.0 + 30.0) / 100.0 * kDt, 1e-12);
  o.deadband_sigma = -1.0;
  EXPECT_THROW(HoldTrim(o, kDt), std::invalid_argument);
}

TEST(HoldTrim, PausesOnAStaleEncoderAndOnFallbackAndOffWhenModelOnly) {
  HoldTrimOptions o;
  o.settle_s = 0.0;
  o.stale_after_s = 1.0;
  HoldTrim t(o, kDt);
  for (int i = 0; i < 100; ++i) t.step(0.0, 5.0, 1.0, true, 0, true, true);
  const double held = t.trim_nm();
  EXPECT_LT(held, 0.0);
  t.step(0.0, 5.0, 1.0, true, 12, true, true);  // 12 samples without a reading > 1 s
  EXPECT_EQ(t.state(), TrimState::kStale);
  EXPECT_EQ(t.trim_nm(), held);
  t.step(0.0, 5.0, 1.0, true, 0, false, true);
  EXPECT_EQ(t.state(), TrimState::kFallback);
  EXPECT_EQ(t.trim_nm(), held);
  t.step(0.0, 5.0, 1.0, false, 0, true, true);
  EXPECT_EQ(t.state(), TrimState::kModelOnly);
  EXPECT_EQ(t.trim_nm(), 0.0);
  EXPECT_THROW(HoldTrim(HoldTrimOptions{true, 5.0, 0.0}, kDt), std::invalid_argument);
}

// The compensator on a stage the model was not built from: the stage creeps more and slower than the model, and
// its offset drifts. Identified on an open-loop run, then closed: intents with 10-min holds.
struct Stage {
  std::unique_ptr<piezo::test::PiCreepModel> plant =
      std::make_unique<piezo::test::PiCreepModel>(std::vector<double>{0.0, 5.0, 10.0, 20.0, 40.0},
                                                  std::vector<double>{8.0, 1.5, 1.2, 1.0, 0.8}, 2.2, 900.0, 11.0);
  double t = 0.0;
  double truth(double v) {
    const piezo::models::ModelInput in{v, nullptr};
    const double y = plant->predict(in) + 6.0 * std::sin(t / 700.0);  // a slow drift the model lacks
    plant->commit(in, y);
    t += kDt;
    return y;
  }
};

piezo::estimation::NoiseModel identify_on_stage(std::uint32_t seed) {
  Stage st;
  auto model = piezo::test::make_pi_creep();
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 20.0);
  std::uniform_real_distribution<double> u(-50.0, 50.0);
  std::vector<double> p, y;
  double v = 0.0;
  st.plant->reset(0.0, 0.0);
  model->reset(0.0, 0.0);
  for (int i = 0; i < 11 * 3600; ++i) {
    if (i % (11 * 300) == 0) v = u(rng);
    const double x = st.truth(v);
    const piezo::models::ModelInput in{v, nullptr};
    const double pm = model->predict(in);
    model->commit(in, pm);
    p.push_back(pm);
    y.push_back(quantise(x + g(rng), 20.0));
  }
  piezo::estimation::IdentifyOptions o;
  o.reading_sigma_nm = std::sqrt(400.0 + 400.0 / 12.0);
  o.step_nm = 20.0;
  o.max_evaluations = 150;
  return piezo::estimation::identify_noise_model(p, y, o);
}

// Worst |truth − intended| over each 10-min hold after its first 2 min, with or without the trim.
double closed_loop_worst(bool trim, const piezo::estimation::NoiseModel& nm, std::size_t* slew_violations) {
  Stage st;
  auto model = piezo::test::make_pi_creep();
  model->meta.estimator = nm.to_yaml();
  piezo::compensation::AxisCompensatorConfig cfg;
  cfg.hold_trim.enabled = trim;
  cfg.hold_trim.slew_nm_per_s = 0.5;
  const piezo::compensation::IdealLine line{14.0, 0.0};
  piezo::compensation::AxisCompensator c(std::move(model), line, cfg);
  std::mt19937 rng(9);
  std::normal_distribution<double> g(0.0, 20.0);
  st.plant->reset(0.0, 0.0);
  double v = 0.0, worst = 0.0, last_trim = 0.0;
  const double targets[] = {300.0, -200.0, 500.0, 100.0};
  for (double target : targets) {
    c.set_intended_position_nm(target);
    last_trim = 0.0;  // a new intent cancels the trim at once: that step is not a slew
    for (int i = 0; i < 11 * 600; ++i) {
      const double x = st.truth(v);
      c.on_sample(v, quantise(x + g(rng), 20.0), true);
      const double tr = c.hold_trim().trim_nm();
      if (std::abs(tr - last_trim) > 0.5 * kDt + 1e-9) ++*slew_violations;
      last_trim = tr;
      if (c.hold_trim().state() == TrimState::kMoving || c.hold_trim().state() == TrimState::kSettling) {
        EXPECT_EQ(tr, 0.0);  // paused during moves
      }
      v = c.command(true).send_v;
      if (i > 11 * 120) worst = std::max(worst, std::abs(x - target));
    }
  }
  return worst;
}

TEST(AxisCompensatorTrim, HoldsTheTipOnAStageTheModelWasNotBuiltFrom) {
  const auto nm = identify_on_stage(5);
  std::size_t slew = 0;
  const double ff = closed_loop_worst(false, nm, &slew);
  const double trimmed = closed_loop_worst(true, nm, &slew);
  std::printf("worst |truth - intended| after 2 min of each hold: feedforward %.2f nm, trimmed %.2f nm (%s)\n", ff,
              trimmed, nm.describe().c_str());
  EXPECT_GT(ff, 8.0);
  EXPECT_LT(trimmed, 0.4 * ff);
  EXPECT_EQ(slew, 0u);
}

TEST(Track, FindsHoldsAndRunsTheSameCompensator) {
  const std::vector<double> v{0, 0, 0, 1, 1, 2, 2, 2, 2};
  const auto h = piezo::compensation::find_holds(v, 1.0, 3.0);
  ASSERT_EQ(h.size(), 2u);
  EXPECT_EQ(h[0], (std::pair<std::size_t, std::size_t>{0, 3}));
  EXPECT_EQ(h[1], (std::pair<std::size_t, std::size_t>{5, 9}));
}

}  // namespace
