#include <gtest/gtest.h>

#include <random>

#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_model_text.h"
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

// A PI kind with an input map (the memory-free play cut into pieces): still a PI kind, the file round-trips, the
// inverse is exact, and a map anywhere but on the first play, or on a preisach kind, is refused.
TEST(PiModel, AnInputMapKeepsThePiKindRoundTripsAndInverts) {
  CreepParams cp;
  cp.kind = models::CreepKind::kFractional;
  cp.alpha = 0.4, cp.b_nm_per_v = 0.3, cp.tau_min_s = 1, cp.tau_max_s = 1000, cp.modes_per_decade = 2;
  const std::vector<std::vector<double>> knots = {{-40, 0, 40}, {}, {}};
  const PiCreepModel m({0, 10, 20}, {4, 6, 9, 12, 1, 0.5}, 3.0, cp, 11.0, knots, true);
  EXPECT_EQ(m.kind(), "pi_creep_fractional");
  EXPECT_TRUE(m.has_input_map());
  EXPECT_FALSE(m.preisach());
  EXPECT_EQ(m.num_parameters(), 6u + 1u + 2u);
  const std::string text = model_file_text(m);
  EXPECT_NE(text.find("input_map"), std::string::npos);
  EXPECT_EQ(text.find("preisach"), std::string::npos);
  EXPECT_EQ(model_file_text(*model_from_text(text)), text);
  PiCreepModel run = m;
  run.reset(0, 0);
  for (int t = 0; t < 300; ++t) {
    const double v = 70 * std::sin(0.04 * t) + 6 * std::sin(0.5 * t);
    for (double target : {-500.0, -60.0, 0.0, 80.0, 700.0}) EXPECT_NEAR(run.predict_v(run.inverse(target)), target, 1e-7);
    run.commit({v, nullptr}, 0);
  }
  EXPECT_THROW(PiCreepModel({0, 10, 20}, {4, 6, 9, 12, 1, 1}, 3.0, {}, 11.0, {{-40, 0, 40}, {5}, {}}, true),
               std::runtime_error);  // knots on a play with memory
  EXPECT_NE(load_error_after(text, "knots_v: [-40, 0, 40]", "knots_v: [-40, 50, 40]").find("increase"), std::string::npos);
  EXPECT_NE(load_error_after(text, "knots_v: [-40, 0, 40]", "knot_v: [-40, 0, 40]").find("model.input_map"), std::string::npos);
  EXPECT_NE(load_error_after(text, "kind: pi_creep_fractional", "kind: preisach").find("input_map"), std::string::npos);
}

// Asymmetric hysteresis (a PI stage plus a term quadratic in V, a form the piecewise-linear map only approximates):
// the PI fit takes the input map by validation and leaves a fraction of the error; on symmetric data it keeps plain PI.
TEST(PiModel, FitTakesTheInputMapWhereTheLoopsAreAsymmetric) {
  const auto v = testdata::random_walk_v(24000, 7);
  auto fit = [&](double quadratic_nm, const char* input_map) {
    PiCreepModel truth = make_pi();
    io::Dataset d = testdata::make_dataset(truth, v, 11.0, 5.0, 3);
    auto& c = d.axis("c");
    for (std::size_t i = 0; i < v.size(); ++i) {
      const double q = quadratic_nm * (v[i] / 80.0) * (v[i] / 80.0);
      c.true_position_nm[i] += q, c.position_nm[i] += q;
    }
    const io::Dataset train = d.slice(0, 18000), val = d.slice(18000, v.size());
    training::FitRequest req;
    req.train = &train;
    req.validation = &val;
    if (*input_map) req.options["input_map"] = input_map;
    auto m = training::fit_model("pi", req);
    // Free run over the whole recording (PI reads no positions), scored on the validation part against the truth.
    const std::vector<double> p = models::stream_model(*m, d, "c").prediction;
    double mae = 0;
    for (std::size_t i = 18000; i < v.size(); ++i) mae += std::abs(p[i] - c.true_position_nm[i]) / (v.size() - 18000);
    return std::make_pair(m->meta.validation.at("fit_input_map_pieces"), mae);
  };
  const auto [pieces, mae] = fit(150.0, "auto");
  const auto [pieces_off, mae_off] = fit(150.0, "");  // the default: off
  std::printf("asymmetric: input map of %.0f pieces %.2f nm vs truth, without %.2f nm\n", pieces, mae, mae_off);
  EXPECT_GT(pieces, 1.0);
  EXPECT_EQ(pieces_off, 0.0);
  EXPECT_LT(mae, 0.5 * mae_off);
  const auto [pieces_sym, mae_sym] = fit(0.0, "auto");
  std::printf("symmetric: input map of %.0f pieces, %.2f nm vs truth\n", pieces_sym, mae_sym);
  EXPECT_EQ(pieces_sym, 0.0);
}

