// The one streaming path (models::stream_model) and the one input resolver (models::InputResolver): modes,
// warm-up, anchor, causal other-axis positions, and evaluation equal to it sample by sample.
#include <gtest/gtest.h>

#include <cmath>
#include <map>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/compensation/drift_forecast.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/analysis/residual/residual.h"
#include "test_residual_common.h"

namespace pm = piezo::models;
namespace pa = piezo::analysis;

namespace {
// Reads the position history: predicts the last committed position plus a voltage step response.
class LastPositionModel : public pm::Model {
 public:
  std::string kind() const override { return "test_last_position"; }
  void reset(double v, double x) override { v_ = v, x_ = x; }
  double predict(const pm::ModelInput& in) const override { return x_ + 3.0 * (in.voltage_v - v_); }
  void commit(const pm::ModelInput& in, double x) override { v_ = in.voltage_v, x_ = x; }
  std::unique_ptr<pm::Model> clone() const override { return std::make_unique<LastPositionModel>(*this); }
  bool uses_position_history() const override { return true; }
  YAML::Node to_yaml() const override { return {}; }
  std::size_t num_parameters() const override { return 1; }

 private:
  double v_ = 0, x_ = 0;
};
}  // namespace

TEST(EvalStream, OneStepCommitsMeasurementFreeRunItsOwnPrediction) {
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.05, 3);
  const auto& ax = d.axis("c");
  LastPositionModel m;
  pm::StreamOptions o;
  o.mode = pm::PredictionMode::kOneStep;
  const auto one = pm::stream_model(m, d, "c", o).prediction;
  o.mode = pm::PredictionMode::kFreeRun;
  const auto free = pm::stream_model(m, d, "c", o).prediction;
  ASSERT_EQ(one.size(), d.size());
  for (std::size_t i = 1; i < d.size(); i += 37) {
    EXPECT_DOUBLE_EQ(one[i], ax.position_nm[i - 1] + 3.0 * (ax.voltage_v[i] - ax.voltage_v[i - 1]));
    EXPECT_NEAR(free[i], ax.position_nm[0] + 3.0 * (ax.voltage_v[i] - ax.voltage_v[0]), 1e-6);
  }
  // Evaluation runs the same path.
  const pa::SeriesPrediction s = pa::predict_series(m, d, "c");
  for (std::size_t i = 0; i < d.size(); i += 41) {
    EXPECT_DOUBLE_EQ(s.one_step[i], one[i]);
    EXPECT_DOUBLE_EQ(s.free_run[i], free[i]);
  }
}

TEST(EvalStream, AnchorFixesTheOffsetFromTheFirstSecondsAndScoresAfterThem) {
  piezo::test::register_test_kind();
  piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.1, 5);
  auto m = piezo::test::LowpassLinearModel::fit(d, "c", d.size());
  for (double& x : d.axis("c").position_nm) x += 250.0;  // unknown initial offset of a new recording
  pm::StreamOptions o;
  const auto plain = pm::stream_model(*m, d, "c", o);
  EXPECT_FALSE(plain.anchored);
  o.anchor_s = 60.0;
  // The offset-only anchor (the plain mean); the start estimate may leave a few nm of a true offset to a history
  // that explains them (docs/models.md, "Start-up state estimate"): scored after the window below.
  o.anchor_history = false;
  const auto anchored = pm::stream_model(*m, d, "c", o);
  ASSERT_TRUE(anchored.anchored);
  EXPECT_EQ(anchored.first_scored, 660u);
  EXPECT_NEAR(anchored.anchor_offset_nm, 250.0, 5.0);  // mean of 660 noisy samples (σ ≈ 21 nm)
  EXPECT_NEAR(anchored.prediction[1000] - plain.prediction[1000], anchored.anchor_offset_nm, 1e-9);
  const auto mask = pm::scored_mask(anchored, d.size());
  EXPECT_EQ(mask[659], 0);
  EXPECT_EQ(mask[660], 1);
  const double before = pa::error_stats(plain.prediction, d.axis("c").position_nm, mask).mae_nm;
  const double after = pa::error_stats(anchored.prediction, d.axis("c").position_nm, mask).mae_nm;
  EXPECT_GT(before, 200.0);
  EXPECT_LT(after, 25.0);
  o.anchor_history = true;
  const auto estimated = pm::stream_model(*m, d, "c", o);
  EXPECT_NEAR(estimated.anchor_offset_nm, 250.0, 15.0);
  EXPECT_LT(pa::error_stats(estimated.prediction, d.axis("c").position_nm, mask).mae_nm, 25.0);
  o.anchor_s = 1e6;
  EXPECT_THROW(pm::stream_model(*m, d, "c", o), piezo::io::DataError);
}

