// The "augmented" model kind: streaming terms are causal, the model round-trips through YAML, clones keep state,
// and a broken model node gives one clear error.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "test_residual_common.h"

namespace pm = piezo::models;
namespace pa = piezo::analysis;

namespace {
pm::EffectTerm make(const std::string& type, const std::string& signal, std::size_t k, double lag_s = 0, double tau_s = 0) {
  pm::EffectTerm t;
  t.type = type;
  t.signal = signal;
  t.lag_s = lag_s;
  t.time_constant_s = tau_s;
  t.center.assign(k, 0.0);
  t.scale.assign(k, 1.0);
  t.weight.assign(k, 1.0);
  return t;
}

// Writes `header` and a C program `main_c` that includes it, compiles them with the C compiler (warnings are
// errors), runs the program on `input` and puts what it printed into `out`.
void run_exported_c(const std::string& name, const std::string& header, const std::string& main_c,
                    const std::string& input, std::string& out) {
  const std::string dir = ::testing::TempDir();
  const std::string hdr = dir + name + ".h", src = dir + name + ".c", exe = dir + name, in = dir + name + "_in.txt";
  std::ofstream(hdr) << header;
  std::ofstream(src) << "#include <stdio.h>\n#include \"" << hdr << "\"\n" << main_c;
  std::ofstream(in) << input;
  const std::string cc = PIEZO_C_COMPILER;
  const std::string build_cmd = cc + " -std=c99 -Wall -Wextra -Werror -pedantic -O2 -o " + exe + " " + src + " -lm 2>&1";
  FILE* p = popen(build_cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  out.clear();
  char buf[4096];
  while (std::size_t n = fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  ASSERT_EQ(pclose(p), 0) << out;
  p = popen((exe + " < " + in).c_str(), "r");
  ASSERT_NE(p, nullptr);
  out.clear();
  while (std::size_t n = fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  ASSERT_EQ(pclose(p), 0);
}
}  // namespace

TEST(ResidualAugmented, LaggedTermReadsOnlyThePast) {
  // lag 2 samples at 1 Hz: the regressor at sample t is the signal at t-2 (the first value until then).
  pm::EffectTermStream s({make("linear", "temperature_c", 1, 2.0)}, 1.0);
  ASSERT_EQ(s.column_signals().size(), 1u);
  const double values[] = {10, 11, 12, 13, 14};
  const double expect[] = {10, 10, 10, 11, 12};
  for (int i = 0; i < 5; ++i) {
    double z = 0;
    s.raw(0.0, 0.0, &values[i], &z);
    EXPECT_DOUBLE_EQ(z, expect[i]) << "sample " << i;
    s.commit(0.0, 0.0, &values[i]);
  }
}

TEST(ResidualAugmented, RateAndPlayAndSinCos) {
  std::vector<pm::EffectTerm> terms = {make("rate", "voltage", 3), make("sincos", "position", 2)};
  terms[1].period = 100.0;
  pm::EffectTermStream s2(terms, 1.0);
  double z[5];
  s2.raw(1.0, 25.0, nullptr, z);  // first sample: no step yet
  EXPECT_DOUBLE_EQ(z[0], 0.0);
  s2.commit(1.0, 25.0, nullptr);
  s2.raw(-2.0, 25.0, nullptr, z);
  EXPECT_DOUBLE_EQ(z[0], -3.0);
  EXPECT_DOUBLE_EQ(z[1], 3.0);
  EXPECT_DOUBLE_EQ(z[2], -9.0);
  // position terms read the corrected position: x + offset + non-position corrections (-3 + 3 - 9 = -9)
  EXPECT_NEAR(z[3], std::sin(6.283185307179586 * (25.0 - 9.0) / 100.0), 1e-12);
  EXPECT_NEAR(z[4], std::cos(6.283185307179586 * (25.0 - 9.0) / 100.0), 1e-12);

  pm::EffectTerm p = make("play", "voltage", 1);
  p.threshold = 2.0;
  pm::EffectTermStream sp({p}, 1.0);
  const double v[] = {0, 1, 3, 5, 4, 2, 1};
  const double expect[] = {0, 0, 1, 3, 3, 3, 3};
  for (int i = 0; i < 7; ++i) {
    double y;
    sp.raw(v[i], 0.0, nullptr, &y);
    EXPECT_DOUBLE_EQ(y, expect[i]) << "sample " << i;
    sp.commit(v[i], 0.0, nullptr);
  }
}

TEST(ResidualAugmented, LowPassedRateHasNoRiseFromZero) {
  // A steady ramp of 0.5 V per sample, low-passed over 240 s at 1 Hz: the debiased filter reads 0.5 V (and
  // 0.25 V² signed) from the first step on. Started at zero and not debiased it rose over ~3τ, a start-up decay
  // the loop's fit traded against the base's start transients (docs/validation/residual-loop.md, "Live loop").
  pm::EffectTermStream s({make("rate", "voltage", 3, 0.0, 240.0)}, 1.0);
  double z[3];
  for (int i = 0; i < 50; ++i) {
    const double v = 0.5 * i;
    s.raw(v, 0.0, nullptr, z);
    if (i == 0) {
      EXPECT_DOUBLE_EQ(z[1], 0.0) << "no step before the second sample";
    } else {
      EXPECT_NEAR(z[0], 0.5, 1e-12) << "sample " << i;
      EXPECT_NEAR(z[1], 0.5, 1e-12) << "sample " << i;
      EXPECT_NEAR(z[2], 0.25, 1e-12) << "sample " << i;
    }
    s.commit(v, 0.0, nullptr);
  }
}

TEST(ResidualAugmented, RoundTripCloneAndStreamingEqualsFreshRun) {
  piezo::test::register_test_kind();
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kAuxTemperature, 0.2, 11);
  auto base = piezo::test::LowpassLinearModel::fit(d, "c", d.size());
  pm::EffectTerm t1 = make("linear", "temperature_c", 1, 1.0, 30.0);
  t1.weight = {40.0};
  t1.center = {22.0};
  pm::EffectTerm t2 = make("sincos", "position", 2);
  t2.period = 333.0;
  t2.weight = {5.0, -3.0};
  pm::EffectTerm t3 = make("linear", "time_s", 1);
  t3.weight = {0.01};
  pm::EffectTerm t4 = make("linear", "a_voltage_v", 1, 0.5);
  t4.weight = {2.0};
  pm::AugmentedModel m(base->clone(), {t1, t2, t3, t4}, 7.0, 11.0);
  EXPECT_EQ(m.aux_inputs(), (std::vector<std::string>{"temperature_c", "time_s", "a_voltage_v"}));

  const std::vector<double> p1 = pm::stream_model(m, d, "c").prediction;
  const YAML::Node node = YAML::Load(YAML::Dump(m.to_yaml()));
  pm::ModelPtr loaded = pm::model_kind("augmented").load(node);
  const std::vector<double> p2 = pm::stream_model(*loaded, d, "c").prediction;
  ASSERT_EQ(p1.size(), p2.size());
  double worst = 0;
  for (std::size_t i = 0; i < p1.size(); ++i) worst = std::max(worst, std::fabs(p1[i] - p2[i]));
  EXPECT_LT(worst, 1e-6);
  // The correction really contributes (the model is not the base).
  auto b2 = base->clone();
  const std::vector<double> pb = pm::stream_model(*b2, d, "c").prediction;
  EXPECT_GT(std::fabs(p1[100] - pb[100]), 1.0);

  // A clone taken half-way continues exactly like the original.
  pm::InputResolver cols(d, m.aux_inputs(), "c");
  m.reset(d.axis("c").voltage_v[0], d.axis("c").position_nm[0]);
  std::unique_ptr<pm::Model> half;
  std::vector<double> aux(cols.size());
  for (std::size_t i = 0; i < 2000; ++i) {
    cols.fill(i, aux.data());
    const pm::ModelInput in{d.axis("c").voltage_v[i], aux.data()};
    if (i == 1000) half = m.clone();
    if (i >= 1000) {
      EXPECT_DOUBLE_EQ(half->predict(in), m.predict(in));
    }
    if (half && i >= 1000) half->commit(in, m.predict(in));
    m.commit(in, m.predict(in));
  }
}

TEST(ResidualAugmented, BrokenNodesGiveOneClearError) {
  piezo::test::register_test_kind();
  auto load = [](const std::string& yaml) { return pm::model_kind("augmented").load(YAML::Load(yaml)); };
  const std::string base = "base_kind: residual_test_lowpass_linear\nbase: {w0: 0, w1: 1, w2: 0, fs: 11}\n"
                           "sample_rate_hz: 11\noffset_nm: 0\n";
  EXPECT_NO_THROW(load(base + "terms: []"));
  auto msg = [&](const std::string& yaml) {
    try {
      load(yaml);
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(msg(base + "terms: [{type: linear, signal: voltage, center: [0], scale: [1]}]").find("weight"), std::string::npos);
  EXPECT_NE(msg(base + "terms: [{type: cubic, signal: voltage, center: [0], scale: [1], weight: [1]}]").find("unknown type"),
            std::string::npos);
  EXPECT_NE(msg(base + "terms: [{type: linear, signal: voltage, colour: red, center: [0], scale: [1], weight: [1]}]")
                .find("unknown key 'colour'"),
            std::string::npos);
  EXPECT_NE(msg(base + "terms: [{type: sincos, signal: position, center: [0, 0], scale: [1, 1], weight: [1, 1]}]").find("period"),
            std::string::npos);
  EXPECT_NE(msg("base_kind: nosuchkind\nbase: {}\nsample_rate_hz: 11\noffset_nm: 0\nterms: []").find("nosuchkind"),
            std::string::npos);
  EXPECT_NE(msg(base).find("missing key 'terms'"), std::string::npos);
  EXPECT_NE(msg(base + "terms: [{type: linear, signal: voltage, center: [.nan], scale: [1], weight: [1]}]").find("non-finite"),
            std::string::npos);
}

TEST(ResidualAugmented, PositionsAndTruthAreNeverInputs) {
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.05, 2);
  EXPECT_THROW(pm::InputResolver(d, {"c_true_position_nm"}, "c"), piezo::io::DataError);
  EXPECT_THROW(pm::InputResolver(d, {"a_true_position_nm"}, "c"), piezo::io::DataError);
  EXPECT_THROW(pm::InputResolver(d, {"c_position_nm"}, "c"), piezo::io::DataError);
  EXPECT_THROW(pm::InputResolver(d, {"pressure_pa"}, "c"), piezo::io::DataError);
  EXPECT_EQ(pm::InputResolver(d, {"a_voltage_v", "time_s", "temperature_c", "a_position_nm"}, "c").size(), 4u);
}

TEST(ResidualAugmented, WarmStartContinuesTheStreamAcrossATimeSplit) {
  piezo::test::register_test_kind();
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.1, 4);
  const std::size_t k = d.size() / 2;
  const piezo::io::Dataset a = d.slice(0, k), b = d.slice(k, d.size()), gap = d.slice(k + 5, d.size());
  EXPECT_TRUE(pa::continues_in_time(a, b));
  EXPECT_FALSE(pa::continues_in_time(a, gap));
  EXPECT_FALSE(pa::continues_in_time(b, a));
  auto m = piezo::test::LowpassLinearModel::fit(d, "c", d.size());
  auto m2 = m->clone();
  const auto whole = pm::stream_model(*m, d, "c").prediction;
  pm::StreamOptions so;
  so.warmup = &a;
  const auto tail = pm::stream_model(*m2, b, "c", so).prediction;
  ASSERT_EQ(tail.size(), b.size());
  for (std::size_t i = 0; i < tail.size(); i += 97) EXPECT_DOUBLE_EQ(tail[i], whole[k + i]);
}

// The C99 export of an augmented model with every term type (gains on the output and on the voltage among
// them), compiled with the C compiler, reproduces the C++ model sample by sample in one-step and free-run.
TEST(ResidualAugmented, C99ExportOfEveryTermTypeMatchesCpp) {
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.1, 9);
  pm::CreepParams lti;
  lti.kind = pm::CreepKind::kLti, lti.taus_s = {10, 100}, lti.gains_nm_per_v = {0.5, 0.25};
  pm::PiCreepModel base({0, 10, 20, 35}, {12, 1, 0.5, 0.25}, 2.0, lti, 11.0);
  std::vector<pm::EffectTerm> terms = {make("linear", "temperature_c", 1, 2.0, 30.0), make("play", "a_voltage_v", 1, 0, 10.0),
                                       make("sincos", "position", 2), make("rate", "voltage", 3, 0, 5.0),
                                       make("powers", "voltage", 2), make("gain", "temperature_c", 1, 5.0, 60.0),
                                       make("gain_quadratic", "time_s", 2), make("gain", "a_position_nm", 1, 1.0)};
  terms[1].threshold = 4.0;
  terms[2].period = 400.0;
  terms[4].pre_center = 1.0, terms[4].pre_scale = 80.0;
  terms[5].pre_center = 22.0, terms[5].pre_scale = 0.5, terms[5].reference = 100.0;
  terms[6].pre_center = 180.0, terms[6].pre_scale = 100.0, terms[6].scales = "voltage";
  terms[7].pre_center = 0.0, terms[7].pre_scale = 500.0;
  for (std::size_t k = 0; k < terms.size(); ++k)
    for (std::size_t r = 0; r < terms[k].weight.size(); ++r) {
      terms[k].weight[r] = 0.01 * static_cast<double>(k + r + 1);
      terms[k].center[r] = 0.1 * static_cast<double>(r);
      terms[k].scale[r] = 1.0 + 0.5 * static_cast<double>(k);
    }
  terms[5].weight = {0.002};  // a 0.2 % gain per standardised unit
  pm::AugmentedModel m(base.clone(), terms, 3.0, 11.0);
  const std::vector<std::string> names = m.aux_inputs();
  pm::InputResolver inputs(d, names, "c");

  const std::size_t rows = 3000;
  const auto& ax = d.axis("c");
  std::ostringstream input;
  input.precision(17);
  for (std::size_t i = 0; i < rows; ++i) {
    input << ax.voltage_v[i] << " " << ax.position_nm[i];
    const double* a = inputs.at(i);
    for (std::size_t k = 0; k < names.size(); ++k) input << " " << a[k];
    input << "\n";
  }
  const std::string main_c =
      "int main(void) { pz_state one, fr; double v, d, aux[pz_NAUX]; int k, first = 1;\n"
      "  while (scanf(\"%lf %lf\", &v, &d) == 2) {\n"
      "    for (k = 0; k < pz_NAUX; ++k) if (scanf(\"%lf\", &aux[k]) != 1) return 1;\n"
      "    if (first) { pz_init(&one, v, d); pz_init(&fr, v, d); first = 0; }\n"
      "    printf(\"%.17g %.17g\\n\", pz_step(&one, v, d, aux), pz_step(&fr, v, NAN, aux)); }\n"
      "  return 0; }\n";
  std::string out;
  ASSERT_NO_FATAL_FAILURE(run_exported_c("pz_aug", pm::export_c99(m, "pz"), main_c, input.str(), out));
  std::istringstream res(out);
  pm::StreamOptions so;
  so.mode = pm::PredictionMode::kOneStep;
  auto one = m.clone();
  const auto cpp_one = pm::stream_model(*one, d.slice(0, rows), "c", so).prediction;
  so.mode = pm::PredictionMode::kFreeRun;
  auto fr = m.clone();
  const auto cpp_free = pm::stream_model(*fr, d.slice(0, rows), "c", so).prediction;
  double worst = 0, a = 0, b = 0;
  std::size_t n = 0;
  while (res >> a >> b) {
    ASSERT_LT(n, rows);
    worst = std::max({worst, std::fabs(a - cpp_one[n]), std::fabs(b - cpp_free[n])});
    ++n;
  }
  EXPECT_EQ(n, rows);
  EXPECT_LT(worst, 1e-9) << "largest difference C vs C++ [nm]";
  // The terms really contribute: the augmented prediction is not the base's.
  auto b2 = base.clone();
  const auto base_pred = pm::stream_model(*b2, d.slice(0, rows), "c").prediction;
  EXPECT_GT(std::fabs(base_pred[2000] - cpp_free[2000]), 1.0);
}

// The C99 export of an augmented model with sensor terms (acts_on: readings): pz_predict gives what the encoder
// reads (C++ predict()), pz_predict_position the stage position (predict() with set_stage_position(true)),
// pz_sensor_part_nm what the sensor terms add (sensor_part_nm()), in one-step and free-run. The base reads its
// last position, so what pz_commit hands it counts: the C++ stage-position model is committed as the compensator
// does (the reading less the sensor part). A sensor term on the temperature moves the corrected position the
// position terms read.
TEST(ResidualAugmented, C99ExportSeparatesSensorTermsAsCpp) {
  piezo::features::FeatureSpec spec;
  piezo::features::FeatureDef volt, last;
  volt.type = "voltage";
  last.type = "lagged_position", last.lag_s = 1 / 11.0;
  spec.features = {volt, last};
  Eigen::VectorXd w(2);
  w << 2.5, 0.5;
  pm::LinearModel base(spec, 11.0, w, 10.0);
  std::vector<pm::EffectTerm> terms = {make("sincos", "position", 2), make("linear", "temperature_c", 1),
                                       make("linear", "voltage", 1, 2.0, 20.0), make("sincos", "position", 2)};
  terms[0].period = 350.0, terms[0].acts_on = pm::kActsOnReadings, terms[0].family = "position_periodic";
  terms[0].weight = {20.0, -12.0};  // the encoder's interpolation error [nm]
  terms[1].acts_on = pm::kActsOnReadings, terms[1].center = {22.0}, terms[1].scale = {0.5}, terms[1].weight = {8.0};
  terms[2].center = {40.0}, terms[2].scale = {20.0}, terms[2].weight = {3.0};
  terms[3].period = 900.0, terms[3].weight = {5.0, 4.0};  // a stage term on the position
  const pm::AugmentedModel m(base.clone(), terms, 3.0, 11.0);
  const std::vector<std::string> names = m.aux_inputs();
  ASSERT_EQ(names, (std::vector<std::string>{"temperature_c"}));

  const std::size_t rows = 400;
  std::vector<double> v(rows), temp_c(rows), reading_nm(rows);
  for (std::size_t i = 0; i < rows; ++i) {
    const double t = static_cast<double>(i);
    v[i] = 40.0 + 30.0 * std::sin(6.283185307179586 * t / 150.0) + 10.0 * std::sin(6.283185307179586 * t / 37.0);
    temp_c[i] = 22.0 + 0.5 * std::sin(t / 50.0);
    reading_nm[i] = 20.0 + 5.0 * v[i] + 3.0 * std::sin(t / 7.0);
  }
  std::ostringstream input;
  input.precision(17);
  for (std::size_t i = 0; i < rows; ++i) input << v[i] << " " << reading_nm[i] << " " << temp_c[i] << "\n";
  const std::string main_c =
      "static void show(const pz_state* st, double v, const double* aux) {\n"
      "  printf(\"%.17g %.17g %.17g \", pz_predict(st, v, aux), pz_predict_position(st, v, aux),\n"
      "         pz_sensor_part_nm(st, v, aux)); }\n"
      "int main(void) { pz_state one, fr; double v, d, aux[1]; int first = 1;\n"
      "  while (scanf(\"%lf %lf %lf\", &v, &d, &aux[0]) == 3) {\n"
      "    if (first) { pz_init(&one, v, d); pz_init(&fr, v, d); first = 0; }\n"
      "    show(&one, v, aux); show(&fr, v, aux); printf(\"\\n\");\n"
      "    pz_step(&one, v, d, aux); pz_step(&fr, v, NAN, aux); }\n"
      "  return 0; }\n";
  std::string out;
  ASSERT_NO_FATAL_FAILURE(run_exported_c("pz_aug_sensor", pm::export_c99(m, "pz"), main_c, input.str(), out));

  // C++: per mode (0 one-step, 1 free-run) a model of the readings and one of the stage position.
  std::unique_ptr<pm::AugmentedModel> reads[2], stage[2];
  for (int k = 0; k < 2; ++k) {
    reads[k] = std::make_unique<pm::AugmentedModel>(m);
    stage[k] = std::make_unique<pm::AugmentedModel>(m);
    stage[k]->set_stage_position(true);
    reads[k]->reset(v[0], reading_nm[0]);
    stage[k]->reset(v[0], reading_nm[0]);
  }
  std::istringstream res(out);
  double worst_read = 0, worst_position = 0, worst_sensor = 0, largest_sensor = 0;
  std::size_t n = 0;
  double c[6];
  while (res >> c[0] >> c[1] >> c[2] >> c[3] >> c[4] >> c[5]) {
    ASSERT_LT(n, rows);
    const pm::ModelInput in{v[n], &temp_c[n]};
    for (int k = 0; k < 2; ++k) {
      const double read = reads[k]->predict(in), position = stage[k]->predict(in), sensor = stage[k]->sensor_part_nm(in);
      worst_read = std::max(worst_read, std::fabs(c[3 * k] - read));
      worst_position = std::max(worst_position, std::fabs(c[3 * k + 1] - position));
      worst_sensor = std::max(worst_sensor, std::fabs(c[3 * k + 2] - sensor));
      largest_sensor = std::max(largest_sensor, std::fabs(sensor));
      reads[k]->commit(in, k == 0 ? reading_nm[n] : read);
      stage[k]->commit(in, k == 0 ? reading_nm[n] - sensor : position);
    }
    ++n;
  }
  EXPECT_EQ(n, rows);
  auto text = [](double x) { std::ostringstream os; os << x; return os.str(); };
  RecordProperty("max_diff_predict_nm", text(worst_read));
  RecordProperty("max_diff_predict_position_nm", text(worst_position));
  RecordProperty("max_diff_sensor_part_nm", text(worst_sensor));
  RecordProperty("largest_sensor_part_nm", text(largest_sensor));
  EXPECT_LT(worst_read, 1e-9) << "pz_predict vs predict() [nm]";
  EXPECT_LT(worst_position, 1e-9) << "pz_predict_position vs predict() of the stage position [nm]";
  EXPECT_LT(worst_sensor, 1e-9) << "pz_sensor_part_nm vs sensor_part_nm() [nm]";
  EXPECT_GT(largest_sensor, 10.0) << "the sensor terms must matter for this test to mean anything";
}
