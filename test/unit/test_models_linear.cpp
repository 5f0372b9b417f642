#include <gtest/gtest.h>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_data.h"

using namespace piezo;
using models::LinearModel;

namespace {
features::FeatureSpec physics_small() {
  features::FeatureSpec s;
  features::FeatureDef f;
  f.type = "voltage";
  s.features.push_back(f);
  f = {};
  f.type = "play";
  f.threshold_v = 10;
  s.features.push_back(f);
  f = {};
  f.type = "lowpass";
  f.time_constant_s = 100;
  s.features.push_back(f);
  return s;
}
}  // namespace

TEST(LinearModel, OlsRecoversTheWeightsThatMadeTheData) {
  const features::FeatureSpec spec = physics_small();
  Eigen::VectorXd w(3);
  w << 10.0, 6.0, 3.0;
  LinearModel truth(spec, 11.0, w, 40.0);
  const auto v = testdata::random_walk_v(20000, 3);
  const io::Dataset d = testdata::make_dataset(truth, v, 11.0, 0.0, 1);
  training::FitRequest req;
  req.train = &d;
  req.options["features"] = spec.to_yaml();
  auto fitted = training::fit_model("linear", req);
  // Same predictions as the generator on fresh data.
  const auto v2 = testdata::random_walk_v(3000, 9);
  fitted->reset(v2[0], 0);
  truth.reset(v2[0], 0);
  for (double x : v2) {
    models::ModelInput in{x, nullptr};
    EXPECT_NEAR(fitted->predict(in), truth.predict(in), 1e-6);
    fitted->commit(in, 0);
    truth.commit(in, 0);
  }
  EXPECT_FALSE(fitted->is_affine_in_voltage());  // play feature
  EXPECT_FALSE(fitted->uses_position_history());
  EXPECT_EQ(fitted->meta.axis, "c");
  EXPECT_NEAR(fitted->meta.sample_rate_hz, 11.0, 1e-9);
}

// A play hinge bends the voltage-to-position map: a linear model weighting one is not affine in V (the
// feedforward inverse then searches instead of solving), one with a zero weight on it is.
TEST(LinearModel, AWeightedPlayHingeIsNotAffineInTheVoltage) {
  features::FeatureSpec spec;
  features::FeatureDef v, h;
  v.type = "voltage";
  h.type = "play_hinge", h.threshold_v = 2.0, h.knot_v = 5.0;
  spec.features = {v, h};
  Eigen::VectorXd w(2);
  w << 10.0, 4.0;
  EXPECT_FALSE(LinearModel(spec, 11.0, w, 0.0).is_affine_in_voltage());
  w(1) = 0.0;
  EXPECT_TRUE(LinearModel(spec, 11.0, w, 0.0).is_affine_in_voltage());
}

TEST(LinearModel, StudyFeaturesAreAffineAndUsePositions) {
  const auto v = testdata::random_walk_v(5000, 4);
  Eigen::VectorXd w(3);
  w << 10.0, 6.0, 3.0;
  LinearModel gen(physics_small(), 11.0, w, 0.0);
  const io::Dataset d = testdata::make_dataset(gen, v, 11.0, 20.0, 2);
  for (const char* method : {"ols", "ridge", "lasso"}) {
    training::FitRequest req;
    req.train = &d;
    req.options["method"] = method;
    req.options["features"] = "study";
    auto m = training::fit_model("linear", req);
    EXPECT_TRUE(m->is_affine_in_voltage()) << method;
    EXPECT_TRUE(m->uses_position_history()) << method;
    // Closed-form inverse from two predictions hits the target.
    m->reset(v[0], d.axis("c").position_nm[0]);
    for (std::size_t i = 0; i < 200; ++i) m->commit({v[i], nullptr}, d.axis("c").position_nm[i]);
    const double f0 = m->predict({0.0, nullptr}), f1 = m->predict({1.0, nullptr});
    const double target = 123.0, vin = (target - f0) / (f1 - f0);
    EXPECT_NEAR(m->predict({vin, nullptr}), target, 1e-6) << method;
  }
  training::FitRequest bad;
  bad.train = &d;
  bad.options["method"] = "magic";
  EXPECT_THROW(training::fit_model("linear", bad), std::runtime_error);
}