// One estimate, one offset (models/model_stream.h): the one-step stream of a model that reads the position takes
// the window mean under the estimate's row weights; with the offset-only anchor (no weights) the plain mean.
TEST(EvalStream, AOneStepOffsetOfAModelThatReadsThePositionIsTheEstimatesWeightedMean) {
  piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.1, 5);
  for (double& x : d.axis("c").position_nm) x += 250.0;
  LastPositionModel m;
  pm::StreamOptions o;
  o.anchor_s = 60.0;
  o.mode = pm::PredictionMode::kOneStep;
  const auto r = pm::stream_model(*m.clone(), d, "c", o);
  ASSERT_GT(r.start.candidates, 1u);
  const std::vector<double>& w = r.start.window_weight;
  ASSERT_EQ(w.size(), r.first_scored);
  const auto& y = d.axis("c").position_nm;
  double sw = 0, swr = 0, plain = 0;
  bool unequal = false;
  for (std::size_t i = 0; i < w.size(); ++i) {
    const double raw = r.prediction[i] - r.anchor_offset_nm;
    sw += w[i], swr += w[i] * (y[i] - raw), plain += (y[i] - raw) / static_cast<double>(w.size());
    unequal = unequal || w[i] != w[0];
  }
  EXPECT_NEAR(r.anchor_offset_nm, swr / sw, 1e-9);
  EXPECT_TRUE(unequal) << "equal weights cannot tell the weighted mean from the plain one";
  o.anchor_history = false;
  const auto plain_run = pm::stream_model(*m.clone(), d, "c", o);
  double mean = 0;
  for (std::size_t i = 0; i < plain_run.first_scored; ++i)
    mean += (y[i] - (plain_run.prediction[i] - plain_run.anchor_offset_nm)) / static_cast<double>(plain_run.first_scored);
  EXPECT_TRUE(plain_run.start.window_weight.empty());
  EXPECT_NEAR(plain_run.anchor_offset_nm, mean, 1e-9);
}

TEST(EvalStream, OtherAxisPositionIsTheLastReadingBeforeThisSample) {
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.02, 4);
  pm::InputResolver r(d, {"a_position_nm", "a_voltage_v", "time_s", "temperature_c"}, "c");
  ASSERT_EQ(r.size(), 4u);
  EXPECT_EQ(r.sources()[0].kind, pm::InputSource::Kind::kAxisPosition);
  EXPECT_EQ(r.sources()[3].kind, pm::InputSource::Kind::kAux);
  const double* row0 = r.at(0);
  EXPECT_DOUBLE_EQ(row0[0], d.axis("a").position_nm[0]);
  const double* row = r.at(10);
  EXPECT_DOUBLE_EQ(row[0], d.axis("a").position_nm[9]);
  EXPECT_DOUBLE_EQ(row[1], d.axis("a").voltage_v[10]);
  EXPECT_DOUBLE_EQ(row[2], d.time_s[10]);
  EXPECT_DOUBLE_EQ(row[3], d.find_aux("temperature_c")->values[10]);
  // The own axis' position and any truth are never inputs; the message names the column and the data.
  try {
    pm::InputResolver bad(d, {"c_position_nm"}, "c");
    FAIL();
  } catch (const piezo::io::DataError& e) {
    EXPECT_NE(std::string(e.what()).find("c_position_nm"), std::string::npos);
  }
  EXPECT_THROW(pm::classify_input("b_true_position_nm", "c", {"a", "c"}), piezo::io::DataError);
}

