#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/features/feature_stream.h"

using namespace piezo;
using features::FeatureDef;
using features::FeatureSpec;
using features::FeatureStream;

namespace {

FeatureDef def(const std::string& type) {
  FeatureDef f;
  f.type = type;
  return f;
}

struct Series {
  std::vector<double> v, d, aux;
};

Series make_series(std::size_t n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0, 3);
  Series s;
  double x = 0;
  for (std::size_t i = 0; i < n; ++i) {
    x += g(rng);
    s.v.push_back(x);
    s.d.push_back(20 * x + 5 * g(rng));
    s.aux.push_back(std::sin(0.01 * i) + 0.1 * g(rng));
  }
  return s;
}

// Brute-force values straight from the definitions; history before sample 0 is "at rest" at v[0], d[0].
double vat(const Series& s, long i) { return s.v[std::max(0L, i)]; }
double dat(const Series& s, long i) { return s.d[std::max(0L, i)]; }

}  // namespace

TEST(FeatureStream, EveryTypeMatchesItsDefinition) {
  const double rate = 10.0;
  FeatureSpec spec;
  FeatureDef f;
  spec.features.push_back(def("voltage"));
  spec.features.push_back(def("voltage_step"));
  f = def("step_sum"), f.window_s = 0.7, spec.features.push_back(f);                      // 7 samples
  f = def("exp_sum"), f.window_s = 1.2, f.decay = 0.9, spec.features.push_back(f);        // 12 samples
  f = def("lowpass"), f.time_constant_s = 2.0, spec.features.push_back(f);
  f = def("play"), f.threshold_v = 4.0, spec.features.push_back(f);
  f = def("stop"), f.threshold_v = 4.0, spec.features.push_back(f);
  f = def("play_lowpass"), f.threshold_v = 2.0, f.time_constant_s = 1.5, spec.features.push_back(f);
  f = def("lagged_position"), f.lag_s = 0.3, spec.features.push_back(f);                   // D_{t-3}
  f = def("position_mean"), f.window_s = 0.5, spec.features.push_back(f);                  // D_{t-5..t-1}
  f = def("aux"), f.signal = "temp", f.lag_s = 0.2, spec.features.push_back(f);
  spec.features.push_back(def("voltage_sq"));
  f = def("play_hinge"), f.threshold_v = 3.0, f.knot_v = 2.0, spec.features.push_back(f);
  ASSERT_EQ(spec.aux_signals(), std::vector<std::string>{"temp"});
  ASSERT_TRUE(spec.uses_positions());

  const Series s = make_series(400, 3);
  FeatureStream fs(spec, rate);
  fs.reset(s.v[0], s.d[0]);
  std::vector<double> x(fs.size());
  const double a_lp = std::exp(-0.1 / 2.0), a_pl = std::exp(-0.1 / 1.5);
  double lp = s.v[0], play = s.v[0], pl_in = s.v[0], pl = s.v[0], hinge_play = s.v[0];
  for (long t = 0; t < static_cast<long>(s.v.size()); ++t) {
    double aux_now = s.aux[t];
    features::ModelInput in{s.v[t], &aux_now};
    fs.compute(in, x.data());
    const double v = s.v[t];
    EXPECT_DOUBLE_EQ(x[0], v);
    EXPECT_NEAR(x[1], v - vat(s, t - 1), 1e-12);
    EXPECT_NEAR(x[2], v - vat(s, t - 7), 1e-12);
    double es = 0;
    for (int k = 0; k < 12; ++k) es += std::pow(0.9, k) * vat(s, t - k);
    EXPECT_NEAR(x[3], es, 1e-9 * (1 + std::abs(es)));
    lp = a_lp * lp + (1 - a_lp) * v;
    EXPECT_NEAR(x[4], lp, 1e-9);
    play = std::max(v - 4.0, std::min(v + 4.0, play));
    EXPECT_NEAR(x[5], play, 1e-12);
    EXPECT_NEAR(x[6], v - play, 1e-12);
    pl_in = std::max(v - 2.0, std::min(v + 2.0, pl_in));
    pl = a_pl * pl + (1 - a_pl) * pl_in;
    EXPECT_NEAR(x[7], pl, 1e-9);
    EXPECT_DOUBLE_EQ(x[8], dat(s, t - 3));
    double m = 0;
    for (int k = 1; k <= 5; ++k) m += dat(s, t - k);
    EXPECT_NEAR(x[9], m / 5, 1e-9);
    EXPECT_DOUBLE_EQ(x[10], s.aux[std::max(0L, t - 2)]);
    EXPECT_DOUBLE_EQ(x[11], v * v);
    hinge_play = std::max(v - 3.0, std::min(v + 3.0, hinge_play));
    EXPECT_NEAR(x[12], std::max(hinge_play - 2.0, 0.0), 1e-12);
    fs.commit(in, s.d[t]);
  }
}

