// The simulated MM3E against the numbers of the reference study.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <numeric>
#include <set>

#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/piezo_axis.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/util/splitmix64.h"

using namespace piezo;

namespace {

constexpr double kRate = 11.0;

// Rows of one segment in sweep phase.
std::vector<std::size_t> rows(const io::Dataset& d, int segment, protocols::Phase phase) {
  std::vector<std::size_t> out;
  for (std::size_t i = 0; i < d.size(); ++i)
    if (d.segment[i] == segment && d.phase[i] == static_cast<int>(phase)) out.push_back(i);
  return out;
}

struct Loop {
  double span_nm = 0.0;   // max − min of the true position over the loop
  double width_nm = 0.0;  // descending minus ascending branch at mid voltage
};

// One up-and-down sweep: width between the branches at the middle voltage.
Loop loop_of(const io::Dataset& d, const std::string& axis, const std::vector<std::size_t>& idx) {
  const auto& a = d.axis(axis);
  double vmin = 1e9, vmax = -1e9, ymin = 1e9, ymax = -1e9;
  std::size_t peak = idx.front();
  for (auto i : idx) {
    if (a.voltage_v[i] > vmax) {
      vmax = a.voltage_v[i];
      peak = i;
    }
    vmin = std::min(vmin, a.voltage_v[i]);
    ymin = std::min(ymin, a.true_position_nm[i]);
    ymax = std::max(ymax, a.true_position_nm[i]);
  }
  const double mid = 0.5 * (vmin + vmax);
  double up = NAN, down = NAN, e_up = 1e9, e_down = 1e9;
  for (auto i : idx) {
    const double e = std::fabs(a.voltage_v[i] - mid);
    if (i <= peak && e < e_up) e_up = e, up = a.true_position_nm[i];
    if (i > peak && e < e_down) e_down = e, down = a.true_position_nm[i];
  }
  return {ymax - ymin, down - up};
}

io::Dataset simulate(const std::string& protocol, std::uint64_t seed, const sim::SimulatorConfig& cfg,
                     const YAML::Node& params = YAML::Node()) {
  auto p = protocols::make_protocol(protocol, params, kRate, seed);
  sim::ManipulatorSimulator s(cfg, seed);
  return s.run(p->program());
}

double mean(const std::vector<double>& v) { return std::accumulate(v.begin(), v.end(), 0.0) / v.size(); }

double stddev(const std::vector<double>& v) {
  const double m = mean(v);
  double s = 0.0;
  for (double x : v) s += (x - m) * (x - m);
  return std::sqrt(s / (v.size() - 1));
}

sim::SimulatorConfig quiet_config() {  // no noise, no quantisation: the physics alone
  auto c = sim::default_simulator_config();
  for (auto& a : c.axes) a.encoder_noise_sigma_nm = 0.0, a.encoder_quantisation_nm = 0.0;
  return c;
}

}  // namespace