TEST(EvalStream, WarmupThenDataEqualsOneRunOverBoth) {
  piezo::test::register_test_kind();
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.1, 6);
  const std::size_t k = d.size() / 3;
  const piezo::io::Dataset a = d.slice(0, k), b = d.slice(k, d.size());
  LastPositionModel m;
  const auto whole = pm::stream_model(m, d, "c").prediction;
  pm::StreamOptions o;
  o.warmup = &a;
  const auto tail = pm::stream_model(m, b, "c", o).prediction;
  ASSERT_EQ(tail.size(), b.size());
  for (std::size_t i = 0; i < tail.size(); i += 53) EXPECT_DOUBLE_EQ(tail[i], whole[k + i]);
  // Continuing without a reset is the same as a warm-up.
  LastPositionModel m2;
  pm::stream_model(m2, a, "c");
  o.warmup = nullptr;
  o.reset = false;
  const auto cont = pm::stream_model(m2, b, "c", o).prediction;
  for (std::size_t i = 0; i < cont.size(); i += 53) EXPECT_DOUBLE_EQ(cont[i], whole[k + i]);
}

TEST(EvalStream, DriftForecastEqualsStreamingAHeldVoltageWithTimeRunningOn) {
  piezo::test::register_test_kind();
  const piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.05, 8);
  auto base = piezo::test::LowpassLinearModel::fit(d, "c", d.size());
  pm::EffectTerm drift;
  drift.type = "linear";
  drift.signal = "time_s";
  drift.center = {0.0};
  drift.scale = {1.0};
  drift.weight = {0.05};  // nm/s
  pm::EffectTerm temp = drift;
  temp.signal = "temperature_c";
  temp.time_constant_s = 30.0;
  temp.weight = {40.0};
  pm::AugmentedModel m(base->clone(), {drift, temp}, 0.0, 11.0);
  pm::stream_model(m, d, "c");  // history, free-run
  // The held future as a data set: voltage and temperature held, time running on.
  const double hold_v = d.axis("c").voltage_v.back() + 5.0, temp_now = d.find_aux("temperature_c")->values.back();
  const std::size_t steps = 330;
  piezo::io::Dataset f;
  f.add_axis("c");
  f.aux.push_back({"temperature_c", {}});
  for (std::size_t i = 0; i <= steps; ++i) {
    f.time_s.push_back(d.time_s.back() + (i + 1) / 11.0);
    f.axis("c").voltage_v.push_back(hold_v);
    f.axis("c").position_nm.push_back(0.0);
    f.aux[0].values.push_back(temp_now);
  }
  auto ahead = m.clone();
  pm::StreamOptions o;
  o.reset = false;
  const auto streamed = pm::stream_model(*ahead, f, "c", o).prediction;
  pm::InputResolver r(f, m.aux_inputs(), "c");
  const auto fc = piezo::compensation::forecast_drift(m, hold_v, {0.0, 10.0, 30.0}, 11.0, r.at(0));
  ASSERT_TRUE(fc.ok) << fc.error;
  EXPECT_NEAR(fc.position_nm[0], streamed[0], 1e-9);
  EXPECT_NEAR(fc.position_nm[1], streamed[110], 1e-9);
  EXPECT_NEAR(fc.position_nm[2], streamed[330], 1e-9);
  EXPECT_GT(std::fabs(fc.drift_nm[2]), 1.0);  // the time term moves it: 0.05 nm/s over 30 s
}

