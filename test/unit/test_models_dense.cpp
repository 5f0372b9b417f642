// Dense network: backprop against finite differences, the single-sample path against the batch path,
// model save/load through the registry, predict() const, determinism for a seed.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <set>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/dense_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_dense_data.h"

using namespace piezo;

namespace {

Eigen::VectorXd finite_difference(const std::function<double(const Eigen::VectorXd&)>& f, Eigen::VectorXd p) {
  Eigen::VectorXd g(p.size());
  for (Eigen::Index i = 0; i < p.size(); ++i) {
    const double h = 1e-6 * std::max(1.0, std::abs(p[i]));
    const double keep = p[i];
    p[i] = keep + h;
    const double up = f(p);
    p[i] = keep - h;
    const double down = f(p);
    p[i] = keep;
    g[i] = (up - down) / (2 * h);
  }
  return g;
}

}  // namespace

TEST(DenseNet, GradientMatchesFiniteDifferences) {
  for (int depth : {0, 1, 3}) {
    models::DenseShape s;
    s.inputs = 4;
    s.depth = depth;
    s.width = 5;
    s.leaky_slope = 0.05;
    const models::DenseNet net(s);
    const Eigen::VectorXd p = net.initial_params(7);
    std::mt19937_64 rng(3);
    std::normal_distribution<double> n01;
    Eigen::MatrixXd x(4, 9);
    Eigen::VectorXd y(9);
    for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] = n01(rng);
    for (Eigen::Index i = 0; i < y.size(); ++i) y[i] = n01(rng);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(p.size());
    net.loss_grad(p, x, y, &g);
    const Eigen::VectorXd fd = finite_difference([&](const Eigen::VectorXd& q) { return net.loss_grad(q, x, y, nullptr); }, p);
    EXPECT_LT((g - fd).norm(), 1e-6 * std::max(1.0, fd.norm())) << "depth " << depth;
    // The streaming single-sample forward equals the batch forward.
    const Eigen::VectorXd out = net.forward_batch(p, x);
    for (Eigen::Index c = 0; c < x.cols(); ++c) EXPECT_NEAR(net.forward(p.data(), x.col(c).data()), out[c], 1e-12);
  }
}

TEST(DenseNet, RejectsBadShape) {
  models::DenseShape s;
  s.width = 0;
  EXPECT_THROW(models::DenseNet{s}, std::runtime_error);
}

TEST(DenseModel, FitsLearnsAndRoundTripsThroughRegistry) {
  const io::Dataset data = test_data::hysteretic_dataset(4000, 11);
  training::FitRequest req;
  req.train = &data;
  req.axis = "c";
  req.seed = 5;
  req.threads = 2;
  req.options["epochs"] = 15;
  req.options["width"] = 8;
  req.options["learning_rate"] = 3e-3;
  const models::ModelPtr m = training::fit_model("dense", req);
  ASSERT_TRUE(m);
  EXPECT_EQ(m->kind(), "dense");
  EXPECT_FALSE(m->uses_position_history());  // default features: voltage history only (one-step = free-run)
  // One-step MAE on the data well below the position spread (the model learned something).
  const double mae = test_data::one_step_mae(*m, data, "c");
  const double spread = test_data::mean_abs_deviation(data.axis("c").position_nm);
  EXPECT_LT(mae, 0.15 * spread);

  // Save/load through the registry reproduces predictions exactly.
  YAML::Emitter out;
  out << m->to_yaml();
  const models::ModelPtr back = models::model_kind("dense").load(YAML::Load(out.c_str()));
  EXPECT_NEAR(test_data::one_step_mae(*back, data, "c"), mae, 1e-9);

  // predict() is const in effect: repeating it gives the same value and does not move the state.
  models::ModelPtr a = m->clone();
  a->reset(0.0, data.axis("c").position_nm[0]);
  const models::ModelInput in{10.0, nullptr};
  const double p1 = a->predict(in), p2 = a->predict(models::ModelInput{-30.0, nullptr}), p3 = a->predict(in);
  EXPECT_EQ(p1, p3);
  EXPECT_NE(p1, p2);

  // Same seed, same weights; another seed, other weights.
  const models::ModelPtr m2 = training::fit_model("dense", req);
  EXPECT_EQ(YAML::Dump(m2->to_yaml()["weights"]), YAML::Dump(m->to_yaml()["weights"]));
  req.seed = 6;
  const models::ModelPtr m3 = training::fit_model("dense", req);
  EXPECT_NE(YAML::Dump(m3->to_yaml()["weights"]), YAML::Dump(m->to_yaml()["weights"]));
}

