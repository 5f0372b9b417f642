// Protocol generators: the study's voltage patterns, random access, determinism and parameter errors.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <set>

#include "piezo_compensation/protocols/protocol.h"

using namespace piezo;
using protocols::Phase;

namespace {
constexpr double kRate = 11.0;

std::unique_ptr<protocols::Protocol> make(const std::string& name, const std::string& yaml = "{}",
                                          std::uint64_t seed = 1) {
  return protocols::make_protocol(name, YAML::Load(yaml), kRate, seed);
}

std::string error_of(const std::string& name, const std::string& yaml) {
  try {
    make(name, yaml);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST(Protocols, ConfigFileMirrorsDefaults) {
  const std::string path = std::string(PIEZO_SOURCE_DIR) + "/config/protocols.yaml";
  for (const auto& name : protocols::protocol_names()) {
    SCOPED_TRACE(name);
    const YAML::Node file = protocols::load_protocol_parameters(path, name);
    ASSERT_TRUE(file.IsMap());
    const YAML::Node def = protocols::default_protocol_parameters()[name];
    ASSERT_EQ(file.size(), def.size());
    for (const auto& kv : def) {
      const std::string key = kv.first.as<std::string>();
      ASSERT_TRUE(file[key]) << key;
      if (kv.second.IsScalar()) {
        EXPECT_EQ(file[key].as<double>(), kv.second.as<double>()) << key;
      } else if (kv.second.IsSequence()) {
        ASSERT_EQ(file[key].size(), kv.second.size()) << key;
        for (std::size_t i = 0; i < kv.second.size(); ++i)
          EXPECT_EQ(file[key][i].as<double>(), kv.second[i].as<double>()) << key;
      }
    }
  }
}

TEST(Protocols, NoiseHoldsFiveLevels) {
  const auto p = make("noise");
  EXPECT_EQ(p->size(), static_cast<std::size_t>(5 * 200 * kRate));
  const io::Dataset d = p->program();
  std::map<int, std::set<double>> levels;
  std::map<int, int> record_samples;
  for (std::size_t i = 0; i < d.size(); ++i) {
    levels[d.segment[i]].insert(d.axis("c").voltage_v[i]);
    record_samples[d.segment[i]] += d.phase[i] == static_cast<int>(Phase::kRecord);
    EXPECT_EQ(d.axis("a").voltage_v[i], d.axis("c").voltage_v[i]);
  }
  const double expect[5] = {-80, -40, 0, 40, 80};
  ASSERT_EQ(levels.size(), 5u);
  for (int s = 0; s < 5; ++s) {
    ASSERT_EQ(levels[s].size(), 1u);
    EXPECT_EQ(*levels[s].begin(), expect[s]);
    EXPECT_EQ(record_samples[s], static_cast<int>(20 * kRate));
  }
  // Settle first, then record.
  EXPECT_EQ(d.phase[0], static_cast<int>(Phase::kSettle));
  EXPECT_NEAR(d.time_s[1] - d.time_s[0], 1.0 / kRate, 1e-12);
}

TEST(Protocols, RandomWalkBoundedTrendingWithPauses) {
  const auto p = make("random_walk", "{duration_s: 36000}", 7);
  const io::Dataset d = p->program();
  ASSERT_EQ(d.size(), static_cast<std::size_t>(36000 * kRate));
  for (const auto& ax : d.axes) {
    const auto [lo, hi] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
    EXPECT_GE(*lo, -80.0);
    EXPECT_LE(*hi, 80.0);
    EXPECT_LT(*lo, -70.0) << ax.name;  // covers the range: deep valleys and high peaks
    EXPECT_GT(*hi, 70.0) << ax.name;
    // Slow and fast motion: both small and large steps are common.
    int slow = 0, fast = 0;
    for (std::size_t i = 1; i < d.size(); ++i) {
      const double s = std::fabs(ax.voltage_v[i] - ax.voltage_v[i - 1]);
      if (d.phase[i] == static_cast<int>(Phase::kExcite)) slow += s < 0.1, fast += s > 0.5;
    }
    EXPECT_GT(slow, static_cast<int>(d.size() / 5)) << ax.name;
    EXPECT_GT(fast, static_cast<int>(d.size() / 50)) << ax.name;
  }
  EXPECT_LT(std::fabs(d.axis("c").voltage_v.back()), 1e-6);  // ends back at 0 V
  // Independent walks on the three axes.
  double same = 0;
  for (std::size_t i = 0; i < d.size(); ++i) same += d.axis("a").voltage_v[i] == d.axis("c").voltage_v[i];
  EXPECT_LT(same, 0.2 * d.size());
  // Pauses: held voltage on all axes, several of them, lasting 20 … 300 s.
  std::vector<std::size_t> pauses;
  std::size_t run = 0;
  for (std::size_t i = 0; i < d.size(); ++i) {
    if (d.phase[i] == static_cast<int>(Phase::kHold)) {
      ++run;
      if (i > 0 && d.phase[i - 1] == static_cast<int>(Phase::kHold)) {
        for (const auto& ax : d.axes) ASSERT_EQ(ax.voltage_v[i], ax.voltage_v[i - 1]);
      }
    } else if (run) {
      pauses.push_back(run);
      run = 0;
    }
  }
  EXPECT_GE(pauses.size(), 20u);
  for (auto n : pauses) {
    EXPECT_GE(n / kRate, 20.0 - 1.0);
    EXPECT_LE(n / kRate, 300.0 + 1.0);
  }
}

TEST(Protocols, SweepFractionsAndStepSizes) {
  const auto p = make("sweep");
  const io::Dataset d = p->program();
  std::map<int, std::pair<double, double>> range;
  std::map<int, double> max_step;
  for (std::size_t i = 1; i < d.size(); ++i) {
    if (d.phase[i] != static_cast<int>(Phase::kSweep)) continue;
    const double v = d.axis("c").voltage_v[i];
    auto& r = range.try_emplace(d.segment[i], v, v).first->second;
    r.first = std::min(r.first, v), r.second = std::max(r.second, v);
    if (d.segment[i - 1] == d.segment[i])
      max_step[d.segment[i]] = std::max(max_step[d.segment[i]], std::fabs(v - d.axis("c").voltage_v[i - 1]));
  }
  // 7 + 3 + 2 partial windows (25, 50, 75 % of the range), then 5 full-range sweeps.
  ASSERT_EQ(range.size(), 17u);
  for (int s = 0; s < 7; ++s) EXPECT_NEAR(range[s].second - range[s].first, 40.0, 1e-4);
  for (int s = 7; s < 10; ++s) EXPECT_NEAR(range[s].second - range[s].first, 80.0, 1e-4);
  for (int s = 10; s < 12; ++s) EXPECT_NEAR(range[s].second - range[s].first, 120.0, 1e-4);
  EXPECT_NEAR(range[0].first, -80.0, 1e-4);
  EXPECT_NEAR(range[6].second, 80.0, 1e-4);
  const double steps[5] = {1.25, 0.5, 0.1, 0.05, 0.01};
  for (int s = 12; s < 17; ++s) {
    EXPECT_NEAR(range[s].first, -80.0, 1e-4);
    EXPECT_NEAR(range[s].second, 80.0, 1e-4);
    EXPECT_NEAR(max_step[s], steps[s - 12], 1e-4) << s;
  }
}

TEST(Protocols, CreepScenariosEndAtDifferentVoltagesFromBothSides) {
  const auto p = make("creep", "{}", 3);
  EXPECT_EQ(p->size(), static_cast<std::size_t>(15 * 3600 * kRate));
  const io::Dataset d = p->program();
  std::set<long> holds;
  int from_below = 0, from_above = 0;
  for (int s = 0; s < 15; ++s) {
    std::size_t first = SIZE_MAX, last = 0;
    for (std::size_t i = 0; i < d.size(); ++i)
      if (d.segment[i] == s && d.phase[i] == static_cast<int>(Phase::kHold)) first = std::min(first, i), last = i;
    ASSERT_NE(first, SIZE_MAX);
    EXPECT_NEAR((last - first + 1) / kRate, 1800.0, 0.5);
    const double v = d.axis("c").voltage_v[first];
    for (std::size_t i = first; i <= last; ++i) ASSERT_EQ(d.axis("c").voltage_v[i], v);
    holds.insert(std::lround(v));
    (d.axis("c").voltage_v[first - 2] < v ? from_below : from_above)++;  // first − 1 is already on target
    EXPECT_GT(std::fabs(v - d.axis("c").voltage_v[first - static_cast<std::size_t>(5 * kRate)]), 1.0);
  }
  EXPECT_GE(holds.size(), 13u);
  EXPECT_GE(from_below, 5);
  EXPECT_GE(from_above, 5);
}

TEST(Protocols, SawtoothAmplitudeIncreases) {
  const auto p = make("sawtooth");
  const io::Dataset d = p->program();
  std::map<int, double> peak;
  for (std::size_t i = 0; i < d.size(); ++i) peak[d.segment[i]] = std::max(peak[d.segment[i]], d.axis("c").voltage_v[i]);
  ASSERT_EQ(peak.size(), 8u);
  EXPECT_NEAR(peak[0], 10.0, 1e-4);
  EXPECT_NEAR(peak[7], 80.0, 1e-4);
  for (int s = 1; s < 8; ++s) EXPECT_GT(peak[s], peak[s - 1]);
  for (std::size_t i = 1; i < d.size(); ++i)
    ASSERT_LE(std::fabs(d.axis("c").voltage_v[i] - d.axis("c").voltage_v[i - 1]), 4.0 / kRate + 1e-4);
}

TEST(Protocols, PlanIsThreeWalksPlusCreepSet) {
  const auto p = make("plan", "{train_s: 3600, validation_s: 1800, test_s: 1800, creep: {scenarios: 3}}", 5);
  const io::Dataset d = p->program();
  std::map<int, std::size_t> count;
  for (int s : d.segment) ++count[s];
  ASSERT_EQ(count.size(), 6u);
  EXPECT_EQ(count[0], static_cast<std::size_t>(3600 * kRate));
  EXPECT_EQ(count[1], static_cast<std::size_t>(1800 * kRate));
  EXPECT_EQ(count[2], static_cast<std::size_t>(1800 * kRate));
  for (int s = 3; s < 6; ++s) EXPECT_EQ(count[s], static_cast<std::size_t>(3600 * kRate));
  // The default plan: ~26 h of walks plus 15 h of creep.
  const auto full = make("plan");
  EXPECT_NEAR(full->size() / kRate / 3600.0, 26.0 + 15.0, 0.01);
}

TEST(Protocols, RandomAccessDeterministicAndRegenerable) {
  const auto p = make("random_walk", "{duration_s: 1000}", 9);
  const auto q = make("random_walk", "{duration_s: 1000}", 9);
  const auto r = make("random_walk", "{duration_s: 1000}", 10);
  const io::Dataset whole = p->program();
  const io::Dataset tail = p->program(5000, 6000);
  ASSERT_EQ(tail.size(), 1000u);
  EXPECT_NEAR(tail.time_s[0], 5000 / kRate, 1e-9);
  for (std::size_t i = 0; i < tail.size(); ++i)
    for (int k = 0; k < 3; ++k) ASSERT_EQ(tail.axes[k].voltage_v[i], whole.axes[k].voltage_v[5000 + i]);
  int differ = 0;
  for (std::size_t i = 0; i < p->size(); ++i) {
    ASSERT_EQ(p->at(i).voltage_v, q->at(i).voltage_v);
    differ += p->at(i).voltage_v != r->at(i).voltage_v;
  }
  EXPECT_GT(differ, 1000);
  EXPECT_THROW(p->at(p->size()), std::out_of_range);
  // parameters() regenerates the same program.
  const YAML::Node par = YAML::Load(YAML::Dump(p->parameters()));
  const auto again = protocols::make_protocol(par["protocol"].as<std::string>(), par["parameters"],
                                              par["sample_rate_hz"].as<double>(), par["seed"].as<std::uint64_t>());
  ASSERT_EQ(again->size(), p->size());
  for (std::size_t i = 0; i < p->size(); i += 97) ASSERT_EQ(again->at(i).voltage_v, p->at(i).voltage_v);
}

TEST(Protocols, BadParametersAreNamed) {
  EXPECT_NE(error_of("noise", "{settle_min: 3}").find("noise.settle_min: unknown key"), std::string::npos);
  EXPECT_NE(error_of("noise", "{settle_s: abc}").find("noise.settle_s"), std::string::npos);
  EXPECT_NE(error_of("noise", "{levels_v: 5}").find("noise.levels_v: expected a list"), std::string::npos);
  EXPECT_NE(error_of("random_walk", "{duration_s: -1}").find("random_walk.duration_s"), std::string::npos);
  EXPECT_NE(error_of("plan", "{creep: {random_walk: {bound: 3}}}").find("plan.creep.random_walk.bound"),
            std::string::npos);
  EXPECT_NE(error_of("sawtooth", "{teeth: 0}").find("sawtooth.teeth"), std::string::npos);
  EXPECT_NE(error_of("spiral", "{}").find("valid: noise, random_walk, sweep, creep, plan, sawtooth"),
            std::string::npos);
  EXPECT_EQ(protocols::phase_from_name("hold"), Phase::kHold);
  EXPECT_THROW(protocols::phase_from_name("wait"), std::invalid_argument);
}