// An output map (a monotone cubic of the hysteresis output): the file round-trips, the inverse is exact through the
// bend and beyond the map's range, and a bend that would fold a branch back is refused on load.
TEST(PiModel, AnOutputMapRoundTripsInvertsAndRefusesAFold) {
  CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {5, 200}, cp.gains_nm_per_v = {0.4, 0.8}, cp.on_hysteresis = true;
  PiCreepModel m = make_pi(cp);
  models::OutputMap map;
  map.lo_nm = -700, map.hi_nm = 700, map.quadratic_nm = 90, map.cubic_nm = -60;
  m.set_output_map(map);
  EXPECT_GT(m.output_map().min_slope(), 0.4);
  EXPECT_EQ(m.num_parameters(), make_pi(cp).num_parameters() + 2u);
  const std::string text = model_file_text(m);
  EXPECT_NE(text.find("output_map"), std::string::npos);
  EXPECT_EQ(model_file_text(*model_from_text(text)), text);
  PiCreepModel run = m, plain = make_pi(cp);
  run.reset(0, 0), plain.reset(0, 0);
  double bend = 0;
  for (int t = 0; t < 400; ++t) {
    const double v = 70 * std::sin(0.03 * t) + 6 * std::sin(0.5 * t);
    for (double target : {-2500.0, -600.0, 0.0, 90.0, 650.0, 2600.0})
      EXPECT_NEAR(run.predict_v(run.inverse(target)), target, 1e-6);
    bend = std::max(bend, std::abs(run.predict_v(v) - plain.predict_v(v)));
    run.commit({v, nullptr}, 0), plain.commit({v, nullptr}, 0);
  }
  EXPECT_GT(bend, 50.0);  // the map is in the prediction, not only in the file
  EXPECT_NE(load_error_after(text, "cubic_nm: -60", "cubic_nm: -900").find("not increasing"), std::string::npos);
  EXPECT_NE(load_error_after(text, "quadratic_nm: 90", "quadratic: 90").find("model.output_map"), std::string::npos);
  map.hi_nm = map.lo_nm;
  EXPECT_THROW(m.set_output_map(map), std::runtime_error);
}

// A stage whose loop is bent by a static map of its hysteresis output: the fit with output_map on recovers most of
// the bend (scored on the shape: the validation part's mean error taken out), auto takes it by validation; on the
// same stage without the bend auto leaves it out.
TEST(PiModel, FitTakesTheOutputMapWhereTheLoopIsBent) {
  const std::size_t N = 60000, split = 30000;  // 45 min of validation at 11 Hz: 9 blocks of 5 min
  const auto v = testdata::random_walk_v(N, 11);
  auto fit = [&](bool bent, const char* option) {
    PiCreepModel truth = make_pi();
    if (bent) {
      models::OutputMap map;
      map.lo_nm = -1500, map.hi_nm = 1500, map.quadratic_nm = 150, map.cubic_nm = -100;  // beyond the walk
      truth.set_output_map(map);
    }
    const io::Dataset d = testdata::make_dataset(truth, v, 11.0, 5.0, 3);
    const io::Dataset train = d.slice(0, split), val = d.slice(split, N);
    training::FitRequest req;
    req.train = &train;
    req.validation = &val;
    req.options["output_map"] = option;
    auto m = training::fit_model("pi", req);
    const std::vector<double> p = models::stream_model(*m, d, "c").prediction;
    const auto& c = d.axis("c");
    double offset = 0, mae = 0;
    for (std::size_t i = split; i < N; ++i) offset += (p[i] - c.true_position_nm[i]) / double(N - split);
    for (std::size_t i = split; i < N; ++i) mae += std::abs(p[i] - offset - c.true_position_nm[i]) / double(N - split);
    const auto it = m->meta.validation.find("fit_output_map");
    return std::make_pair(it == m->meta.validation.end() ? -1.0 : it->second, mae);
  };
  const auto [on, mae_on] = fit(true, "on");
  const auto [off, mae_off] = fit(true, "off");
  const auto [taken, mae_auto] = fit(true, "auto");
  std::printf("bent loop: with the map %.2f nm vs truth, without %.2f nm, auto %.2f nm (map %.0f)\n", mae_on, mae_off,
              mae_auto, taken);
  EXPECT_EQ(on, 1.0);
  EXPECT_EQ(off, -1.0);  // off: no map fitted, nothing recorded
  EXPECT_LT(mae_on, 0.3 * mae_off);
  EXPECT_EQ(taken, 1.0);
  const auto [plain, mae_plain] = fit(false, "auto");
  std::printf("plain loop: auto %.2f nm vs truth (map %.0f)\n", mae_plain, plain);
  EXPECT_EQ(plain, 0.0);
}