TEST(FeatureStream, CausalTheCurrentPositionNeverEntersTheCurrentFeatures) {
  const FeatureSpec spec = features::candidate_features();
  const Series s = make_series(300, 5);
  FeatureStream a(spec, 11.0), b(spec, 11.0);
  a.reset(s.v[0], s.d[0]);
  b.reset(s.v[0], s.d[0]);
  std::vector<double> xa(a.size()), xb(b.size());
  for (std::size_t t = 0; t <= 151; ++t) {
    features::ModelInput in{s.v[t], nullptr};
    a.compute(in, xa.data());
    b.compute(in, xb.data());
    if (t <= 150) {  // D_150 differs, but only after it is committed: features of sample 150 agree
      for (std::size_t j = 0; j < xa.size(); ++j) ASSERT_EQ(xa[j], xb[j]) << "t=" << t << " " << spec.features[j].name();
    } else {  // ...and the lagged position D_{t-1} of the next sample sees it
      EXPECT_DOUBLE_EQ(xb[0] - xa[0], 1000.0);
    }
    a.commit(in, s.d[t]);
    b.commit(in, t == 150 ? s.d[t] + 1000.0 : s.d[t]);
  }
}

TEST(FeatureStream, WindowsAreSecondsAtAnyRate) {
  FeatureSpec spec;
  FeatureDef f = def("step_sum");
  f.window_s = 2.0;
  spec.features.push_back(f);
  for (double rate : {5.0, 11.0, 20.0}) {
    FeatureStream fs(spec, rate);
    fs.reset(0, 0);
    const long w = std::lround(2.0 * rate);
    double x = 0;
    for (long t = 0; t <= w + 3; ++t) {
      features::ModelInput in{double(t), nullptr};
      fs.compute(in, &x);
      EXPECT_DOUBLE_EQ(x, t - std::max(0L, t - w)) << rate << " Hz, t=" << t;
      fs.commit(in, 0);
    }
  }
}

TEST(FeatureStream, RestStateIsStationaryAndStandardisationApplies) {
  FeatureSpec spec = features::physics_features();
  spec.mean.assign(spec.size(), 1.0);
  spec.scale.assign(spec.size(), 2.0);
  FeatureStream fs(spec, 11.0);
  fs.reset(12.5, 300.0);
  std::vector<double> first(fs.size()), x(fs.size());
  features::ModelInput in{12.5, nullptr};
  fs.compute(in, first.data());
  for (int t = 0; t < 50; ++t) {
    fs.compute(in, x.data());
    for (std::size_t j = 0; j < x.size(); ++j) EXPECT_NEAR(x[j], first[j], 1e-9) << spec.features[j].name();
    fs.commit(in, 300.0);
  }
  EXPECT_NEAR(first[0], (12.5 - 1.0) / 2.0, 1e-12);  // V standardised
  FeatureStream copy = fs;  // deep copy continues identically
  copy.compute(in, x.data());
  EXPECT_EQ(x, first);
}

