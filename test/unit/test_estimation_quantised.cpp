// The quantised reading model (estimation/quantised_reading.h) and the error filter on a coarse-encoder axis:
// the likelihood against Monte Carlo and in its tails, the moment-matched update against quadrature, the dithered
// limit against the Kalman update, and the filter on the simulator's 250 nm axis a against the truth (a cold start
// mid-walk, 30-min holds with and without a crossing, a stuck encoder, the noise σ identified). A few seconds.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <random>
#include <vector>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/estimation/error_filter.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/estimation/quantised_reading.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"

namespace {

using namespace piezo::estimation;

constexpr double kDt = 1.0 / 11.0;
constexpr double kStep = 250.0;
constexpr double kSigma = 19.97;  // the simulator's σ before the quantiser

double quantise(double x, double q) { return q * std::nearbyint(x / q); }

TEST(QuantisedReading, LikelihoodMatchesMonteCarlo) {
  std::mt19937 rng(1);
  std::normal_distribution<double> g(0.0, kSigma);
  const int n = 200000;
  for (double x : {0.0, 60.0, 110.0, 125.0, 140.0, -118.0}) {
    std::map<long, int> count;
    for (int i = 0; i < n; ++i) ++count[std::lround(quantise(x + g(rng), kStep) / kStep)];
    double total = 0.0;
    for (long k = -3; k <= 3; ++k) {
      const double p = std::exp(reading_log_likelihood(k * kStep, x, kSigma, kStep));
      total += p;
      const double p_hat = static_cast<double>(count[k]) / n;
      EXPECT_NEAR(p_hat, p, 5.0 * std::sqrt(p * (1.0 - p) / n) + 1e-6) << "x " << x << " level " << k;
    }
    EXPECT_NEAR(total, 1.0, 1e-9);
  }
  // fine steps (axis c: 20 nm against 20 nm) are the same model
  std::map<long, int> count;
  for (int i = 0; i < n; ++i) ++count[std::lround(quantise(7.0 + g(rng), 20.0) / 20.0)];
  for (long k = -4; k <= 4; ++k) {
    const double p = std::exp(reading_log_likelihood(k * 20.0, 7.0, kSigma, 20.0));
    EXPECT_NEAR(static_cast<double>(count[k]) / n, p, 5.0 * std::sqrt(p * (1.0 - p) / n)) << k;
  }
}

TEST(QuantisedReading, TailsAreFiniteAndMatchTheAsymptote) {
  for (double z : {10.0, 20.0, 40.0, 100.0, 1e4}) {
    // a reading z σ beyond the truth: log Q(z) ≈ −z²/2 − log(z √(2π))
    const double ll = reading_log_likelihood(kStep, kStep / 2.0 - z * kSigma, kSigma, kStep);
    ASSERT_TRUE(std::isfinite(ll)) << z;
    EXPECT_NEAR(ll, -0.5 * z * z - std::log(z * std::sqrt(2.0 * M_PI)), 0.01 * std::max(1.0, 1.0 / (z * z)) + 1e-3 * z)
        << z;
    EXPECT_TRUE(std::isfinite(log_normal_cdf(-z)));
    EXPECT_NEAR(log_normal_cdf(-z), log_normal_sf(z), 1e-12 * z * z);
    // both tails, both ends of the cell, and the update from a prior that far off
    for (double sign : {1.0, -1.0}) {
      const double s = std::sqrt(30.0 * 30.0 + kSigma * kSigma);
      const ReadingUpdate u = quantised_update(0.0, 30.0 * 30.0, sign * (z * s + kStep / 2.0), kSigma, kStep);
      ASSERT_TRUE(std::isfinite(u.mean_nm) && std::isfinite(u.var_nm2) && std::isfinite(u.log_p)) << z;
      EXPECT_GT(u.var_nm2, 0.0);
      EXPECT_LT(u.var_nm2, 30.0 * 30.0);
      EXPECT_GT(sign * u.mean_nm, 0.0);  // pulled towards the reading
      EXPECT_NEAR(u.cell_distance, z, 1e-3 * z);
    }
  }
  const TruncatedMoments t = truncated_standard_normal(10.0, 10.5);
  EXPECT_TRUE(std::isfinite(t.log_z) && t.mean > 10.0 && t.mean < 10.5 && t.var > 0.0 && t.var < 0.25 / 12.0 * 4.0);
}

// The moment-matched posterior against the exact one by quadrature: Gaussian prior × the cell's likelihood.
TEST(QuantisedReading, MomentMatchingIsTheExactPosteriorsMeanAndVariance) {
  struct Case { double m, P, y, q; };
  for (const Case c : {Case{0.0, 100.0 * 100.0, 250.0, 250.0}, Case{110.0, 30.0 * 30.0, 0.0, 250.0},
                       Case{-40.0, 5.0 * 5.0, 0.0, 250.0}, Case{3.0, 40.0 * 40.0, 20.0, 20.0},
                       Case{900.0, 50.0 * 50.0, 0.0, 250.0}}) {
    double z = 0, s1 = 0, s2 = 0;
    // the far case's posterior weight is e^-100: scaled by e^(shift/2) before the sum, unscaled in log_p
    const double gap = std::max(0.0, std::abs(c.m - c.y) - c.q / 2.0), shift = gap * gap / (c.P + kSigma * kSigma);
    const double sd = std::sqrt(c.P), h = std::min(sd, kSigma) / 500.0;
    const double lo = std::min(c.m - 12.0 * sd, c.y - c.q / 2.0 - 12.0 * kSigma);
    const double hi = std::max(c.m + 12.0 * sd, c.y + c.q / 2.0 + 12.0 * kSigma);
    for (double x = lo; x <= hi; x += h) {
      const double w = std::exp(-0.5 * (x - c.m) * (x - c.m) / c.P + reading_log_likelihood(c.y, x, kSigma, c.q) + 0.5 * shift);
      z += w, s1 += w * x, s2 += w * x * x;
    }
    const double mean = s1 / z, var = s2 / z - mean * mean;
    const ReadingUpdate u = quantised_update(c.m, c.P, c.y, kSigma, c.q);
    EXPECT_NEAR(u.mean_nm, mean, 1e-4 * sd) << c.m << " " << c.y;
    EXPECT_NEAR(u.var_nm2, var, 1e-4 * c.P) << c.m << " " << c.y;
    EXPECT_NEAR(u.log_p, std::log(z * h / std::sqrt(2.0 * M_PI * c.P)) - 0.5 * shift, 1e-4) << c.m << " " << c.y;
  }
}

// q → 0: the Kalman update with r = σ², one code path.
TEST(QuantisedReading, APointReadingIsTheKalmanUpdate) {
  for (double q : {0.0, 1e-9}) {
    const ReadingUpdate u = quantised_update(10.0, 400.0, 37.0, kSigma, q);
    const double s = 400.0 + kSigma * kSigma, k = 400.0 / s;
    EXPECT_NEAR(u.mean_nm, 10.0 + k * 27.0, 1e-9);
    EXPECT_NEAR(u.var_nm2, 400.0 * (1.0 - k), 1e-6);
    EXPECT_NEAR(u.innovation_nm, 27.0, 1e-9);
    if (q == 0.0) {
      EXPECT_NEAR(u.log_p, -0.5 * (std::log(2.0 * M_PI * s) + 27.0 * 27.0 / s), 1e-12);
    }
  }
}

// The simulator's axis a (250 nm steps, σ 19.97 nm before the quantiser) driven by a voltage program; the "model"
// is the truth less a known error: a start offset, a random walk (q_rest at rest + q_motion per nm moved) and a
// fast part that follows each move and settles, so the filter's noise model is the true one.
struct SimRun {
  std::vector<double> truth, y, p;
};

NoiseModel true_noise_model() {
  NoiseModel m;
  m.step_nm = kStep;
  m.noise_sigma_nm = kSigma;
  m.reading_sigma_nm = std::sqrt(kSigma * kSigma + kStep * kStep / 12.0);
  m.q_rest_nm2_per_s = 0.5;
  m.q_motion_nm = 0.02;
  m.q_fast_nm = 0.05;
  m.fast_tau_s = 20.0;
  m.initial_sigma_nm = 200.0;
  return m;
}

// walk_s of a random walk (a new target every 4 s within ±40 V), then hold_v for hold_s.
SimRun simulate(std::uint64_t seed, double walk_s, double hold_v, double hold_s, double offset_nm) {
  piezo::sim::ManipulatorSimulator sim(piezo::sim::default_simulator_config(), seed);
  const NoiseModel nm = true_noise_model();
  std::mt19937 rng(static_cast<std::uint32_t>(seed));
  std::normal_distribution<double> g(0.0, 1.0);
  std::uniform_real_distribution<double> u(-40.0, 40.0);
  SimRun r;
  double v = 0.0, target = 0.0, slow = offset_nm, fast = 0.0, last = 0.0;
  const double phi = std::exp(-kDt / nm.fast_tau_s);
  const std::size_t walk_n = static_cast<std::size_t>(walk_s / kDt), n = walk_n + static_cast<std::size_t>(hold_s / kDt);
  for (std::size_t i = 0; i < n; ++i) {
    if (i < walk_n && i % 44 == 0) target = u(rng);
    if (i == walk_n) target = hold_v;
    v += std::clamp(target - v, -1.0, 1.0);  // 11 V/s
    const auto s = sim.step({v, 0.0, 0.0}, kDt);
    const double x = s.axes[0].true_position_nm, dp = i ? std::abs(x - last) : 0.0;
    last = x;
    slow += std::sqrt(nm.q_rest_nm2_per_s * kDt + nm.q_motion_nm * dp) * g(rng);
    fast = phi * fast + std::sqrt(nm.q_fast_nm * dp) * g(rng);
    r.truth.push_back(x);
    r.y.push_back(s.axes[0].measured_position_nm);
    r.p.push_back(x - slow - fast);
  }
  return r;
}

struct Score {
  double mae = 0, worst = 0, within2 = 0, mean_sigma = 0, end_sigma = 0, end_err = 0;
  std::size_t rejected = 0;
};

Score run_and_score(const NoiseModel& nm, const SimRun& r, std::size_t from, std::size_t to, ErrorFilter* out = nullptr,
                    std::size_t stuck_from = SIZE_MAX) {
  ErrorFilter f(nm, kDt);
  Score s;
  std::size_t in2 = 0;
  for (std::size_t i = 0; i < r.p.size() && i < to; ++i) {
    const double y = i >= stuck_from ? r.y[stuck_from] : r.y[i];
    f.step(r.p[i], y, true);
    if (i < from) continue;
    const double e = std::abs(f.fused_nm() - r.truth[i]);
    s.mae += e, s.worst = std::max(s.worst, e), s.mean_sigma += f.sigma_nm();
    in2 += e <= 2.0 * f.sigma_nm();
  }
  const double n = static_cast<double>(std::min(to, r.p.size()) - from);
  s.mae /= n, s.mean_sigma /= n, s.within2 = in2 / n;
  s.end_sigma = f.sigma_nm();
  s.end_err = f.fused_nm() - r.truth[std::min(to, r.p.size()) - 1];
  s.rejected = f.rejected_readings();
  if (out) *out = f;
  return s;
}

// A cold start in the middle of a walk: the model is 180 nm off and the filter starts at 0 ± 200 nm (what a cold
// start on an unrecorded history gives). The first minute of motion pins the zero.
TEST(QuantisedFilter, ColdStartMidWalkPinsTheZeroInTheFirstMinute) {
  const SimRun r = simulate(21, 1200.0, 0.0, 0.0, 180.0);
  const NoiseModel nm = true_noise_model();
  const std::size_t minute = static_cast<std::size_t>(60.0 / kDt);
  ErrorFilter f(nm, kDt);
  const Score first = run_and_score(nm, r, 0, minute, &f);
  EXPECT_TRUE(f.zero_known()) << f.sigma_nm();
  EXPECT_LT(std::abs(first.end_err), 25.0);
  const Score rest = run_and_score(nm, r, minute, r.p.size());
  std::printf("cold start mid-walk: after 1 min |error| %.1f nm, 1σ %.1f nm; then MAE %.2f nm, mean 1σ %.2f nm, "
              "within 2σ %.1f %%\n", std::abs(first.end_err), first.end_sigma, rest.mae, rest.mean_sigma,
              100.0 * rest.within2);
  EXPECT_LT(rest.mae, 10.0);  // a twenty-fifth of a step
  EXPECT_GE(rest.within2, 0.93);
}

// 30-min holds after a 10-min walk, at voltages where the truth stays inside one cell or crosses a boundary.
TEST(QuantisedFilter, ThirtyMinuteHoldsWithAndWithoutACrossingStayHonest) {
  const NoiseModel nm = true_noise_model();
  bool seen_crossing = false, seen_quiet = false;
  for (double hold_v : {-30.0, -17.0, -4.0, 9.0, 22.0, 35.0}) {
    const SimRun r = simulate(31, 600.0, hold_v, 1800.0, -60.0);
    const std::size_t hold0 = static_cast<std::size_t>(600.0 / kDt) + 200;
    const std::size_t levels = std::set<double>(r.y.begin() + hold0, r.y.end()).size();
    const Score s = run_and_score(nm, r, hold0, r.p.size());
    std::printf("hold at %.0f V, %zu level(s): MAE %.2f nm, worst %.2f nm, end %.2f nm, mean 1σ %.2f, end 1σ %.2f, "
                "within 2σ %.1f %%\n", hold_v, levels, s.mae, s.worst, s.end_err, s.mean_sigma, s.end_sigma,
                100.0 * s.within2);
    EXPECT_GE(s.within2, 0.93) << hold_v;
    EXPECT_LT(s.worst, kStep / 2.0) << hold_v;  // within one step, always
    if (levels == 1) {
      seen_quiet = true;
      // nothing crosses: the σ says the cell bounds it (no sub-nm claim from a model that walks 0.5 nm²/s)
      EXPECT_LT(s.end_sigma, kStep / std::sqrt(12.0)) << hold_v;
      EXPECT_GT(s.end_sigma, 10.0) << hold_v;
    } else {
      seen_crossing = true;
      EXPECT_LT(std::abs(s.end_err), 40.0) << hold_v;
    }
  }
  EXPECT_TRUE(seen_crossing && seen_quiet);
}

// The encoder sticks (its level frozen) for 2 min while the stage walks. The filter must not believe the stale
// level: once the model has moved further than the level can explain, the readings since it was first read are
// undone and no more are taken; the filter predicts and its σ grows.
TEST(QuantisedFilter, AStuckEncoderIsNotBelieved) {
  const SimRun r = simulate(41, 900.0, 0.0, 0.0, 50.0);
  const std::size_t stuck = static_cast<std::size_t>(600.0 / kDt), end = stuck + static_cast<std::size_t>(120.0 / kDt);
  const NoiseModel nm = true_noise_model();
  ErrorFilter f(nm, kDt);
  const Score before = run_and_score(nm, r, stuck - 600, stuck);
  const Score s = run_and_score(nm, r, stuck, end, &f, stuck);
  double away = 0.0;  // how far the truth went from the stale level
  for (std::size_t i = stuck; i < end; ++i) away = std::max(away, std::abs(r.truth[i] - r.y[stuck]));
  std::printf("stuck encoder 2 min (truth up to %.0f nm from the stale level): end |error| %.1f nm, 1σ %.1f nm "
              "(%.1f nm before), %zu readings stale, within 2σ %.1f %%\n", away, std::abs(s.end_err), s.end_sigma,
              before.end_sigma, f.stale_readings(), 100.0 * s.within2);
  EXPECT_GT(away, 1000.0);
  EXPECT_GT(f.stale_readings(), 1000u);
  EXPECT_GT(f.samples_since_reading(), 1000u);  // the hold trim sees a stale encoder
  EXPECT_GT(s.end_sigma, 2.0 * before.end_sigma);
  EXPECT_LT(std::abs(s.end_err), 2.0 * s.end_sigma);
  EXPECT_GE(s.within2, 0.8);  // the readings before the model has moved far enough to tell are believed
}

// The noise σ before the quantiser and the variance rates, by maximum likelihood under the quantised model.
TEST(QuantisedFilter, IdentifiesTheNoiseBeforeTheQuantiser) {
  const SimRun r = simulate(51, 2400.0, 10.0, 1200.0, 0.0);
  IdentifyOptions o;
  o.dt_s = kDt;
  o.reading_sigma_nm = kStep / std::sqrt(12.0);  // what the noise floor reports when rounding dominates
  o.step_nm = kStep;
  o.fast_tau_grid_s = {20.0};
  o.max_evaluations = 300;
  const NoiseModel m = identify_noise_model(r.p, r.y, o);
  std::printf("identified: %s\n", m.describe().c_str());
  EXPECT_TRUE(m.fuse);
  EXPECT_NEAR(m.noise_sigma_nm, kSigma, 2.0);
}

// A held axis started cold with a start offset several cells off and too confident a σ (the demo's axis a: no move
// to learn the zero from): the same level read again and again is the zero the start did not know. Before any
// reading has been taken it is taken (the slow error widened to reach it), and the estimate ends inside the cell.
TEST(QuantisedFilter, AHeldAxisStartedFarOffTakesItsLevel) {
  const NoiseModel nm = true_noise_model();
  ErrorFilter f(nm, kDt);
  f.reset(-250.0, 60.0);  // the model's zero 950 nm from the truth at +700, σ 60 nm
  const double truth = 700.0, level = 750.0;  // 700 nm read through 250-nm cells: level 3
  for (int i = 0; i < static_cast<int>(60.0 / kDt); ++i) f.step(0.0, level, true);
  std::printf("held axis, start 950 nm off: fused %.1f nm (truth %.0f, cell [625, 875]), 1σ %.1f nm\n", f.fused_nm(),
              truth, f.sigma_nm());
  EXPECT_GT(f.fused_nm(), 625.0 - 2.0 * f.sigma_nm());
  EXPECT_LT(f.fused_nm(), 875.0 + 2.0 * f.sigma_nm());
  EXPECT_LT(f.sigma_nm(), 125.0);
  EXPECT_GT(f.updates(), 0u);
}

// An encoder that never changes level (a stuck one, or a tip that never left its cell) identifies nothing: the
// likelihood is flat in σ and the rates. The block is model-only and says why, in the file and in describe().
TEST(QuantisedFilter, AnEncoderThatNeverChangesLevelIsModelOnlyAndSaysWhy) {
  const SimRun r = simulate(51, 600.0, 10.0, 1200.0, 0.0);
  IdentifyOptions o;
  o.dt_s = kDt;
  o.reading_sigma_nm = 0.0;  // what the noise floor reports for readings that never change
  o.step_nm = 0.0;
  const std::vector<double> stuck(r.p.size(), 500.0);
  const NoiseModel m = identify_noise_model(r.p, stuck, o);
  std::printf("never changes level: %s\n", m.describe().c_str());
  EXPECT_FALSE(m.fuse);
  EXPECT_NE(m.method.find("changed level 0 times"), std::string::npos) << m.method;
  EXPECT_NE(m.describe().find("not identifiable"), std::string::npos) << m.describe();
  EXPECT_GT(m.model_sigma_nm, 0.0);
  const NoiseModel back = NoiseModel::from_yaml(m.to_yaml(), "stuck.yaml");  // the block loads again
  EXPECT_FALSE(back.fuse);
  EXPECT_EQ(back.describe(), m.describe());
  ErrorFilter f(back, kDt);
  for (std::size_t i = 0; i < 100; ++i) f.step(r.p[i], stuck[i], true);
  EXPECT_EQ(f.fused_nm(), r.p[99]);  // model-only: the fused position is the model's
  // a few crossings do not identify it either; the same walk read through the quantiser does
  std::vector<double> few = stuck;
  for (std::size_t i = 1000; i < 1004; ++i) few[i] = 750.0;
  o.reading_sigma_nm = kStep / std::sqrt(12.0);
  o.step_nm = kStep;
  EXPECT_FALSE(identify_noise_model(r.p, few, o).fuse);
}

// The compensator closes the hold on a coarse axis: the coarse stage's simulated axis a (20 µm, 250 nm steps) and
// the shipped model fitted on another seed of it, from rest: a 5-min walk of intents, then a 20-min hold. The trim
// acts under the same rules as on c (0 and never active while the intent moves, slew-limited, bounded), and the
// tip ends the hold within 40 nm of the intent.
TEST(QuantisedFilter, TheHoldTrimWorksOnACoarseAxis) {
  const std::string src = PIEZO_SOURCE_DIR;
  const piezo::sim::StageConfig stage = piezo::sim::load_stage(src + "/config/stages/mm3e_coarse_stage.yaml");
  piezo::sim::ManipulatorSimulator sim(stage.simulator, 211);
  piezo::models::ModelPtr model = piezo::models::load_model(src + "/config/models/mm3e_coarse_a.yaml");
  piezo::compensation::IdealLineOptions lo;
  lo.hold_s = 60.0;
  const piezo::compensation::IdealLine line = piezo::compensation::ideal_line_from_model(*model, lo);
  piezo::compensation::AxisCompensatorConfig cfg;
  piezo::compensation::AxisCompensator c(std::move(model), line, cfg);
  ASSERT_TRUE(c.estimator() && c.estimator()->fusing()) << c.estimator_status();
  const double slew = cfg.hold_trim.slew_nm_per_s * kDt + 1e-9;
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-50.0, 50.0);
  double v = 0.0, last_trim = 0.0, worst_end = 0.0, worst_model_end = 0.0;
  std::size_t bad_slew = 0, bad_move = 0, active = 0;
  const std::size_t walk = static_cast<std::size_t>(300.0 / kDt), n = walk + static_cast<std::size_t>(1200.0 / kDt);
  for (std::size_t i = 0; i < n; ++i) {
    const bool moving = i < walk && i % 44 == 0;
    if (moving) c.set_intended_voltage(u(rng));
    if (i == walk) c.set_intended_voltage(12.0);
    const auto s = sim.step({v, 0.0, 0.0}, kDt);
    const auto up = c.on_sample(v, s.axes[0].measured_position_nm, true);
    const double trim = c.hold_trim().trim_nm();
    if (moving || i == walk) {
      bad_move += trim != 0.0 || c.hold_trim().state() == piezo::compensation::TrimState::kActive;
    } else {
      bad_slew += std::abs(trim - last_trim) > slew;
    }
    active += c.hold_trim().state() == piezo::compensation::TrimState::kActive;
    last_trim = trim;
    v = c.command(true).send_v;
    if (i + 55 >= n) {
      const double intended = line.position_nm(12.0);
      worst_end = std::max(worst_end, std::abs(s.axes[0].true_position_nm - intended));
      worst_model_end = std::max(worst_model_end, std::abs(up.predicted_nm - s.axes[0].true_position_nm));
    }
  }
  std::printf("coarse axis, 20-min hold: last 5 s worst |truth - intended| %.1f nm (model's own error %.1f nm), trim "
              "%.1f nm, fused 1σ %.1f nm, %zu samples active\n", worst_end, worst_model_end, last_trim,
              c.estimator()->sigma_nm(), active);
  EXPECT_EQ(bad_move, 0u);
  EXPECT_EQ(bad_slew, 0u);
  EXPECT_GT(active, 5000u);
  EXPECT_LE(std::abs(last_trim), c.hold_trim().options().max_nm);
  EXPECT_LT(worst_end, 40.0);
}

}  // namespace
