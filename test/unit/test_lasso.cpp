#include <gtest/gtest.h>

#include <random>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/lasso.h"
#include "test_models_data.h"

using namespace piezo;
using namespace piezo::training;

namespace {
// Gram sums of rows [begin, end) of a dense design.
GramStats stats(const Eigen::MatrixXd& X, const Eigen::VectorXd& y, Eigen::Index begin, Eigen::Index end) {
  GramStats g(X.cols());
  auto Xb = X.middleRows(begin, end - begin);
  auto yb = y.segment(begin, end - begin);
  g.n = double(end - begin);
  g.sy = yb.sum();
  g.syy = yb.squaredNorm();
  g.sx = Xb.colwise().sum().transpose();
  g.sxy = Xb.transpose() * yb;
  g.sxx = Xb.transpose() * Xb;
  return g;
}

// Axis c of a data set at 11 Hz driven by testdata's random walk (positions left to the test).
io::Dataset walk_dataset(std::size_t n, std::uint64_t seed) {
  io::Dataset d;
  io::AxisSeries& c = d.add_axis("c");
  c.voltage_v = testdata::random_walk_v(n, seed);
  for (std::size_t i = 0; i < n; ++i) d.time_s.push_back(i / 11.0);
  return d;
}
}  // namespace

TEST(Lasso, SoftThresholdOnOrthogonalDesign) {
  // With XᵀX = n·I the lasso solution is the soft-thresholded OLS coefficient.
  const double n = 100;
  Eigen::MatrixXd G = n * Eigen::MatrixXd::Identity(3, 3);
  Eigen::VectorXd c(3);
  c << 250, -30, 80;  // OLS: 2.5, -0.3, 0.8
  Eigen::VectorXd beta;
  lasso_cd(G, c, n, 0.5, beta);
  EXPECT_NEAR(beta(0), 2.0, 1e-12);
  EXPECT_NEAR(beta(1), 0.0, 1e-12);
  EXPECT_NEAR(beta(2), 0.3, 1e-12);
}

TEST(Lasso, RecoversPlantedSparseModelWithTimeBlockCV) {
  const int N = 20000, p = 30;
  std::mt19937_64 rng(42);
  std::normal_distribution<double> g(0, 1);
  Eigen::MatrixXd X(N, p);
  for (int i = 0; i < N; ++i)
    for (int j = 0; j < p; ++j) X(i, j) = g(rng) + (j > 0 ? 0.3 * X(i, j - 1) : 0.0);  // correlated columns
  Eigen::VectorXd truth = Eigen::VectorXd::Zero(p);
  truth(2) = 3.0, truth(7) = -2.0, truth(15) = 1.5, truth(22) = 0.8;
  Eigen::VectorXd y = X * truth + Eigen::VectorXd::Constant(N, 10.0);
  for (int i = 0; i < N; ++i) y(i) += 0.5 * g(rng);
  std::vector<GramStats> blocks;
  for (int k = 0; k < 5; ++k) blocks.push_back(stats(X, y, k * N / 5, (k + 1) * N / 5));
  const LassoPath path = lasso_path_cv(blocks);
  ASSERT_EQ(path.lambdas.size(), 60u);
  EXPECT_GE(path.lambda_1se(), path.lambda_min());
  const Eigen::VectorXd& b = path.coefs[path.index_1se];
  for (int j = 0; j < p; ++j) {
    if (truth(j) != 0) {
      EXPECT_NEAR(b(j), truth(j), 0.1) << j;
    } else {
      EXPECT_EQ(b(j), 0.0) << "spurious feature " << j << " = " << b(j);
    }
  }
  EXPECT_NEAR(path.intercepts[path.index_1se], 10.0, 0.1);
  EXPECT_NEAR(std::sqrt(path.cv_mse[path.index_min]), 0.5, 0.03);  // CV error reaches the noise level
  // The path starts empty (λ_max) and densifies.
  EXPECT_EQ((path.coefs.front().array() != 0).count(), 0);
}