TEST(FeatureSpecYaml, RoundTripAndClearErrors) {
  FeatureSpec spec = features::study_features();
  FeatureDef hinge = def("play_hinge");
  hinge.threshold_v = 4.5, hinge.knot_v = -12.5;
  spec.features.push_back(hinge);
  spec.mean.assign(spec.size(), 0.5);
  spec.scale.assign(spec.size(), 3.0);
  const FeatureSpec back = FeatureSpec::from_yaml(YAML::Load(YAML::Dump(spec.to_yaml())));
  ASSERT_EQ(back.size(), spec.size());
  for (std::size_t j = 0; j < spec.size(); ++j) EXPECT_EQ(back.features[j].name(), spec.features[j].name());
  EXPECT_EQ(back.features.back().knot_v, -12.5);
  EXPECT_EQ(back.mean, spec.mean);
  EXPECT_EQ(back.scale, spec.scale);

  auto err = [](const std::string& yaml) {
    try {
      FeatureSpec::from_yaml(YAML::Load(yaml));
    } catch (const std::runtime_error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(err("features: [{type: wiggle}]").find("features[0].type: unknown feature type 'wiggle'"), std::string::npos);
  EXPECT_NE(err("features: [{window_s: 3}]").find("features[0].type: missing"), std::string::npos);
  EXPECT_NE(err("features: [{type: step_sum, window_s: abc}]").find("features[0].window_s"), std::string::npos);
  EXPECT_NE(err("features: [{type: voltage}]\nmean: [1, 2]\nscale: [1, 2]").find("mean/scale"), std::string::npos);
  EXPECT_NE(err("features: [{type: voltage}]\nmean: [1]\nscale: [0]").find("scale[0]"), std::string::npos);
  EXPECT_NE(err("nothing: 1").find("features: missing"), std::string::npos);
  EXPECT_NE(err("features: [{type: play_hinge, threshold_v: 2}]").find("features[0].knot_v: missing"), std::string::npos);
  EXPECT_NE(err("features: [{type: voltage}, {type: play_hinge, threshold_v: 2, knot: 1}]").find("features[1].knot: unknown key"),
            std::string::npos);
  // Values that only fail when the stream is built (at a given rate) name feature and key.
  auto stream_err = [](const FeatureDef& f) {
    FeatureSpec one;
    one.features.push_back(f);
    try {
      FeatureStream fs(one, 11.0);
    } catch (const std::runtime_error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  FeatureDef lag = def("lagged_position");
  lag.lag_s = 0.01;  // 0 samples at 11 Hz: would read the target
  EXPECT_NE(stream_err(lag).find("features[0] (lagged_position).lag_s"), std::string::npos) << stream_err(lag);
  FeatureDef h = def("play_hinge");
  h.threshold_v = 1.0, h.knot_v = std::nan("");
  EXPECT_NE(stream_err(h).find("features[0] (play_hinge).knot_v"), std::string::npos) << stream_err(h);
}

TEST(FeatureSets, StudySetIsCausalAndNamed) {
  const FeatureSpec s = features::study_features();
  ASSERT_EQ(s.size(), 6u);
  FeatureStream fs(s, 11.0);  // 10/11 s → 10 samples
  fs.reset(0, 0);
  std::vector<double> x(6);
  for (int t = 0; t < 12; ++t) {
    features::ModelInput in{0.0, nullptr};
    fs.compute(in, x.data());
    EXPECT_DOUBLE_EQ(x[4], t >= 10 ? double(t - 10) : 0.0);  // D_{t-10}
    fs.commit(in, double(t));
  }
  EXPECT_GT(features::candidate_features().size(), 30u);
  EXPECT_FALSE(features::physics_features().uses_positions());
  EXPECT_THROW(features::named_features("nope"), std::runtime_error);
}

// The candidates placed on a recording keep only what it can identify: no time constant, window or lag over a
// third of its length (a 20-s recording's lasso had weighted 2-h and 8-h low-passes ±10⁸ nm/V against each other).
TEST(FeatureSpecs, CandidatesOnShortDataKeepOnlyWhatItCanIdentify) {
  const FeatureSpec all = features::candidate_features();
  io::DataSpan span;
  span.voltage_min_v = 0, span.voltage_max_v = 100, span.duration_s = 20.0, span.sample_rate_hz = 5000;
  const FeatureSpec kept = features::candidate_features(&span);
  EXPECT_LT(kept.size(), all.size());
  bool has_voltage = false;
  for (const auto& f : kept.features) {
    EXPECT_LE(f.time_constant_s, 20.0 / 3) << f.name();
    EXPECT_LE(f.window_s, 20.0 / 3) << f.name();
    EXPECT_LE(f.lag_s, 20.0 / 3) << f.name();
    has_voltage |= f.type == "voltage";
  }
  EXPECT_TRUE(has_voltage);
  span.duration_s = 1e7;  // a long recording keeps them all, and adds plays and hinges placed on its voltage span:
  span.voltage_min_v = -80, span.voltage_max_v = 20;  // plays 5, 15, 30 V wide; knots their outputs reach (10 of 12)
  const FeatureSpec placed = features::candidate_features(&span);
  ASSERT_EQ(placed.size(), all.size() + 13);
  for (std::size_t j = 0; j < 3; ++j) {
    EXPECT_EQ(placed.features[all.size() + j].type, "play");
    const double widths_v[] = {5, 15, 30};
    EXPECT_NEAR(placed.features[all.size() + j].threshold_v, widths_v[j], 1e-9);
  }
  const std::vector<std::pair<double, double>> hinges = {{5, -60}, {5, -40}, {5, -20}, {5, 0},   {15, -60},
                                                         {15, -40}, {15, -20}, {15, 0}, {30, -40}, {30, -20}};
  for (std::size_t j = 0; j < hinges.size(); ++j) {
    const auto& h = placed.features[all.size() + 3 + j];
    EXPECT_EQ(h.type, "play_hinge");
    EXPECT_NEAR(h.threshold_v, hinges[j].first, 1e-9) << j;
    EXPECT_NEAR(h.knot_v, hinges[j].second, 1e-9) << j;
  }
}