// The fitted map never bends a branch flatter than kMinMapSlope (0.2, training/fit_output_map.cpp): on a stage whose
// bend folds its branch back (slope −0.6 at the low end of its range) the least-squares map is shrunk towards the
// identity until its smallest slope is 0.2. And auto needs at least 4 moving 5-min blocks of validation to take a
// map: 15 min of it (3 blocks) keeps plain PI on a stage the map clearly helps, 45 min (9 blocks) takes it.
TEST(PiModel, TheFittedMapStaysIncreasingAndAutoNeedsFourMovingBlocks) {
  auto fit = [](double bend, std::size_t val_rows, const char* option) {
    const std::size_t train_rows = 30000;
    const auto v = testdata::random_walk_v(train_rows + val_rows, 11);
    PiCreepModel truth = make_pi();
    io::Dataset d = testdata::make_dataset(truth, v, 11.0, 5.0, 3);
    auto& c = d.axis("c");
    const auto [lo, hi] = std::minmax_element(c.true_position_nm.begin(), c.true_position_nm.end());
    const double mid = 0.5 * (*lo + *hi), half = 0.5 * (*hi - *lo);
    for (std::size_t i = 0; i < v.size(); ++i) {  // a bend of the position itself: bend·half·z², z on its range
      const double z = (c.true_position_nm[i] - mid) / half, q = bend * half * z * z;
      c.true_position_nm[i] += q, c.position_nm[i] += q;
    }
    const io::Dataset train = d.slice(0, train_rows), val = d.slice(train_rows, train_rows + val_rows);
    training::FitRequest req;
    req.train = &train;
    req.validation = &val;
    req.options["output_map"] = option;
    return training::fit_model("pi", req);
  };
  const auto folded = fit(0.8, 6000, "on");  // dS/dp = 1 + 1.6·z: −0.6 at z = −1
  const auto* pi = dynamic_cast<const PiCreepModel*>(folded.get());
  ASSERT_TRUE(pi);
  std::printf("folding bend: fitted map slope at least %.3f\n", pi->output_map().min_slope());
  EXPECT_FALSE(pi->output_map().empty());
  EXPECT_GE(pi->output_map().min_slope(), 0.2 - 1e-9);
  EXPECT_LT(pi->output_map().min_slope(), 0.2 + 1e-3);  // shrunk to the floor, not past it
  const auto short_val = fit(0.1, 9900, "auto");  // 15 min at 11 Hz: 3 blocks of 5 min
  EXPECT_EQ(short_val->meta.validation.at("fit_output_map"), 0.0);
  const auto long_val = fit(0.1, 30000, "auto");  // 45 min: 9 blocks
  EXPECT_EQ(long_val->meta.validation.at("fit_output_map"), 1.0);
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

// What tools ask of a kind without a cast (models/model.h): the PI family answers for itself, an augmented model
// passes the creep question to its base and is no PI model itself.
TEST(PiModel, AnswersTheKindQueries) {
  CreepParams cp;
  cp.kind = models::CreepKind::kLti;
  cp.taus_s = {20, 400};
  cp.gains_nm_per_v = {0.4, 0.8};
  auto pi = std::make_unique<PiCreepModel>(make_pi(cp));
  const models::Model& m = *pi;
  EXPECT_EQ(m.pi_family(), pi.get());
  EXPECT_TRUE(m.takes_output_map());
  EXPECT_EQ(m.creep_mode_taus_s(), (std::vector<double>{20, 400}));
  EXPECT_TRUE(make_pi().creep_mode_taus_s().empty());  // no creep law: no modes
  const models::AugmentedModel aug(std::move(pi), {}, 0.0, 11.0);
  EXPECT_EQ(aug.creep_mode_taus_s(), (std::vector<double>{20, 400}));
  EXPECT_EQ(aug.pi_family(), nullptr);
  EXPECT_FALSE(aug.takes_output_map());
}

// The term kinds' names: the one conversion, both ways, and an unknown name refused naming the known ones.
TEST(PiModel, TermKindNamesRoundTrip) {
  for (int k = 0; k <= static_cast<int>(models::TermKind::kGainQuadratic); ++k) {
    const auto kind = static_cast<models::TermKind>(k);
    EXPECT_EQ(models::term_kind(models::term_kind_name(kind)), kind);
  }
  EXPECT_STREQ(models::term_kind_name(models::TermKind::kSinCos), "sincos");
  try {
    models::term_kind("cosine");
    ADD_FAILURE() << "an unknown term type was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("gain_quadratic"), std::string::npos);
  }
}