TEST(LinearModel, PredictionOfSampleTDoesNotDependOnMeasurementT) {
  // One-step semantics through the Model interface: changing D_t must not change the prediction of t.
  const features::FeatureSpec spec = training::fit_standardisation(features::study_features(), [] {
    io::Dataset d;
    d.add_axis("c");
    for (int i = 0; i < 100; ++i) {
      d.time_s.push_back(i / 11.0);
      d.axis("c").voltage_v.push_back(i % 7);
      d.axis("c").position_nm.push_back(i * 3 % 11);
    }
    return d;
  }(), "c");
  Eigen::VectorXd w = Eigen::VectorXd::LinSpaced(spec.size(), 1, 2);
  LinearModel a(spec, 11.0, w, 0), b(spec, 11.0, w, 0);
  a.reset(0, 0);
  b.reset(0, 0);
  for (int t = 0; t <= 21; ++t) {
    const models::ModelInput in{double(t % 5), nullptr};
    if (t <= 20) {
      EXPECT_EQ(a.predict(in), b.predict(in)) << t;
    } else {
      EXPECT_NE(a.predict(in), b.predict(in));  // D_20 is seen by the next sample
    }
    a.commit(in, 10.0 * t);
    b.commit(in, t == 20 ? 5000.0 : 10.0 * t);
  }
  // Free-run differs from one-step for a position-using model: clone continues independently.
  auto c = a.clone();
  const models::ModelInput in{1.0, nullptr};
  c->commit(in, c->predict(in));
  a.commit(in, 1e4);
  EXPECT_NE(c->predict(in), a.predict(in));
}

// A free run that amplifies its start error is numerically wild whatever its score: free_run_gain measures it (two
// free runs started 1 µm apart), and fit_linear refits such a fit on its voltage features alone.
TEST(LinearModel, AFreeRunThatAmplifiesItsStartIsRefittedOnTheVoltage) {
  features::FeatureSpec spec;
  features::FeatureDef f;
  f.type = "voltage";
  spec.features.push_back(f);
  f = {};
  f.type = "lagged_position";
  f.lag_s = 1.0 / 11.0;
  spec.features.push_back(f);
  const auto v = testdata::random_walk_v(400, 5);
  Eigen::VectorXd w(2);
  for (double a : {0.5, 1.0, 1.05}) {
    w << 10.0, a;
    LinearModel m(spec, 11.0, w, 0.0);
    const io::Dataset d = testdata::make_dataset(m, v, 11.0, 0.0, 1);
    const double gain = training::free_run_gain(m, d, "c");
    if (a < 1)
      EXPECT_LE(gain, 0.5 + 1e-9);  // the first prediction carries a·Δ, later ones less
    else if (a == 1.0)
      EXPECT_NEAR(gain, 1.0, 1e-9);  // a random walk keeps its start
    else
      EXPECT_GT(gain, 1e6);  // 1.05^400
  }
  // Data made by that amplifying recursion (y_t = 1.05 y_{t−1} + 10 V_t): OLS finds it exactly, and the fit keeps
  // only the voltage.
  w << 10.0, 1.05;
  LinearModel wild(spec, 11.0, w, 0.0);
  const io::Dataset d = testdata::make_dataset(wild, v, 11.0, 0.0, 1);
  training::FitRequest req;
  req.train = &d;
  req.options["features"] = spec.to_yaml();
  std::string said;
  req.progress = [&](double, double, const std::string& what) { said += what; };
  const models::ModelPtr fitted = training::fit_model("linear", req);
  EXPECT_FALSE(fitted->uses_position_history());
  const auto& refit_spec = dynamic_cast<const LinearModel&>(*fitted).spec();
  EXPECT_EQ(refit_spec.mean.size(), refit_spec.size());  // standardised like every fit (the lasso's penalty needs it)
  EXPECT_LE(training::free_run_gain(*fitted, d, "c"), 0.0);
  EXPECT_NE(said.find("refitted on the voltage features"), std::string::npos) << said;
  // Data from the stable one keeps its position feature.
  w << 10.0, 0.5;
  LinearModel tame(spec, 11.0, w, 0.0);
  const io::Dataset stable = testdata::make_dataset(tame, v, 11.0, 0.0, 1);
  req.train = &stable;
  EXPECT_TRUE(training::fit_model("linear", req)->uses_position_history());
}