// `piezo eval` scores every kind of model `piezo residual` writes: one augmented model file per family (the term
// types and signals that family adds), saved and loaded, evaluated on data with an `a` axis, a temperature
// column and holds. Before the one resolver, a cross_axis term on a_voltage_v failed here.
TEST(EvalStream, EvalScoresAModelOfEveryResidualFamily) {
  piezo::test::register_test_kind();
  piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 0.2, 10);
  d.phase.assign(d.size(), 0);  // the synthetic holds (voltage unchanged) as phase markers
  for (std::size_t i = 1; i < d.size(); ++i)
    if (d.axis("c").voltage_v[i] == d.axis("c").voltage_v[i - 1]) d.phase[i] = static_cast<int>(piezo::protocols::Phase::kHold);
  auto base = piezo::test::LowpassLinearModel::fit(d, "c", d.size());
  auto mk = [](const std::string& family, const std::string& type, const std::string& signal, std::size_t k) {
    pm::EffectTerm t;
    t.family = family, t.type = type, t.signal = signal;
    t.center.assign(k, 0.0), t.scale.assign(k, 1.0), t.weight.assign(k, 0.5);
    return t;
  };
  std::map<std::string, std::vector<pm::EffectTerm>> by_family;
  by_family["time_drift"] = {mk("time_drift", "linear", "time_s", 1)};
  by_family["cross_axis"] = {mk("cross_axis", "linear", "a_voltage_v", 1), mk("cross_axis", "linear", "a_position_nm", 1)};
  by_family["position_periodic"] = {mk("position_periodic", "sincos", "position", 2)};
  by_family["position_periodic"][0].period = 400.0;
  by_family["rate_dependent"] = {mk("rate_dependent", "rate", "voltage", 3)};
  by_family["aux_signal"] = {mk("aux_signal", "linear", "temperature_c", 1)};
  by_family["periodic_disturbance"] = {mk("periodic_disturbance", "sincos", "time_s", 2)};
  by_family["periodic_disturbance"][0].period = 81.3;
  by_family["missing_memory"] = {mk("missing_memory", "play", "voltage", 1)};
  by_family["missing_memory"][0].threshold = 5.0, by_family["missing_memory"][0].time_constant_s = 300.0;
  by_family["voltage_nonlinearity"] = {mk("voltage_nonlinearity", "powers", "voltage", 2)};
  by_family["voltage_nonlinearity"][0].pre_scale = 80.0;
  by_family["time_gain"] = {mk("time_gain", "gain", "time_s", 1)};
  by_family["time_gain"][0].pre_center = 300.0, by_family["time_gain"][0].pre_scale = 200.0;
  by_family["cross_axis_gain"] = {mk("cross_axis_gain", "gain_quadratic", "a_position_nm", 2)};
  by_family["cross_axis_gain"][0].pre_scale = 500.0, by_family["cross_axis_gain"][0].scales = "voltage";
  by_family["aux_gain"] = {mk("aux_gain", "gain", "temperature_c", 1)};
  by_family["aux_gain"][0].pre_center = 22.0, by_family["aux_gain"][0].time_constant_s = 300.0;
  ASSERT_EQ(by_family.size(), pa::residual_family_names().size());
  pa::EvalOptions eo;
  eo.axis = "c";
  for (const auto& f : pa::residual_family_names()) {
    ASSERT_TRUE(by_family.count(f)) << f;
    pm::AugmentedModel m(base->clone(), by_family[f], 1.0, 11.0);
    const std::string path = ::testing::TempDir() + "eval_family_" + f + ".yaml";
    pm::save_model(path, m);
    const pm::ModelPtr loaded = pm::load_model(path);
    const pa::ModelEvaluation ev = pa::evaluate_model(*loaded, f, d, nullptr, eo);
    EXPECT_TRUE(ev.hysteresis.free_run.vs_measured.valid()) << f;
    EXPECT_TRUE(std::isfinite(ev.hysteresis.free_run.vs_truth.mae_nm)) << f;
    EXPECT_TRUE(ev.holds_free_run.valid()) << f << ": hold errors reported apart";
    // The same numbers as streaming the in-memory model.
    auto again = m.clone();
    const auto pred = pm::stream_model(*again, d, "c").prediction;
    EXPECT_NEAR(ev.test.free_run[d.size() / 2], pred[d.size() / 2], 1e-9) << f;
  }
}