TEST(DenseModel, MalformedNodesGiveOneClearError) {
  const io::Dataset data = test_data::hysteretic_dataset(800, 11);
  training::FitRequest req;
  req.train = &data;
  req.options["epochs"] = 1;
  const YAML::Node good = training::fit_model("dense", req)->to_yaml();
  auto expect_error = [](const YAML::Node& n, const std::string& needle) {
    try {
      models::model_kind("dense").load(n);
      ADD_FAILURE() << "no error for " << needle;
    } catch (const std::runtime_error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  YAML::Node n = YAML::Clone(good);
  n["weights"].push_back(1.0);
  expect_error(n, "weights");
  n = YAML::Clone(good);
  n["hyperparameters"]["colour"] = 3;
  expect_error(n, "colour");
  n = YAML::Clone(good);
  n["weights"][0] = "abc";
  expect_error(n, "weights");
  n = YAML::Clone(good);
  n.remove("target");
  expect_error(n, "target");
  YAML::Node opts;
  opts["widht"] = 3;
  req.options = opts;
  EXPECT_THROW(training::fit_model("dense", req), std::runtime_error);
}

// The default: the lasso's survivors among the voltage-only candidates placed on the training data; none kept (a
// position that does not follow the voltage) is one error naming the cause.
TEST(DenseModel, DefaultFeaturesAreTheLassosVoltageOnlySurvivors) {
  io::Dataset data = test_data::hysteretic_dataset(3000, 5);
  training::FitRequest req;
  req.train = &data;
  req.options = YAML::Load("{steps: 20, patience: 0}");
  const models::ModelPtr m = training::fit_model("dense", req);
  const YAML::Node f = m->to_yaml()["features"]["features"];
  ASSERT_TRUE(f && f.size() > 0);
  std::set<std::string> types;
  for (const auto& e : f) types.insert(e["type"].as<std::string>());
  EXPECT_FALSE(types.count("lagged_position") || types.count("position_mean"));
  EXPECT_TRUE(types.count("voltage") || types.count("play") || types.count("play_hinge")) << f;
  EXPECT_FALSE(m->uses_position_history());
  // A disconnected sensor: the reading is noise whatever the voltage.
  std::mt19937_64 rng(9);
  std::normal_distribution<double> noise(0.0, 20.0);
  for (double& y : data.axis("c").position_nm) y = noise(rng);
  try {
    training::fit_model("dense", req);
    ADD_FAILURE() << "fitted a dense model on a position that does not follow the voltage";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("the lasso kept no candidate feature"), std::string::npos) << e.what();
  }
}

TEST(DenseModel, VoltageHistoryFeaturesArePlacedOnTheDataSpanAndReadNoPositions) {
  const features::FeatureSpec s = features::voltage_history_features({0.0, 4.0, 40.0, 200.0});
  EXPECT_FALSE(s.uses_positions());
  std::vector<double> thresholds, taus;
  for (const auto& f : s.features) {
    if (f.type == "play") thresholds.push_back(f.threshold_v);
    if (f.type == "play_lowpass") taus.push_back(f.time_constant_s);
  }
  ASSERT_EQ(thresholds.size(), 4u);
  EXPECT_NEAR(thresholds[0], 0.12, 1e-12);
  EXPECT_NEAR(thresholds[3], 1.6, 1e-12);
  ASSERT_EQ(taus.size(), 4u);
  EXPECT_NEAR(taus[0], 40.0 / 3000, 1e-12);  // above two samples (0.01 s)
  EXPECT_NEAR(taus[3], 40.0 / 3, 1e-12);     // below the duration
  // Ten times the voltage: ten times the thresholds (scale-free); at 11 Hz the fastest time constant is 2 samples.
  const features::FeatureSpec s10 = features::voltage_history_features({-20.0, 20.0, 40.0, 11.0});
  EXPECT_NEAR(s10.features[2].threshold_v, 1.2, 1e-12);
  EXPECT_NEAR(s10.features[6].time_constant_s, 2.0 / 11.0, 1e-12);
  EXPECT_THROW(features::voltage_history_features({1.0, 1.0, 40.0, 200.0}), std::runtime_error);  // no span
  EXPECT_THROW(features::named_features("voltage_history"), std::runtime_error);                 // no data
  EXPECT_NO_THROW(features::check_feature_set_name("voltage_history"));
  EXPECT_THROW(features::check_feature_set_name("volts"), std::runtime_error);
}

TEST(DenseModel, LinearStartFitsFasterThanTheRandomStart) {
  const io::Dataset data = test_data::hysteretic_dataset(4000, 17);
  training::FitRequest req;
  req.train = &data;
  req.seed = 4;
  req.threads = 2;
  req.options["steps"] = 100;
  req.options["patience"] = 0;
  const double linear = test_data::one_step_mae(*training::fit_model("dense", req), data, "c");
  req.options["init"] = "random";
  const double random = test_data::one_step_mae(*training::fit_model("dense", req), data, "c");
  EXPECT_LT(linear, 0.5 * random);
  req.options["init"] = "zero";
  EXPECT_THROW(training::fit_model("dense", req), std::runtime_error);
}

TEST(DenseModel, ExportedC99HeaderMatchesCppSampleBySample) {
  const io::Dataset data = test_data::hysteretic_dataset(1500, 11);
  training::FitRequest req;
  req.train = &data;
  req.options["epochs"] = 3;
  req.options["depth"] = 2;
  const models::ModelPtr m = training::fit_model("dense", req);
  const std::string c = models::model_kind("dense").export_c99(*m, "pz");
  EXPECT_NE(c.find("pz_network(const double* x)"), std::string::npos);
  EXPECT_LT(test_data::c_export_max_diff(*m, c, data, "c"), 1e-10);
}

TEST(DenseModel, TuningThroughTheRegistryRunsTrialsAndReportsProgress) {
  const io::Dataset data = test_data::hysteretic_dataset(1500, 13);
  training::FitRequest req;
  req.train = &data;
  req.tune_trials = 4;
  req.options["epochs"] = 3;
  req.options["tune_epochs"] = 1;  // trials short, the winner retrained with 3 epochs
  int calls = 0;
  double last_done = 0, last_total = 0;
  req.progress = [&](double done, double total, const std::string& what) {
    if (what == "features" || what == "lasso path") return;  // the default features' lasso, before the trials
    ++calls;
    EXPECT_EQ(what, "trial");
    last_done = done;
    last_total = total;
  };
  const models::ModelPtr m = training::fit_model("dense", req);
  EXPECT_EQ(calls, 4);
  EXPECT_EQ(last_done, 4);
  EXPECT_EQ(last_total, 4);
  const YAML::Node info = m->to_yaml()["training"]["tuning"];
  ASSERT_TRUE(info);
  EXPECT_EQ(info["trials"].as<int>(), 4);
  EXPECT_NE(info["best"].as<std::string>().find("learning_rate="), std::string::npos);
  EXPECT_GT(m->meta.validation.at("validation_rmse_nm"), 0.0);
}

TEST(DenseModel, FreeRunStaysWithinTheOutputRails) {
  models::DenseShape s{6, 1, 3, 0.01};
  models::TargetScale target;
  target.output_min_nm = -100.0;
  target.output_max_nm = 100.0;
  // Huge weights: unclamped, the free-run feedback through the position features would explode.
  const Eigen::VectorXd p = models::DenseNet(s).initial_params(3) * 1e6;
  models::DenseModel m(features::study_features(), 11.0, s, p, target);
  m.reset(0.0, 0.0);
  double lo = 0, hi = 0;
  for (int t = 0; t < 300; ++t) {
    const models::ModelInput in{40.0 * std::sin(0.05 * t), nullptr};
    const double y = m.predict(in);
    lo = std::min(lo, y);
    hi = std::max(hi, y);
    m.commit(in, y);
  }
  EXPECT_GE(lo, -100.0);
  EXPECT_LE(hi, 100.0);
  EXPECT_TRUE(lo == -100.0 || hi == 100.0);  // a rail was reached: the clamp did the work

  YAML::Node n = m.to_yaml();
  n["target"]["output_min_nm"] = 200.0;
  EXPECT_THROW(models::model_kind("dense").load(n), std::runtime_error);
}
