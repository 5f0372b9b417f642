// LSTM: truncated-BPTT gradient against finite differences (several layers, warm-up, odd sizes), the kernels
// against a plain reference, streaming step equal to the sequence path (bit for bit), NaN propagation,
// predict() leaves (h, c) unchanged, save/load through the registry, determinism.
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

namespace {

// A plain LSTM (std::exp, std::tanh, loops in the parameter layout of LstmNet) for one sequence from the zero
// state: the outputs of every step.
std::vector<double> reference_outputs(const models::LstmShape& s, const Eigen::VectorXd& p,
                                      const std::vector<std::vector<double>>& xs) {
  const int H = s.hidden;
  std::vector<std::vector<double>> h(s.layers, std::vector<double>(H, 0.0)), c = h;
  std::vector<double> out;
  for (const auto& x : xs) {
    std::vector<double> input = x;
    std::size_t o = 0;
    for (int l = 0; l < s.layers; ++l) {
      const int in = static_cast<int>(input.size());
      const double *W = p.data() + o, *U = W + 4 * H * in, *b = U + 4 * H * H;
      std::vector<double> z(4 * H);
      for (int r = 0; r < 4 * H; ++r) {
        z[r] = b[r];
        for (int k = 0; k < in; ++k) z[r] += W[r + 4 * H * k] * input[k];
        for (int k = 0; k < H; ++k) z[r] += U[r + 4 * H * k] * h[l][k];
      }
      auto sig = [](double v) { return 1.0 / (1.0 + std::exp(-v)); };
      for (int j = 0; j < H; ++j) {
        c[l][j] = sig(z[H + j]) * c[l][j] + sig(z[j]) * std::tanh(z[2 * H + j]);
        h[l][j] = sig(z[3 * H + j]) * std::tanh(c[l][j]);
      }
      o += static_cast<std::size_t>(4 * H * (in + H + 1));
      input = h[l];
    }
    double y = p[static_cast<Eigen::Index>(o) + H];
    for (int j = 0; j < H; ++j) y += p[static_cast<Eigen::Index>(o) + j] * input[j];
    out.push_back(y);
  }
  return out;
}

// Random sequences in the layout of sequence_loss_grad (inputs × steps·B, step-major), random parameters.
struct Problem {
  models::LstmShape shape;
  Eigen::VectorXd params;
  Eigen::MatrixXd x, ys;
};
Problem problem(int inputs, int layers, int hidden, int steps, int T, int B, double param_scale,
                std::uint64_t seed) {
  Problem pr;
  pr.shape = {inputs, layers, hidden};
  const models::LstmNet net(pr.shape);
  pr.params = net.initial_params(seed);
  std::mt19937_64 rng(seed + 1);
  std::normal_distribution<double> n01;
  for (Eigen::Index i = 0; i < pr.params.size(); ++i)
    pr.params[i] = param_scale * (pr.params[i] + 0.3 * n01(rng));
  pr.x.resize(inputs, steps * B);
  for (Eigen::Index i = 0; i < pr.x.size(); ++i) pr.x.data()[i] = 2.0 * n01(rng);
  pr.ys.resize(T, B);
  for (Eigen::Index i = 0; i < pr.ys.size(); ++i) pr.ys.data()[i] = n01(rng);
  return pr;
}

}  // namespace