TEST(SimConfig, YamlFileMirrorsDefaults) {
  const auto file = sim::load_simulator_config(std::string(PIEZO_SOURCE_DIR) + "/config/simulator.yaml");
  const auto def = sim::default_simulator_config();
  EXPECT_EQ(file.sample_rate_hz, def.sample_rate_hz);
  for (int k = 0; k < 3; ++k) {
    const auto &f = file.axes[k], &d = def.axes[k];
    SCOPED_TRACE(d.name);
    EXPECT_EQ(f.stroke_nm, d.stroke_nm);
    EXPECT_EQ(f.loop_width_fraction, d.loop_width_fraction);
    EXPECT_EQ(f.play_operator_count, d.play_operator_count);
    EXPECT_EQ(f.play_weight_decay_v, d.play_weight_decay_v);
    EXPECT_EQ(f.asymmetry_nm, d.asymmetry_nm);
    EXPECT_EQ(f.creep_mode_count, d.creep_mode_count);
    EXPECT_EQ(f.creep_tau_min_s, d.creep_tau_min_s);
    EXPECT_EQ(f.creep_tau_max_s, d.creep_tau_max_s);
    EXPECT_EQ(f.creep_alpha, d.creep_alpha);
    EXPECT_EQ(f.creep_gain, d.creep_gain);
    EXPECT_EQ(f.encoder_quantisation_nm, d.encoder_quantisation_nm);
    EXPECT_EQ(f.encoder_noise_sigma_nm, d.encoder_noise_sigma_nm);
    EXPECT_EQ(f.voltage_min_v, d.voltage_min_v);
    EXPECT_EQ(f.voltage_max_v, d.voltage_max_v);
    EXPECT_EQ(f.hysteresis_model, d.hysteresis_model);
    EXPECT_EQ(f.preisach_grid_count, d.preisach_grid_count);
    EXPECT_EQ(f.preisach_centre_offset, d.preisach_centre_offset);
    EXPECT_EQ(f.preisach_centre_spread, d.preisach_centre_spread);
    EXPECT_EQ(f.preisach_width_decay, d.preisach_width_decay);
    EXPECT_EQ(f.creep_spectrum_tau_s, d.creep_spectrum_tau_s);
    EXPECT_EQ(f.creep_spectrum_weights, d.creep_spectrum_weights);
  }
  EXPECT_EQ(file.thermal_drift.gain_nm_per_c, def.thermal_drift.gain_nm_per_c);
  EXPECT_EQ(file.thermal_drift.period_s, def.thermal_drift.period_s);
  EXPECT_EQ(file.cross_axis.gain, def.cross_axis.gain);
  EXPECT_EQ(file.encoder_periodic.amplitude_nm, def.encoder_periodic.amplitude_nm);
  EXPECT_EQ(file.rate_dependent.gain, def.rate_dependent.gain);
  EXPECT_EQ(file.periodic_disturbance.frequency_hz, def.periodic_disturbance.frequency_hz);
  EXPECT_TRUE(sim::enabled_effects(file).empty());
}

