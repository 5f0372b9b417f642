#include <gtest/gtest.h>

#include <random>

#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_data.h"

using namespace piezo;
using models::CreepParams;
using models::PiCreepModel;

namespace {
PiCreepModel make_pi(CreepParams cp = {}) {
  return PiCreepModel({0, 8, 16, 24, 32, 40, 48, 56}, {9.0, 2.0, 1.5, 1.0, 0.8, 0.5, 0.3, 0.2}, 25.0, cp, 11.0);
}
}  // namespace

TEST(PiModel, ClassicalInverseComposedWithPiIsIdentity) {
  PiCreepModel pi = make_pi();
  pi.reset(0, 0);
  models::PiInverse inv(pi.thresholds_v(), pi.weights(), pi.bias_nm());
  inv.reset(pi.bias_nm());  // both from the zero state
  const auto v = testdata::random_walk_v(20000, 11);
  double max_err = 0;
  for (double x : v) {
    const double y = pi.predict_v(x);
    pi.commit({x, nullptr}, y);
    max_err = std::max(max_err, std::abs(inv.step(y) - x));
  }
  EXPECT_LT(max_err, 1e-9);
  EXPECT_THROW(models::PiInverse({0, 1}, {0.0, 1.0}, 0), std::runtime_error);  // w_0 = 0: no inverse
}

TEST(PiModel, StateInverseHitsEveryTargetWithCreep) {
  CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {20, 400};
  cp.gains_nm_per_v = {1.0, 0.5};
  PiCreepModel m = make_pi(cp);
  const auto v = testdata::random_walk_v(3000, 5);
  m.reset(v[0], 0);
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(-1500, 1500);
  for (std::size_t i = 0; i < v.size(); ++i) {
    if (i % 50 == 0) {
      const double target = u(rng);
      const double vin = m.inverse(target);
      EXPECT_NEAR(m.predict_v(vin), target, 1e-7) << i;
    }
    m.commit({v[i], nullptr}, 0);
  }
}

TEST(PiModel, FitRecoversWeightsAndKeepsThemInvertible) {
  PiCreepModel truth = make_pi();
  const auto v = testdata::random_walk_v(30000, 21);
  const io::Dataset d = testdata::make_dataset(truth, v, 11.0, 0.0, 1);
  training::FitRequest req;
  req.train = &d;
  req.options["thresholds_v"] = std::vector<double>{0, 8, 16, 24, 32, 40, 48, 56};
  auto fitted = training::fit_model("pi", req);
  const auto& m = dynamic_cast<const PiCreepModel&>(*fitted);
  for (std::size_t i = 0; i < truth.weights().size(); ++i) EXPECT_NEAR(m.weights()[i], truth.weights()[i], 1e-4) << i;
  EXPECT_NEAR(m.bias_nm(), truth.bias_nm(), 1e-3);
  // With noise the weights stay non-negative and w_0 > 0 (constrained LS), so the inverse exists.
  const io::Dataset noisy = testdata::make_dataset(truth, v, 11.0, 20.0, 2);
  req.train = &noisy;
  req.options = YAML::Node();
  req.options["n_play"] = 20;  // more operators than the truth: some weights hit the bound
  auto f2 = training::fit_model("pi", req);
  const auto& m2 = dynamic_cast<const PiCreepModel&>(*f2);
  EXPECT_GT(m2.weights()[0], 0.0);
  for (double w : m2.weights()) EXPECT_GE(w, 0.0);
  EXPECT_NO_THROW(models::PiInverse(m2.thresholds_v(), m2.weights(), m2.bias_nm()));
}

TEST(Nnls, MatchesBruteForceOnSmallProblem) {
  // min ½xᵀGx − cᵀx, x0 free, x1..x2 ≥ 0: compare with enumerating all active sets.
  Eigen::MatrixXd A(6, 3);
  A << 1, 2, 0.5, 0.3, -1, 2, 2, 0.1, 1, -1, 1, 1, 0.5, 0.5, -2, 1, 1, 1;
  Eigen::VectorXd y(6);
  y << 1, -2, 0.5, 3, -1, 0.2;
  const Eigen::MatrixXd G = A.transpose() * A;
  const Eigen::VectorXd c = A.transpose() * y;
  const Eigen::VectorXd x = training::nnls_gram(G, c, {false, true, true});
  double best = INFINITY;
  Eigen::VectorXd best_x;
  for (int mask = 0; mask < 4; ++mask) {
    std::vector<int> idx = {0};
    if (mask & 1) idx.push_back(1);
    if (mask & 2) idx.push_back(2);
    Eigen::MatrixXd Gs(idx.size(), idx.size());
    Eigen::VectorXd cs(idx.size());
    for (std::size_t a = 0; a < idx.size(); ++a) {
      cs(a) = c(idx[a]);
      for (std::size_t b = 0; b < idx.size(); ++b) Gs(a, b) = G(idx[a], idx[b]);
    }
    Eigen::VectorXd s = Gs.ldlt().solve(cs), full = Eigen::VectorXd::Zero(3);
    bool feasible = true;
    for (std::size_t a = 0; a < idx.size(); ++a) {
      full(idx[a]) = s(a);
      if (idx[a] > 0 && s(a) < 0) feasible = false;
    }
    const double f = 0.5 * full.dot(G * full) - c.dot(full);
    if (feasible && f < best) best = f, best_x = full;
  }
  EXPECT_LT((x - best_x).norm(), 1e-9);
}