// The vectorised kernels (sizes that are not multiples of their vector width and tiles, saturated gates)
// against the plain reference: the sequence path and the streaming step.
TEST(LstmNet, MatchesAPlainReference) {
  for (int hidden : {5, 1, 8}) {
    const int warmup = 2, T = 4, B = 7;
    const Problem pr = problem(3, 3, hidden, warmup + T, T, B, 3.0, 40 + static_cast<std::uint64_t>(hidden));
    const models::LstmNet net(pr.shape);
    double loss = 0.0;
    for (int j = 0; j < B; ++j) {
      std::vector<std::vector<double>> xs;
      for (int tau = 0; tau < warmup + T; ++tau) {
        const auto col = pr.x.col(tau * B + j);
        xs.emplace_back(col.data(), col.data() + col.size());
      }
      const std::vector<double> ref = reference_outputs(pr.shape, pr.params, xs);
      std::vector<double> h(static_cast<std::size_t>(3 * hidden), 0.0), c = h;
      for (int tau = 0; tau < warmup + T; ++tau) {
        const double y = net.step(pr.params.data(), xs[tau].data(), h.data(), c.data(), h.data(), c.data());
        EXPECT_NEAR(y, ref[tau], 1e-12 * std::max(1.0, std::abs(ref[tau]))) << "hidden " << hidden;
      }
      for (int t = 0; t < T; ++t) loss += std::pow(ref[warmup + t] - pr.ys(t, j), 2);
    }
    EXPECT_NEAR(net.sequence_loss_grad(pr.params, pr.x, pr.ys, warmup, nullptr), loss, 1e-11 * loss);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(pr.params.size());
    EXPECT_NEAR(net.sequence_loss_grad(pr.params, pr.x, pr.ys, warmup, &g), loss, 1e-11 * loss);
  }
}

// The gradient at sizes that exercise every tail of the kernels: hidden not a multiple of 4 (the padded
// transposes), batches that are not multiples of the column tiles, three layers.
TEST(LstmNet, BpttGradientMatchesFiniteDifferencesAtOddSizes) {
  for (int hidden : {5, 1}) {
    const int T = 4, B = 6;
    const Problem pr = problem(3, 3, hidden, T, T, B, 1.0, 7 + static_cast<std::uint64_t>(hidden));
    const models::LstmNet net(pr.shape);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(pr.params.size());
    net.sequence_loss_grad(pr.params, pr.x, pr.ys, 0, &g);
    Eigen::VectorXd fd(pr.params.size());
    for (Eigen::Index i = 0; i < pr.params.size(); ++i) {
      Eigen::VectorXd q = pr.params;
      const double h = 1e-6;
      q[i] = pr.params[i] + h;
      const double up = net.sequence_loss_grad(q, pr.x, pr.ys, 0, nullptr);
      q[i] = pr.params[i] - h;
      const double down = net.sequence_loss_grad(q, pr.x, pr.ys, 0, nullptr);
      fd[i] = (up - down) / (2 * h);
    }
    EXPECT_LT((g - fd).norm(), 1e-6 * std::max(1.0, fd.norm())) << "hidden " << hidden;
  }
}

// Streaming and training compute the same sums in the same order: the streaming outputs as targets give a
// loss of exactly zero, batch and warm-up included.
TEST(LstmNet, StreamingStepEqualsTrainingBitForBit) {
  const int warmup = 3, T = 5, B = 6, hidden = 7;
  Problem pr = problem(4, 2, hidden, warmup + T, T, B, 1.0, 5);
  const models::LstmNet net(pr.shape);
  for (int j = 0; j < B; ++j) {
    std::vector<double> h(2 * hidden, 0.0), c = h;
    for (int tau = 0; tau < warmup + T; ++tau) {
      const double y =
          net.step(pr.params.data(), pr.x.col(tau * B + j).data(), h.data(), c.data(), h.data(), c.data());
      if (tau >= warmup) pr.ys(tau - warmup, j) = y;
    }
  }
  EXPECT_EQ(net.sequence_loss_grad(pr.params, pr.x, pr.ys, warmup, nullptr), 0.0);
}

// A NaN input reaches the output (the activations clamp their argument, but not NaN).
TEST(LstmNet, NanPropagates) {
  Problem pr = problem(2, 1, 6, 2, 2, 3, 1.0, 9);
  const models::LstmNet net(pr.shape);
  const double x[2] = {0.5, std::nan("")};
  std::vector<double> h(6, 0.0), c = h;
  EXPECT_TRUE(std::isnan(net.step(pr.params.data(), x, h.data(), c.data(), h.data(), c.data())));
  pr.x(1, 4) = std::nan("");
  EXPECT_TRUE(std::isnan(net.sequence_loss_grad(pr.params, pr.x, pr.ys, 0, nullptr)));
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