TEST(Lasso, SelectsPlantedFeaturesFromCandidatesOnStreamedData) {
  // Positions made from two physics features; lasso on the candidate set must keep them.
  features::FeatureSpec planted;
  features::FeatureDef play;
  play.type = "play";
  play.threshold_v = 10;
  features::FeatureDef lp;
  lp.type = "lowpass";
  lp.time_constant_s = 36;
  planted.features = {play, lp};
  io::Dataset d = walk_dataset(30000, 7);
  io::AxisSeries& c = d.axis("c");
  const std::vector<double>& v = c.voltage_v;
  std::mt19937_64 rng(1);
  std::normal_distribution<double> noise(0, 5);
  c.position_nm.assign(v.size(), 0.0);
  std::vector<double> pos;
  for_each_sample(planted, d, "c", [&](std::size_t, const double* x, double) { pos.push_back(12 * x[0] + 4 * x[1] + noise(rng)); });
  c.position_nm = pos;
  const LassoSelection sel = run_lasso(features::physics_features(), d, "c");
  const Eigen::VectorXd& b = sel.path.coefs[sel.path.index_1se];
  int play_idx = -1, lp_idx = -1;
  for (std::size_t j = 0; j < sel.spec.size(); ++j) {
    if (sel.spec.features[j].name() == play.name()) play_idx = int(j);
    if (sel.spec.features[j].name() == lp.name()) lp_idx = int(j);
  }
  ASSERT_GE(play_idx, 0);
  ASSERT_GE(lp_idx, 0);
  EXPECT_GT(std::abs(b(play_idx)), 0.0);
  EXPECT_GT(std::abs(b(lp_idx)), 0.0);
  // The two planted features carry almost all of the weight.
  const double planted_weight = std::abs(b(play_idx)) + std::abs(b(lp_idx));
  EXPECT_GT(planted_weight, 0.9 * b.cwiseAbs().sum());
  const std::string report = lasso_report(sel.spec, sel.path);
  EXPECT_NE(report.find(play.name()), std::string::npos);
  EXPECT_NE(report.find("λ_1se"), std::string::npos);
}

// Several fits on one data set (model selection's dense, KAN and LSTM all read voltage_lasso) resolve each lasso
// set once; another slice (the carry-over fold's half) is another entry, so a fold never takes a selection made on
// rows it holds out; without a cache every fit runs its own lasso, with the same result.
TEST(Lasso, ACacheResolvesEachSetOncePerDataSet) {
  io::Dataset d = walk_dataset(6000, 11);
  io::AxisSeries& c = d.axis("c");
  std::mt19937_64 rng(2);
  std::normal_distribution<double> noise(0, 5);
  for (double x : c.voltage_v) c.position_nm.push_back(30 * x + 0.02 * x * std::abs(x) + noise(rng));
  LassoFeatureCache cache;
  FitRequest rq;
  rq.train = &d;
  rq.options = YAML::Load("{features: voltage_lasso}");
  const features::FeatureSpec plain = resolve_features(rq, "study");
  rq.lasso_cache = &cache;
  const features::FeatureSpec first = resolve_features(rq, "study");
  const features::FeatureSpec again = resolve_features(rq, "study");
  EXPECT_EQ(cache.lassos_run(), 1u);
  ASSERT_EQ(first.size(), plain.size());
  ASSERT_EQ(again.size(), plain.size());
  for (std::size_t j = 0; j < plain.size(); ++j) {
    EXPECT_EQ(first.features[j].name(), plain.features[j].name());
    EXPECT_EQ(again.features[j].name(), plain.features[j].name());
    EXPECT_EQ(again.mean[j], plain.mean[j]);
    EXPECT_EQ(again.scale[j], plain.scale[j]);
  }
  const io::Dataset half = d.slice(0, d.size() / 2);
  rq.train = &half;
  resolve_features(rq, "study");
  EXPECT_EQ(cache.lassos_run(), 2u) << "a slice is other data: its own lasso";
  rq.options = YAML::Load("{features: lasso}");
  resolve_features(rq, "study");
  EXPECT_EQ(cache.lassos_run(), 3u) << "another set on the same data: its own lasso";
  rq.options = YAML::Load("{features: voltage_history}");
  resolve_features(rq, "study");
  EXPECT_EQ(cache.lassos_run(), 3u) << "a fixed set runs no lasso";
}