TEST(SimConfig, BadKeysAndEffectsAreNamed) {
  const std::string path = ::testing::TempDir() + "bad_sim.yaml";
  auto error_of = [&](const std::string& text) -> std::string {
    std::ofstream(path) << text;
    try {
      sim::load_simulator_config(path);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  };
  EXPECT_NE(error_of("axes: {c: {stroke_mm: 2}}").find("axes.c.stroke_mm: unknown key"), std::string::npos);
  EXPECT_NE(error_of("axes: {c: {stroke_nm: abc}}").find("axes.c.stroke_nm: expected a number"), std::string::npos);
  EXPECT_NE(error_of("axes: {c: {stroke_nm: -5}}").find("stroke_nm"), std::string::npos);
  EXPECT_NE(error_of("effects: {wobble: {enabled: true}}").find("unknown effect"), std::string::npos);
  EXPECT_NE(error_of("effects: {thermal_drift: {enabled: maybe}}").find("thermal_drift.enabled"), std::string::npos);
  EXPECT_NE(error_of("axes: [1, 2").find("cannot read"), std::string::npos);
  EXPECT_EQ(error_of("effects: {cross_axis: {enabled: true, gain: 0.05}}"), "");

  auto c = sim::default_simulator_config();
  try {
    sim::enable_effect(c, "thermal");
    FAIL() << "unknown effect accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("thermal_drift, cross_axis, encoder_periodic"), std::string::npos);
  }
  for (const auto& e : sim::effect_names()) sim::enable_effect(c, e);
  EXPECT_EQ(sim::enabled_effects(c).size(), 5u);
}

TEST(SimPhysics, FullRangeLoopWidthInBand) {
  const auto d = simulate("sweep", 1, quiet_config());
  const int fast_seg = 12, slow_seg = 16;  // full-range sweeps at 1.25 V and 0.01 V per sample
  ASSERT_NEAR(d.axis("c").voltage_v[rows(d, slow_seg, protocols::Phase::kSweep)[1]] -
                  d.axis("c").voltage_v[rows(d, slow_seg, protocols::Phase::kSweep)[0]],
              0.01, 1e-4);
  for (int seg : {fast_seg, slow_seg}) {
    const Loop l = loop_of(d, "c", rows(d, seg, protocols::Phase::kSweep));
    SCOPED_TRACE(seg);
    EXPECT_NEAR(l.span_nm, 2150.0, 250.0);  // stroke ≈ 2 µm
    EXPECT_GE(l.width_nm / l.span_nm, 0.10);
    EXPECT_LE(l.width_nm / l.span_nm, 0.15);
  }
}

TEST(SimPhysics, SlowSweepsCreepFurther) {
  const auto d = simulate("sweep", 2, quiet_config());
  const Loop fast = loop_of(d, "c", rows(d, 12, protocols::Phase::kSweep));  // 1.25 V per sample
  const Loop slow = loop_of(d, "c", rows(d, 16, protocols::Phase::kSweep));  // 0.01 V per sample
  // Creep follows the slow sweep: the loop stretches by well over the encoder noise.
  EXPECT_GT(slow.span_nm - fast.span_nm, 150.0);
  // Spans grow monotonically with the sweep duration.
  double prev = 0.0;
  for (int seg = 12; seg <= 16; ++seg) {
    const double span = loop_of(d, "c", rows(d, seg, protocols::Phase::kSweep)).span_nm;
    EXPECT_GT(span, prev) << "segment " << seg;
    prev = span;
  }
}

TEST(SimPhysics, PartialSweepsGiveMinorLoops) {
  const auto d = simulate("sweep", 3, quiet_config());
  // 0.25 of the range from seven starting points: loops narrower than the full one, widest near the top
  // (the play operators engaged since the last reversal).
  const Loop full = loop_of(d, "c", rows(d, 12, protocols::Phase::kSweep));
  for (int seg = 0; seg < 7; ++seg) {
    const Loop l = loop_of(d, "c", rows(d, seg, protocols::Phase::kSweep));
    EXPECT_GT(l.width_nm, 10.0) << seg;
    EXPECT_LT(l.width_nm, full.width_nm) << seg;
    EXPECT_LT(l.span_nm, 0.5 * full.span_nm) << seg;
  }
}

TEST(SimPhysics, MinorLoopsCloseAndWipeOut) {
  auto cfg = quiet_config();
  for (auto& a : cfg.axes) a.creep_gain = 0.0;  // rate-independent part alone: closure is exact
  sim::ManipulatorSimulator s(cfg, 5);
  auto go = [&](double v) {
    sim::StepResult r;
    for (int i = 0; i < 5; ++i) r = s.step({v, v, v}, 1.0 / kRate);
    return r.axes[2].true_position_nm;
  };
  go(80.0);
  const double at_m20 = go(-20.0);
  // Minor loop -20 → 30 → -20 returns to the same point.
  go(30.0);
  EXPECT_NEAR(go(-20.0), at_m20, 1e-9);
  // Nested loops -20 → 10 → -5 → 20 → -20: still closes.
  go(10.0), go(-5.0), go(20.0);
  EXPECT_NEAR(go(-20.0), at_m20, 1e-9);
  // Wiping out: two histories that differ only inside a range later exceeded end in the same state.
  sim::ManipulatorSimulator s2(cfg, 5);
  auto go2 = [&](double v) {
    sim::StepResult r;
    for (int i = 0; i < 5; ++i) r = s2.step({v, v, v}, 1.0 / kRate);
    return r.axes[2].true_position_nm;
  };
  go2(80.0), go2(-20.0), go2(50.0), go2(0.0);
  const double a1 = go(-60.0), b1 = go2(-60.0);  // below every minimum since the last +80 V
  EXPECT_NEAR(a1, b1, 1e-9);
  EXPECT_NEAR(go(25.0), go2(25.0), 1e-9);
  // ... and before the wiping excursion the two states differed.
  sim::ManipulatorSimulator s3(cfg, 5);
  for (double v : {80.0, -20.0, 50.0, 0.0, 20.0}) {
    for (int i = 0; i < 5; ++i) s3.step({v, v, v}, 1.0 / kRate);
  }
  sim::ManipulatorSimulator s4(cfg, 5);
  for (double v : {80.0, -20.0, 30.0, -20.0, 20.0}) {
    for (int i = 0; i < 5; ++i) s4.step({v, v, v}, 1.0 / kRate);
  }
  EXPECT_GT(std::fabs(s3.step({20, 20, 20}, 0.1).axes[2].true_position_nm -
                      s4.step({20, 20, 20}, 0.1).axes[2].true_position_nm),
            5.0);
}

// The Preisach step visits only the relays whose thresholds the input crossed; it must give what visiting every
// relay gives, on inputs that land exactly on switching voltages (no jitter: the grid's bin centres, and the
// memoryless α = β relays) as well as between them, with and without jitter, after a reset too.
TEST(SimPhysics, PreisachIncrementalStepMatchesEveryRelay) {
  for (bool jitter : {false, true}) {
    sim::AxisConfig axis = sim::default_simulator_config().axes[2];
    axis.hysteresis_model = "preisach";
    axis.preisach_grid_count = 40;
    axis.preisach_threshold_jitter = jitter;
    sim::Preisach fast(axis), every(axis);
    const double lo = axis.voltage_min_v, hi = axis.voltage_max_v, mid = 0.5 * (lo + hi), half = 0.5 * (hi - lo);
    const int n = axis.preisach_grid_count;
    std::uint64_t h = 12345;
    double v = mid, worst = 0.0;
    for (int t = 0; t < 20000; ++t) {
      const double r = static_cast<double>(piezo::util::splitmix64(h) >> 11) * 0x1.0p-53;
      if (t % 3 == 0) {  // exactly on a bin centre (a switching voltage without jitter)
        const int k = static_cast<int>(r * n);
        v = mid + half * (-1.0 + (2.0 * k + 1.0) / n);
      } else if (t % 3 == 1) {
        v = std::min(hi, std::max(lo, v + (r - 0.5) * 0.3 * (hi - lo)));
      }  // else: the same input again
      if (t == 12000) fast.reset(), every.reset();
      const double s = 1.0 + 0.1 * std::sin(0.01 * t);
      worst = std::max(worst, std::fabs(fast.update(v, s) - every.update_every_relay(v, s)));
    }
    EXPECT_LT(worst, 1e-9) << "jitter " << jitter;
  }
}

TEST(SimPhysics, ThirtyMinuteCreepDependsOnHistory) {
  const auto d = simulate("creep", 3, quiet_config());
  const auto& c = d.axis("c");
  std::vector<double> drift30, drift10;
  for (int s = 0; s < 15; ++s) {
    const auto hold = rows(d, s, protocols::Phase::kHold);
    ASSERT_NEAR(hold.size() / kRate, 1800.0, 1.0);
    const double start = c.true_position_nm[hold.front()];
    drift30.push_back(c.true_position_nm[hold.back()] - start);
    drift10.push_back(c.true_position_nm[hold[static_cast<std::size_t>(600 * kRate)]] - start);
    for (auto i : hold) ASSERT_EQ(c.voltage_v[i], c.voltage_v[hold.front()]);
  }
  double max_abs = 0.0;
  int positive = 0, negative = 0;
  for (double x : drift30) {
    max_abs = std::max(max_abs, std::fabs(x));
    positive += x > 20.0;
    negative += x < -20.0;
  }
  // Up to ~10 % of the 2 µm stroke, both directions, set by the history.
  EXPECT_GT(max_abs, 100.0);
  EXPECT_LT(max_abs, 250.0);
  EXPECT_GE(positive, 3);
  EXPECT_GE(negative, 3);
  std::set<long> distinct;
  for (double x : drift30) distinct.insert(std::lround(x / 5.0));
  EXPECT_GE(distinct.size(), 12u);
  // Long memory: the largest drifts are still growing after 10 minutes (log-like, not one time constant).
  for (std::size_t s = 0; s < drift30.size(); ++s)
    if (std::fabs(drift30[s]) > 80.0) {
      EXPECT_GT(std::fabs(drift30[s] - drift10[s]), std::max(8.0, 0.08 * std::fabs(drift30[s]))) << s;
      EXPECT_LT(std::fabs(drift30[s] - drift10[s]), 0.6 * std::fabs(drift30[s])) << s;
    }
}

TEST(SimPhysics, CreepModesStepResponseIsLogLike) {
  auto axis = sim::default_simulator_config().axes[2];
  sim::CreepModes m(axis);
  // Unit step of the hysteretic displacement: equal creep per decade of time (±50 %) from 1 s to 1000 s.
  double t = 0.0, prev_out = 0.0;
  std::vector<double> per_decade;
  double next = 1.0;
  const double dt = 0.05;
  while (t < 1000.0 + 1e-9) {
    const double out = m.update(1.0, dt);
    t += dt;
    if (t >= next - 1e-9) {
      if (next > 1.0) per_decade.push_back(out - prev_out);
      prev_out = out;
      next *= 10.0;
    }
  }
  ASSERT_EQ(per_decade.size(), 3u);
  const double avg = mean(per_decade);
  for (double x : per_decade) EXPECT_NEAR(x, avg, 0.5 * avg);
  EXPECT_GT(avg, 0.03);  // several % of the step per decade
}

TEST(SimEncoder, NoiseSigmaMatchesStudy) {
  sim::ManipulatorSimulator s(sim::default_simulator_config(), 11);
  // Pure encoder error over many positions.
  std::vector<double> err;
  for (int i = 0; i < 40000; ++i) {
    const double v = 80.0 * std::sin(i * 1e-3);
    const auto r = s.step({v, v, v}, 1.0 / kRate);
    err.push_back(r.axes[2].measured_position_nm - r.axes[2].true_position_nm);
  }
  EXPECT_NEAR(stddev(err), 20.79, 0.02 * 20.79);
  EXPECT_NEAR(mean(err), 0.0, 0.5);
}

TEST(SimEncoder, NoiseProtocolRecoversSigmaLikeTheStudy) {
  // Study §4.1.1: settle 3 min at five voltages, zero, record 20 s; σ of the zeroed readings.
  YAML::Node longer;
  longer["record_s"] = 60.0;
  const auto d = simulate("noise", 12, sim::default_simulator_config(), longer);
  std::vector<double> zeroed;
  for (int seg = 0; seg < 5; ++seg) {
    const auto rec = rows(d, seg, protocols::Phase::kRecord);
    std::vector<double> x;
    for (auto i : rec) x.push_back(d.axis("c").position_nm[i]);
    const double m = mean(x);
    for (double v : x) zeroed.push_back(v - m);
  }
  EXPECT_NEAR(stddev(zeroed), 20.79, 0.05 * 20.79);
}

TEST(SimEncoder, QuantisationPerAxis) {
  auto cfg = sim::default_simulator_config();
  for (auto& a : cfg.axes) a.encoder_noise_sigma_nm = 0.0;
  sim::ManipulatorSimulator s(cfg, 13);
  std::set<double> c_values;
  for (int i = 0; i < 3000; ++i) {
    const double v = -80.0 + 160.0 * i / 3000.0;
    const auto r = s.step({v, v, v}, 1.0 / kRate);
    for (int k = 0; k < 3; ++k) {
      const double q = k == 2 ? 20.0 : 250.0;
      const double m = r.axes[k].measured_position_nm;
      EXPECT_NEAR(m / q, std::round(m / q), 1e-9);
      EXPECT_LE(std::fabs(m - r.axes[k].true_position_nm), q / 2 + 1e-9);
    }
    c_values.insert(r.axes[2].measured_position_nm);
  }
  EXPECT_GT(c_values.size(), 80u);  // 2 µm / 20 nm levels are all visited
}

TEST(SimApi, DeterministicStepEqualsRunAndResumes) {
  auto p = protocols::make_protocol("random_walk", YAML::Load("{duration_s: 600}"), kRate, 21);
  const auto prog = p->program();
  const auto cfg = sim::default_simulator_config();
  sim::ManipulatorSimulator a(cfg, 21), b(cfg, 21), c(cfg, 21), other(cfg, 22);
  const auto da = a.run(prog);
  // Same seed, in two chunks (a resumed recording): the same data.
  auto db = b.run(prog.slice(0, 2000));
  db.append(b.run(prog.slice(2000, prog.size())));
  ASSERT_EQ(da.size(), db.size());
  for (std::size_t i = 0; i < da.size(); ++i)
    for (int k = 0; k < 3; ++k) {
      ASSERT_NEAR(da.axes[k].true_position_nm[i], db.axes[k].true_position_nm[i], 1e-6) << i;
      ASSERT_EQ(da.axes[k].position_nm[i], db.axes[k].position_nm[i]) << i;
    }
  // Step API gives the same as run.
  for (std::size_t i = 0; i < 500; ++i) {
    const auto r = c.step({prog.axes[0].voltage_v[i], prog.axes[1].voltage_v[i], prog.axes[2].voltage_v[i]},
                          1.0 / kRate);
    ASSERT_NEAR(r.axes[2].true_position_nm, da.axes[2].true_position_nm[i], 1e-6);
    ASSERT_EQ(r.axes[2].measured_position_nm, da.axes[2].position_nm[i]);
  }
  // Another seed: different noise, same physics.
  const auto dother = other.run(prog);
  int differ = 0;
  for (std::size_t i = 0; i < da.size(); ++i) differ += da.axes[2].position_nm[i] != dother.axes[2].position_nm[i];
  EXPECT_GT(differ, static_cast<int>(da.size() / 2));
  EXPECT_NEAR(da.axes[2].true_position_nm.back(), dother.axes[2].true_position_nm.back(), 1e-9);
}

TEST(SimApi, ClampsVoltagesAndRejectsBadInput) {
  sim::ManipulatorSimulator s(quiet_config(), 1), t(quiet_config(), 1);
  const auto r1 = s.step({200.0, -300.0, 95.0}, 0.1);
  const auto r2 = t.step({80.0, -80.0, 80.0}, 0.1);
  EXPECT_EQ(r1.axes[0].voltage_v, 80.0);
  EXPECT_EQ(r1.axes[1].voltage_v, -80.0);
  EXPECT_EQ(r1.axes[2].true_position_nm, r2.axes[2].true_position_nm);
  EXPECT_THROW(s.step({NAN, 0.0, 0.0}, 0.1), std::invalid_argument);
  EXPECT_THROW(s.step({0.0, 0.0, 0.0}, 0.0), std::invalid_argument);
  EXPECT_THROW(s.step({0.0, 0.0, 0.0}, NAN), std::invalid_argument);
  io::Dataset bad;
  bad.time_s = {0.0, 0.1, 0.1};
  bad.add_axis("c").voltage_v = {0.0, 1.0, 2.0};
  try {
    s.run(bad);
    FAIL() << "non-increasing time accepted";
  } catch (const io::DataError& e) {
    EXPECT_NE(std::string(e.what()).find("row 4, column time_s"), std::string::npos) << e.what();
  }
  bad.time_s = {0.0, 0.1, 0.2};
  bad.axis("c").voltage_v[1] = INFINITY;
  EXPECT_THROW(s.run(bad), io::DataError);
  auto cfg = sim::default_simulator_config();
  cfg.axes[2].creep_gain = 2.0;
  EXPECT_THROW(sim::ManipulatorSimulator(cfg, 1), std::invalid_argument);
}

TEST(SimApi, MissingAxesHeldAtZeroAndOnlyPresentAxesReturned) {
  io::Dataset prog;
  for (int i = 0; i < 100; ++i) prog.time_s.push_back(i / kRate);
  prog.add_axis("c").voltage_v.assign(100, 40.0);
  sim::ManipulatorSimulator s(sim::default_simulator_config(), 3);
  const auto d = s.run(prog);
  ASSERT_EQ(d.axes.size(), 1u);
  EXPECT_EQ(d.axes[0].name, "c");
  EXPECT_TRUE(d.axes[0].has_truth());
  EXPECT_GT(d.axes[0].true_position_nm.back(), 300.0);
  EXPECT_EQ(d.find_aux("temperature_c"), nullptr);
}
