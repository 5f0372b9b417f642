// Optimisers on known problems, the trainer's early stopping, determinism and time budget, and the TPE search.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <thread>
#include <chrono>
#include <algorithm>

#include "piezo_compensation/training/hyperparameter_search.h"
#include "piezo_compensation/training/optimizer.h"
#include "piezo_compensation/training/trainer.h"

using namespace piezo::training;

namespace {

// Linear least squares y = Xβ* + noise as an Objective (units = samples).
class LinearObjective : public Objective {
 public:
  LinearObjective(std::size_t n, double noise, std::uint64_t seed, Eigen::VectorXd beta) : beta_(std::move(beta)) {
    std::mt19937_64 rng(seed);
    std::normal_distribution<double> n01;
    x_.resize(beta_.size(), static_cast<Eigen::Index>(n));
    y_.resize(static_cast<Eigen::Index>(n));
    for (Eigen::Index i = 0; i < x_.size(); ++i) x_.data()[i] = n01(rng);
    y_ = x_.transpose() * beta_;
    for (Eigen::Index i = 0; i < y_.size(); ++i) y_[i] += noise * n01(rng);
  }
  std::size_t num_units() const override { return static_cast<std::size_t>(x_.cols()); }
  double loss_sum(const Eigen::VectorXd& p, const std::size_t* u, std::size_t n, Eigen::VectorXd* g) const override {
    double loss = 0.0;
    for (std::size_t i = 0; i < n; ++i) {
      const auto c = static_cast<Eigen::Index>(u[i]);
      const double e = x_.col(c).dot(p) - y_[c];
      loss += e * e;
      if (g) *g += 2.0 * e * x_.col(c);
    }
    return loss;
  }
  Eigen::VectorXd beta_;
  Eigen::MatrixXd x_;
  Eigen::VectorXd y_;
};

}  // namespace

TEST(Optimizer, EachKindConvergesOnAQuadratic) {
  // f(p) = Σ a_i (p_i - t_i)², badly scaled.
  const Eigen::Vector3d a(1.0, 10.0, 0.1), target(1.0, -2.0, 3.0);
  for (const char* name : {"adam", "rmsprop", "sgd"}) {
    OptimizerConfig cfg;
    cfg.kind = parse_optimizer(name);
    cfg.learning_rate = cfg.kind == OptimizerKind::SGD ? 0.04 : 0.02;
    cfg.momentum = cfg.kind == OptimizerKind::SGD ? 0.9 : 0.0;
    Optimizer opt(cfg, 3);
    Eigen::VectorXd p = Eigen::VectorXd::Zero(3);
    for (int it = 0; it < 4000; ++it) {
      const Eigen::VectorXd g = 2.0 * a.cwiseProduct(p - target);
      opt.step(p, g);
    }
    EXPECT_LT((p - target).norm(), 0.02) << name;
  }
  EXPECT_THROW(parse_optimizer("lbfgs"), std::runtime_error);
  OptimizerConfig bad;
  bad.learning_rate = -1.0;
  EXPECT_THROW(Optimizer(bad, 2), std::runtime_error);
}

TEST(Trainer, RecoversLinearModelDeterministicallyForAnyThreadCount) {
  const Eigen::Vector4d beta(0.5, -1.0, 2.0, 0.0);
  const LinearObjective train_obj(2000, 0.1, 1, beta), val_obj(400, 0.1, 2, beta);
  TrainerConfig cfg;
  cfg.epochs = 30;
  cfg.batch_size = 64;
  cfg.optimizer.learning_rate = 0.02;
  cfg.seed = 9;
  cfg.threads = 1;
  const TrainResult r1 = train(train_obj, &val_obj, Eigen::VectorXd::Zero(4), cfg);
  EXPECT_LT((r1.params - beta).norm(), 0.05);
  EXPECT_NEAR(r1.best_validation_mse, 0.01, 0.005);  // the noise variance
  cfg.threads = 2;
  const TrainResult r2 = train(train_obj, &val_obj, Eigen::VectorXd::Zero(4), cfg);
  EXPECT_EQ(r1.params, r2.params);  // bit-identical: fixed shards summed in order
  EXPECT_EQ(r1.validation_mse, r2.validation_mse);
  cfg.seed = 10;
  const TrainResult r3 = train(train_obj, &val_obj, Eigen::VectorXd::Zero(4), cfg);
  EXPECT_NE(r1.params, r3.params);
  EXPECT_NEAR(mean_loss(val_obj, r1.params, 1), mean_loss(val_obj, r1.params, 2), 0.0);
}

TEST(Trainer, EarlyStoppingTriggersAndKeepsTheBestEpoch) {
  // Validation data from another β: training improves the train loss while the validation loss gets worse
  // after the first epochs, so training stops after `patience` epochs without improvement.
  const LinearObjective train_obj(1000, 0.1, 3, Eigen::Vector2d(1.0, 1.0));
  const LinearObjective val_obj(300, 0.1, 4, Eigen::Vector2d(0.2, 0.2));
  TrainerConfig cfg;
  cfg.epochs = 200;
  cfg.batch_size = 50;
  cfg.patience = 3;
  cfg.optimizer.learning_rate = 0.01;
  const TrainResult r = train(train_obj, &val_obj, Eigen::VectorXd::Zero(2), cfg);
  EXPECT_TRUE(r.stopped_early);
  EXPECT_LT(r.epochs_run, 200);
  EXPECT_EQ(r.epochs_run, r.best_epoch + cfg.patience);
  const double best = *std::min_element(r.validation_mse.begin(), r.validation_mse.end());
  EXPECT_DOUBLE_EQ(r.best_validation_mse, best);
  EXPECT_NEAR(mean_loss(val_obj, r.params, 2), best, 1e-12);  // best weights restored

  // Without validation, every epoch runs.
  cfg.epochs = 5;
  const TrainResult all = train(train_obj, nullptr, Eigen::VectorXd::Zero(2), cfg);
  EXPECT_EQ(all.epochs_run, 5);
  EXPECT_FALSE(all.stopped_early);
}

