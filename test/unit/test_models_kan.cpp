// KAN: B-spline basis properties, gradient (incl. spline coefficients) against finite differences, grid update
// keeps the learned functions, formula printing recovers planted functions, fit/save/load/export.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/models/kan_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_dense_data.h"

using namespace piezo;

TEST(KanBasis, PartitionOfUnityAndDerivative) {
  const std::vector<double> t{-3.5, -2.5, -1.5, -0.5, 0.0, 0.7, 1.5, 2.5, 3.5, 4.5, 5.5};  // order 3, grid 4
  const int m = static_cast<int>(t.size()), k = 3;
  for (double x = -0.5; x < 1.5 + 1e-9; x += 0.013) {  // inside the core range the bases sum to 1
    int first = 0;
    double v[4], d[4];
    ASSERT_TRUE(models::bspline_basis(t.data(), m, k, x, &first, v, d));
    EXPECT_NEAR(v[0] + v[1] + v[2] + v[3], 1.0, 1e-12);
    EXPECT_NEAR(d[0] + d[1] + d[2] + d[3], 0.0, 1e-9);
  }
  // Derivative against finite differences of each basis function, also in the extended region.
  for (double x : {-3.0, -1.0, 0.3, 1.1, 3.0, 5.0}) {
    const double h = 1e-6;
    int f0 = 0, fu = 0, fd = 0;
    double v[4], d[4], vu[4], vd[4];
    models::bspline_basis(t.data(), m, k, x, &f0, v, d);
    models::bspline_basis(t.data(), m, k, x + h, &fu, vu, nullptr);
    models::bspline_basis(t.data(), m, k, x - h, &fd, vd, nullptr);
    ASSERT_EQ(f0, fu);
    ASSERT_EQ(f0, fd);
    for (int r = 0; r < 4; ++r) EXPECT_NEAR(d[r], (vu[r] - vd[r]) / (2 * h), 1e-5) << "x " << x << " r " << r;
  }
  int first = 0;
  double v[4];
  EXPECT_FALSE(models::bspline_basis(t.data(), m, k, 6.0, &first, v, nullptr));
}

TEST(KanNet, GradientMatchesFiniteDifferences) {
  models::KanShape s;
  s.widths = {3, 4, 2, 1};
  s.grid = 4;
  s.order = 3;
  const models::KanNet net(s);
  Eigen::VectorXd p = net.initial_params(5);
  std::mt19937_64 rng(8);
  std::normal_distribution<double> n01;
  for (Eigen::Index i = 0; i < p.size(); ++i) p[i] += 0.2 * n01(rng);
  Eigen::MatrixXd x(3, 7);
  Eigen::VectorXd y(7);
  for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] = 1.2 * n01(rng);
  for (Eigen::Index i = 0; i < y.size(); ++i) y[i] = n01(rng);
  Eigen::VectorXd g = Eigen::VectorXd::Zero(p.size());
  const double loss = net.loss_grad(p, x, y, &g);
  double loss_fwd = 0.0;
  for (Eigen::Index c = 0; c < x.cols(); ++c) loss_fwd += std::pow(net.forward(p.data(), x.col(c).data()) - y[c], 2);
  EXPECT_NEAR(loss, loss_fwd, 1e-10);
  Eigen::VectorXd fd(p.size());
  for (Eigen::Index i = 0; i < p.size(); ++i) {
    Eigen::VectorXd q = p;
    const double h = 1e-6;
    q[i] = p[i] + h;
    const double up = net.loss_grad(q, x, y, nullptr);
    q[i] = p[i] - h;
    fd[i] = (up - net.loss_grad(q, x, y, nullptr)) / (2 * h);
  }
  EXPECT_LT((g - fd).norm(), 1e-6 * std::max(1.0, fd.norm()));
  // Spline coefficients get gradient (not only the SiLU weights).
  EXPECT_GT(std::abs(g[net.edge_offset(0, 0, 0) + 3]) + std::abs(g[net.edge_offset(0, 0, 0) + 4]), 0.0);
}

TEST(KanNet, GridUpdateKeepsTheFunctions) {
  models::KanShape s;
  s.widths = {2, 3, 1};
  s.grid = 8;
  const models::KanNet net0(s);
  models::KanNet net = net0;
  Eigen::VectorXd p = net.initial_params(3);
  std::mt19937_64 rng(1);
  std::normal_distribution<double> n01;
  Eigen::MatrixXd x(2, 500);
  for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] = 0.5 * n01(rng) + 0.3;  // narrower than [-2, 2]
  Eigen::VectorXd before(x.cols()), after(x.cols());
  for (Eigen::Index c = 0; c < x.cols(); ++c) before[c] = net.forward(p.data(), x.col(c).data());
  net.update_grids(p, x);
  for (Eigen::Index c = 0; c < x.cols(); ++c) after[c] = net.forward(p.data(), x.col(c).data());
  EXPECT_LT((after - before).cwiseAbs().maxCoeff(), 0.02 * before.cwiseAbs().maxCoeff());
  EXPECT_NE(net.knots(0, 0)[s.order], net0.knots(0, 0)[s.order]);  // the grid moved to the data
}

