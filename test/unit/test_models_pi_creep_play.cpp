// Kind pi_creep_play: exact inverse, monotone loop ends, the fit on its own physics, the model file, clone
// and stream, and the exported C99 header against the C++ stream.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <random>
#include <sstream>

#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_creep_play_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/training/fitters.h"
#include "test_models_data.h"

using namespace piezo;
using models::PiCreepPlayModel;

namespace {

// Six plays over ±80 V; creep on the linear term and on two of the wide plays, each at its own time
// constants; with bends, the linear term curves up and play 2 down on their ranges.
PiCreepPlayModel make_play_model(bool bends = true) {
  const std::vector<double> r = {0, 10, 20, 30, 45, 60}, taus = {5, 60, 600};
  std::vector<double> g(r.size() * taus.size(), 0.0);
  g[0 * 3 + 0] = 0.4, g[0 * 3 + 2] = 0.3;  // linear term: fast and slow creep
  g[3 * 3 + 1] = 0.8;                      // play 3: minute creep
  g[5 * 3 + 2] = 1.2;                      // widest play: slow creep
  models::PlayBends b;
  if (bends) {
    for (double ri : r) b.lo_v.push_back(-80 + ri), b.hi_v.push_back(80 - ri);
    b.convex_nm_per_v = {1.5, 0, 0, 0, 0, 0};
    b.concave_nm_per_v = {0, 0, 1.0, 0, 0, 0};
  }
  return PiCreepPlayModel(r, {8.0, 2.0, 1.5, 1.0, 0.6, 0.4}, taus, g, 30.0, 11.0, b);
}

std::vector<double> stream_of(models::Model& m, const std::vector<double>& v) {
  std::vector<double> y;
  m.reset(v[0], 0);
  for (double x : v) {
    y.push_back(m.predict({x, nullptr}));
    m.commit({x, nullptr}, y.back());
  }
  return y;
}

std::string run_shell(const std::string& cmd) {
  std::string out;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return "FAILED: popen";
  char buf[4096];
  while (std::size_t n = fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  if (const int rc = pclose(p); rc != 0) out = "FAILED(" + std::to_string(rc) + "): " + out;
  return out;
}

}  // namespace

TEST(PiCreepPlay, InverseIsExactOnRandomWalks) {
  for (std::uint64_t seed : {3u, 8u, 21u}) {
    PiCreepPlayModel m = make_play_model(seed != 8u);
    const auto v = testdata::random_walk_v(6000, seed);
    m.reset(v[0], 0);
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u(-1500, 1500), uv(-90, 90);
    double worst = 0;
    for (std::size_t i = 0; i < v.size(); ++i) {
      for (double target : {u(rng), m.predict_v(uv(rng)), m.predict_v(v[i])}) {
        worst = std::max(worst, std::abs(m.predict_v(m.inverse(target)) - target));
      }
      m.commit({v[i], nullptr}, 0);
    }
    EXPECT_LT(worst, 1e-9) << "seed " << seed;
  }
}

TEST(PiCreepPlay, LoopEndsAreMonotone) {
  PiCreepPlayModel m = make_play_model();
  EXPECT_FALSE(m.bends().empty());
  // Every state of a random walk: the prediction strictly increasing in V over the whole range.
  const auto v = testdata::random_walk_v(4000, 5);
  m.reset(v[0], 0);
  for (std::size_t i = 0; i < v.size(); ++i) {
    if (i % 97 == 0) {
      for (double x = -100; x < 100; x += 0.5) ASSERT_LT(m.predict_v(x), m.predict_v(x + 0.5)) << "row " << i;
    }
    m.commit({v[i], nullptr}, 0);
  }
  // A slow sweep: each ascending branch rises, each descending one falls.
  m.reset(-80, 0);
  double prev = m.predict_v(-80);
  for (int pass = 0; pass < 4; ++pass)
    for (int k = 1; k <= 320; ++k) {
      const double x = pass % 2 == 0 ? -80 + 0.5 * k : 80 - 0.5 * k;
      const double y = m.predict_v(x);
      if (pass % 2 == 0)
        EXPECT_GT(y, prev) << pass << " " << k;
      else
        EXPECT_LT(y, prev) << pass << " " << k;
      m.commit({x, nullptr}, y);
      prev = y;
    }
}

TEST(PiCreepPlay, RefusesWhatCouldNotBeInverted) {
  const std::vector<double> r = {0, 10}, taus = {5};
  EXPECT_THROW(PiCreepPlayModel(r, {1.0, -0.1}, taus, {0, 0}, 0, 11), std::runtime_error);  // negative weight
  EXPECT_THROW(PiCreepPlayModel(r, {1.0, 1.0}, taus, {0, -1e-3}, 0, 11),
               std::runtime_error);                                                        // negative gain
  EXPECT_THROW(PiCreepPlayModel(r, {0.0, 1.0}, taus, {0, 0}, 0, 11), std::runtime_error);  // flat linear term
  EXPECT_THROW(PiCreepPlayModel({5, 10}, {1, 1}, taus, {0, 0}, 0, 11), std::runtime_error);  // no linear term
  EXPECT_THROW(PiCreepPlayModel(r, {1, 1}, {}, {}, 0, 11), std::runtime_error);  // no time constant
  EXPECT_NO_THROW(PiCreepPlayModel(r, {0.0, 1.0}, taus, {0.5, 0}, 0, 11));  // the slope comes from the creep
}

TEST(PiCreepPlay, FitRecoversItsOwnPhysics) {
  PiCreepPlayModel truth = make_play_model();
  const auto v = testdata::random_walk_v(30000, 17, 0.003);
  io::Dataset data = testdata::make_dataset(truth, v, 11.0, 5.0, 4);
  io::Dataset train = data.slice(0, 22000), val = data.slice(22000, data.size());
  training::FitRequest req;
  req.train = &train;
  req.validation = &val;
  req.options["thresholds_v"] = truth.thresholds_v();
  req.options["taus_s"] = truth.taus_s();
  auto m = training::fit_model("pi_creep_play", req);
  ASSERT_EQ(m->kind(), "pi_creep_play");
  // Run from the truth's own rest over all rows, scored on the validation rows.
  const auto pred = models::free_run_prediction(*m, data, "c");
  const auto& t = data.axis("c").true_position_nm;
  double mean = 0, mae = 0, span = 0;
  for (std::size_t i = train.size(); i < data.size(); ++i) mean += (t[i] - pred[i]) / double(val.size());
  for (std::size_t i = train.size(); i < data.size(); ++i)
    mae += std::abs(pred[i] + mean - t[i]) / double(val.size());
  for (double x : t) span = std::max(span, std::abs(x));
  EXPECT_LT(mae, 3.0) << "MAE " << mae << " nm of ±" << span;
  const auto* p = dynamic_cast<const PiCreepPlayModel*>(m.get());
  ASSERT_NE(p, nullptr);
  for (double g : p->gains()) EXPECT_GE(g, 0.0);
  EXPECT_GT(p->step_slopes()[0], 0.0);
  EXPECT_GT(m->meta.validation.at("validation_free_run_mae_nm"), 0.0);
  // Defaults (10 plays, 7 time constants) on the same data: within a few nm of the noise.
  training::FitRequest dflt = req;
  dflt.options = YAML::Node();
  auto d = training::fit_model("pi_creep_play", dflt);
  EXPECT_LT(d->meta.validation.at("validation_free_run_mae_nm"), 3.0 * 5.0);
}

TEST(PiCreepPlay, FileRoundTripCloneAndStreamAgree) {
  PiCreepPlayModel m = make_play_model();
  m.meta.axis = "c";
  const YAML::Node file = models::model_to_file_yaml(m);
  auto back = models::model_from_file_yaml(YAML::Load(YAML::Dump(file)), "test");
  ASSERT_EQ(back->kind(), "pi_creep_play");
  const auto v = testdata::random_walk_v(5000, 9);
  const auto a = stream_of(m, v), b = stream_of(*back, v);
  for (std::size_t i = 0; i < v.size(); ++i) ASSERT_EQ(a[i], b[i]) << i;
  // A clone mid-stream continues exactly as the original.
  m.reset(v[0], 0);
  for (std::size_t i = 0; i < 2500; ++i) m.commit({v[i], nullptr}, 0);
  auto c = m.clone();
  for (std::size_t i = 2500; i < v.size(); ++i) {
    ASSERT_EQ(m.predict({v[i], nullptr}), c->predict({v[i], nullptr})) << i;
    m.commit({v[i], nullptr}, 0);
    c->commit({v[i], nullptr}, 0);
  }
  // The one streaming path gives the model's own stream.
  io::Dataset data = testdata::make_dataset(m, v, 11.0, 0.0, 1);
  auto s = back->clone();
  const auto r = models::stream_model(*s, data, "c");
  for (std::size_t i = 0; i < v.size(); ++i)
    ASSERT_EQ(r.prediction[i], data.axis("c").true_position_nm[i]) << i;
  // A negative gain in a file is one clear error.
  YAML::Node bad = YAML::Load(YAML::Dump(file));
  bad["model"]["creep"]["gains_nm_per_v"][0] = -1.0;
  EXPECT_THROW(models::model_from_file_yaml(bad, "bad"), std::runtime_error);
  YAML::Node folded = YAML::Load(YAML::Dump(file));
  folded["model"]["bends"]["concave_nm_per_v"][2] = -0.5;
  EXPECT_THROW(models::model_from_file_yaml(folded, "folded"), std::runtime_error);
}

TEST(PiCreepPlay, LinearStatesShiftThePrediction) {
  PiCreepPlayModel m = make_play_model();
  m.reset(10, 0);
  ASSERT_EQ(m.linear_state_count(), 4u);
  const double before = m.predict_v(12);
  m.shift_linear_state(2, 7.5);
  EXPECT_NEAR(m.predict_v(12) - before, 7.5, 1e-9);
}

TEST(PiCreepPlay, ExportedCMatchesCppStreamAndInverse) {
  for (bool bends : {false, true}) {
    PiCreepPlayModel m = make_play_model(bends);
    const std::string dir = ::testing::TempDir(),
                      tag = "pcp" + std::to_string(::getpid()) + (bends ? "b" : "");
    const std::string hdr = dir + tag + ".h", src = dir + tag + ".c", exe = dir + tag,
                      in = dir + tag + ".txt";
    std::ofstream(hdr) << models::export_c99(m, "pz");
    std::ofstream(src) << "#include <stdio.h>\n#include \"" << hdr << "\"\n"
                       << "int main(void) { pz_state s; double v; int first = 1;\n"
                       << "  while (scanf(\"%lf\", &v) == 1) {\n"
                       << "    if (first) { pz_init(&s, v, 0.0); first = 0; }\n"
                       << "    double inv = pz_inverse(&s, 100.0 + v);\n"
                       << "    printf(\"%.17g %.17g\\n\", pz_step(&s, v, NAN), inv); }\n  return 0; }\n";
    const std::string build =
        run_shell(std::string(PIEZO_C_COMPILER) + " -std=c99 -Wall -Wextra -Werror -pedantic -O2 -o " + exe +
                  " " + src + " -lm 2>&1");
    ASSERT_EQ(build, "") << "C compile failed";
    const auto v = testdata::random_walk_v(4000, 12);
    std::ostringstream os;
    os.precision(17);
    for (double x : v) os << x << "\n";
    std::ofstream(in) << os.str();
    std::istringstream out(run_shell(exe + " < " + in));
    m.reset(v[0], 0);
    std::size_t rows = 0;
    double worst = 0, y_c = 0, inv_c = 0;
    while (out >> y_c >> inv_c) {
      ASSERT_LT(rows, v.size());
      const double x = v[rows++];
      const double inv = m.inverse(100.0 + x), y = m.predict_v(x);
      worst = std::max(
          {worst, std::abs(y_c - y) / (1 + std::abs(y)), std::abs(inv_c - inv) / (1 + std::abs(inv))});
      m.commit({x, nullptr}, y);
    }
    EXPECT_EQ(rows, v.size());
    EXPECT_LT(worst, 1e-12) << (bends ? "with bends" : "straight");
  }
}