TEST(Trainer, StepBudgetStopsMidEpochAndIsDeterministic) {
  // 1000 samples in batches of 64: 16 steps per epoch, so a budget of 40 steps ends inside epoch 3.
  const LinearObjective train_obj(1000, 0.1, 5, Eigen::Vector2d(1.0, -1.0)), val_obj(200, 0.1, 6, Eigen::Vector2d(1.0, -1.0));
  TrainerConfig cfg;
  cfg.epochs = 1000;
  cfg.batch_size = 64;
  cfg.patience = 0;
  cfg.max_steps = 40;
  const TrainResult a = train(train_obj, &val_obj, Eigen::VectorXd::Zero(2), cfg);
  EXPECT_TRUE(a.hit_step_budget);
  EXPECT_EQ(a.steps, 40);
  EXPECT_EQ(a.epochs_run, 3);
  EXPECT_EQ(a.validation_mse.size(), 3u);  // the partial epoch is validated too
  cfg.threads = 1;
  const TrainResult b = train(train_obj, &val_obj, Eigen::VectorXd::Zero(2), cfg);
  EXPECT_EQ(a.params, b.params);
  cfg.max_steps = 0;
  cfg.epochs = 2;
  const TrainResult c = train(train_obj, &val_obj, Eigen::VectorXd::Zero(2), cfg);
  EXPECT_FALSE(c.hit_step_budget);
  EXPECT_EQ(c.steps, 32);
}

TEST(Trainer, RejectsBadConfigAndDivergence) {
  const LinearObjective obj(100, 0.1, 3, Eigen::Vector2d(1.0, 1.0));
  TrainerConfig cfg;
  cfg.epochs = 0;
  EXPECT_THROW(train(obj, nullptr, Eigen::VectorXd::Zero(2), cfg), std::runtime_error);
  cfg.epochs = 2000;
  cfg.patience = 0;  // keep going while the validation loss explodes
  cfg.optimizer.kind = OptimizerKind::SGD;
  cfg.optimizer.learning_rate = 10.0;  // far beyond stability
  EXPECT_THROW(train(obj, &obj, Eigen::VectorXd::Zero(2), cfg), std::runtime_error);
}

TEST(HyperparameterSearch, TpeFindsTheOptimumAndIsDeterministic) {
  // Minimum at depth 2, width 12, adam, lr 1e-3.
  auto objective = [](const TrialParams& p, int, double) {
    const double lr = std::log10(p.number.at("learning_rate")) + 3.0;
    const double d = p.number.at("depth") - 2.0, w = (p.number.at("width") - 12.0) / 4.0;
    return lr * lr + d * d + w * w + (p.choice.at("optimizer") == "adam" ? 0.0 : 1.0);
  };
  SearchConfig cfg;
  cfg.trials = 60;
  cfg.seed = 4;
  const SearchResult a = tpe_search(dense_search_space(), cfg, objective);
  ASSERT_EQ(a.trials.size(), 60u);
  EXPECT_LT(a.best_trial().value, 0.5);
  EXPECT_EQ(a.best_trial().params.choice.at("optimizer"), "adam");
  for (const auto& t : a.trials) {  // every draw inside the study's space
    EXPECT_GE(t.params.number.at("depth"), 1);
    EXPECT_LE(t.params.number.at("depth"), 5);
    EXPECT_EQ(t.params.number.at("width"), std::round(t.params.number.at("width")));
    EXPECT_GE(t.params.number.at("learning_rate"), 1e-5);
    EXPECT_LE(t.params.number.at("learning_rate"), 1e-1);
  }
  const SearchResult b = tpe_search(dense_search_space(), cfg, objective);
  for (std::size_t i = 0; i < a.trials.size(); ++i) EXPECT_EQ(a.trials[i].params.to_string(), b.trials[i].params.to_string());

  // TPE beats its own random start-up phase run for all trials (same budget), on average over seeds.
  double tpe = 0, rnd = 0;
  for (std::uint64_t s = 1; s <= 5; ++s) {
    SearchConfig c = cfg;
    c.trials = 40;
    c.seed = s;
    tpe += tpe_search(dense_search_space(), c, objective).best_trial().value;
    c.startup_trials = 40;
    rnd += tpe_search(dense_search_space(), c, objective).best_trial().value;
  }
  EXPECT_LT(tpe, rnd);
}

TEST(HyperparameterSearch, FailedTrialsAndTimeBudget) {
  SearchConfig cfg;
  cfg.trials = 10;
  int calls = 0;
  const SearchResult r = tpe_search(lstm_search_space(), cfg, [&](const TrialParams& p, int trial, double) {
    ++calls;
    if (trial % 2 == 0) throw std::runtime_error("diverged");
    return p.number.at("hidden");
  });
  EXPECT_EQ(calls, 10);
  EXPECT_TRUE(std::isfinite(r.best_trial().value));
  EXPECT_TRUE(std::isinf(r.trials[0].value));

  cfg.trials = 1000;
  cfg.time_budget_s = 0.05;
  const SearchResult timed = tpe_search(kan_search_space(), cfg, [](const TrialParams&, int, double left) {
    EXPECT_GT(left, -1.0);
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
    return 1.0;
  });
  EXPECT_LT(timed.trials.size(), 20u);
  EXPECT_GE(timed.trials.size(), 1u);
}