TEST(KanSymbolic, RecoversPlantedFunctions) {
  std::vector<double> x, y_sin, y_sq, y_lin, y_tanh;
  for (int i = 0; i <= 100; ++i) {
    const double v = -2.0 + 4.0 * i / 100.0;
    x.push_back(v);
    y_sin.push_back(0.7 * std::sin(2.0 * v + 0.5) - 0.1);
    y_sq.push_back(1.5 * v * v - 0.2 * v + 0.3);
    y_lin.push_back(-0.8 * v + 2.0);
    y_tanh.push_back(1.3 * std::tanh(3.0 * v - 1.0));
  }
  const auto fs = models::fit_symbolic(x, y_sin);
  EXPECT_EQ(fs.family, "sin");
  EXPECT_GT(fs.r2, 0.99999);
  EXPECT_NEAR(std::abs(fs.coef[1]), 2.0, 0.01);
  const auto fq = models::fit_symbolic(x, y_sq);
  EXPECT_EQ(fq.family, "x^2");
  EXPECT_NEAR(fq.coef[2], 1.5, 1e-9);
  EXPECT_EQ(models::fit_symbolic(x, y_lin).family, "x");
  const auto ft = models::fit_symbolic(x, y_tanh);
  EXPECT_EQ(ft.family, "tanh");
  EXPECT_GT(ft.r2, 0.9999);
  EXPECT_NE(fq.formula("z0").find("z0^2"), std::string::npos);
}

TEST(KanModel, FitPrintsFormulasAndRoundTrips) {
  const io::Dataset data = test_data::hysteretic_dataset(3000, 31);
  training::FitRequest req;
  req.train = &data;
  req.seed = 2;
  req.options["epochs"] = 10;
  req.options["width"] = 3;
  req.options["grid_updates"] = 2;
  const models::ModelPtr m = training::fit_model("kan", req);
  const double mae = test_data::one_step_mae(*m, data, "c");
  EXPECT_LT(mae, 0.15 * test_data::mean_abs_deviation(data.axis("c").position_nm));

  YAML::Emitter out;
  out << m->to_yaml();
  const models::ModelPtr back = models::model_kind("kan").load(YAML::Load(out.c_str()));
  EXPECT_NEAR(test_data::one_step_mae(*back, data, "c"), mae, 1e-9);

  const auto* kan = dynamic_cast<const models::KanModel*>(m.get());
  ASSERT_NE(kan, nullptr);
  const std::string text = kan->formulas();
  EXPECT_NE(text.find("R²"), std::string::npos);
  EXPECT_NE(text.find("z0 -> h1_0"), std::string::npos);

  const std::string c = models::model_kind("kan").export_c99(*m, "pz");
  EXPECT_NE(c.find("pz_network(const double* x)"), std::string::npos);
  EXPECT_LT(test_data::c_export_max_diff(*m, c, data, "c"), 1e-10);

  YAML::Node bad = m->to_yaml();
  bad["grids"][0][1] = -100.0;
  EXPECT_THROW(models::model_kind("kan").load(bad), std::runtime_error);
  bad = m->to_yaml();
  bad["hyperparameters"]["widths"][0] = 2;
  EXPECT_THROW(models::model_kind("kan").load(bad), std::runtime_error);
}

TEST(KanModel, TuningSearchesGridOrderAndWidth) {
  const io::Dataset data = test_data::hysteretic_dataset(800, 33);
  training::FitRequest req;
  req.train = &data;
  req.tune_trials = 2;
  req.options["epochs"] = 1;
  req.options["grid_updates"] = 1;
  const models::ModelPtr m = training::fit_model("kan", req);
  const YAML::Node h = m->to_yaml()["hyperparameters"];
  EXPECT_GE(h["grid"].as<int>(), 3);
  EXPECT_LE(h["grid"].as<int>(), 20);
  EXPECT_GE(h["order"].as<int>(), 1);
  EXPECT_LE(h["order"].as<int>(), 4);
  EXPECT_EQ(m->to_yaml()["training"]["tuning"]["trials"].as<int>(), 2);
}

// The KAN takes at most KanNet::kMaxWidth inputs: a wider feature set (here 65 plays) is one error naming the count
// and the remedy, before any training.
TEST(KanModel, MoreInputsThanItTakesIsOneClearError) {
  const io::Dataset data = test_data::hysteretic_dataset(800, 35);
  training::FitRequest req;
  req.train = &data;
  YAML::Node list(YAML::NodeType::Sequence);
  for (int i = 0; i < 65; ++i) list.push_back(YAML::Load("{type: play, threshold_v: " + std::to_string(0.1 * (i + 1)) + "}"));
  req.options["features"]["features"] = list;
  req.options["steps"] = 5;
  try {
    training::fit_model("kan", req);
    ADD_FAILURE() << "a KAN with 65 inputs was fitted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("kan: 65 input features, at most 64"), std::string::npos) << e.what();
  }
}
