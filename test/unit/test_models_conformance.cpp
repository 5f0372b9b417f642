// Every registered model kind (models::model_kind_names()) meets the Model contract: fitted by its fitter on a short
// simulation (or, for a kind that cannot be fitted on its own, built on a fitted base), it reports its own kind,
// survives a model-file round trip, streams the same from a clone as from the original in both modes, gives what its
// C export gives where it has one, and either runs at another sample period or refuses it with its reason.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <set>
#include <string>

#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/training/fitters.h"
#include "test_c_export.h"
#include "test_model_text.h"

using namespace piezo;

namespace {

// Kinds with no fitter of their own: what builds them (`piezo residual` for augmented).
const std::set<std::string> kLoadOnlyKinds = {"augmented"};
const std::set<std::string> kNeuralKinds = {"dense", "lstm", "kan"};

// 15 min of the MM3E PI-creep stage at 11 Hz: the first 60 % to fit, the next 20 % to validate, the rest to stream.
struct Data {
  io::Dataset all, train, val, rest;
};
const Data& data() {
  static const Data d = [] {
    Data x;
    const sim::StageConfig st = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_pi_creep.yaml");
    x.all = sim::simulate_stage(st, 31, 900.0);
    const std::size_t n = x.all.size();
    x.train = x.all.slice(0, n * 3 / 5);
    x.val = x.all.slice(n * 3 / 5, n * 4 / 5);
    x.rest = x.all.slice(n * 4 / 5, n);
    return x;
  }();
  return d;
}

// An augmented model: a fitted PI base and one linear term on the voltage.
models::ModelPtr augmented(const training::FitRequest& req) {
  models::ModelPtr base = training::fit_model("pi", req);
  models::EffectTerm t;
  t.type = "linear";
  t.signal = models::kSignalVoltage;
  t.family = "conformance";
  t.center = {0.0};
  t.scale = {10.0};
  t.weight = {3.0};
  const double rate = base->meta.sample_rate_hz;
  return std::make_unique<models::AugmentedModel>(std::move(base), std::vector<models::EffectTerm>{t}, 1.5, rate);
}

models::ModelPtr make(const std::string& kind) {
  training::FitRequest req;
  req.train = &data().train;
  req.validation = &data().val;
  req.axis = "c";
  req.seed = 5;
  if (kNeuralKinds.count(kind)) req.options = YAML::Load("{steps: 20, patience: 0}");
  if (kLoadOnlyKinds.count(kind)) return augmented(req);
  return training::fit_model(kind, req);
}

std::vector<double> stream(models::Model& m, const io::Dataset& d, models::PredictionMode mode, bool reset = true) {
  models::StreamOptions o;
  o.mode = mode;
  o.reset = reset;
  return models::stream_model(m, d, "c", o).prediction;
}

double max_rel_diff(const std::vector<double>& a, const std::vector<double>& b) {
  EXPECT_EQ(a.size(), b.size());
  double m = 0;
  for (std::size_t i = 0; i < std::min(a.size(), b.size()); ++i) m = std::max(m, std::abs(a[i] - b[i]) / (1 + std::abs(a[i])));
  return m;
}

void expect_round_trip(const models::Model& m) {
  const std::string text = model_file_text(m);
  const models::ModelPtr back = model_from_text(text);
  EXPECT_EQ(back->kind(), m.kind());
  EXPECT_EQ(model_file_text(*back), text) << "a second round trip changes the file";
  const std::string refused = load_error_after(text, "kind: " + m.kind(), "kind: " + m.kind() + "_unknown");
  EXPECT_NE(refused.find("unknown model kind"), std::string::npos) << refused;
  auto a = m.clone();
  for (auto mode : {models::PredictionMode::kFreeRun, models::PredictionMode::kOneStep})
    EXPECT_LT(max_rel_diff(stream(*a, data().rest, mode), stream(*back, data().rest, mode)), 1e-12)
        << models::prediction_mode_name(mode);
}

// Streamed over the first half, cloned, then both streamed on over the second half without a reset: the same.
void expect_clone_streams_equal(const models::Model& m) {
  const std::size_t half = data().rest.size() / 2;
  const io::Dataset first = data().rest.slice(0, half), second = data().rest.slice(half, data().rest.size());
  for (auto mode : {models::PredictionMode::kFreeRun, models::PredictionMode::kOneStep}) {
    auto a = m.clone();
    stream(*a, first, mode);
    auto b = a->clone();
    const std::vector<double> pa = stream(*a, second, mode, false), pb = stream(*b, second, mode, false);
    EXPECT_EQ(pa, pb) << models::prediction_mode_name(mode);
    for (double y : pa) ASSERT_TRUE(std::isfinite(y)) << models::prediction_mode_name(mode);
  }
}

// The exported C header, compiled and run on the streamed rows, against the C++ model in both modes.
void expect_c_export_matches(const models::Model& m) {
  const io::AxisSeries& ax = data().rest.axis("c");
  const std::vector<double> v(ax.voltage_v.begin(), ax.voltage_v.begin() + 2000),
      d(ax.position_nm.begin(), ax.position_nm.begin() + 2000);
  const auto rows = run_c(m, v, d);
  ASSERT_EQ(rows.size(), v.size());
  auto one = m.clone(), free = m.clone();
  one->reset(v[0], d[0]);
  free->reset(v[0], d[0]);
  double diff = 0;
  for (std::size_t i = 0; i < v.size(); ++i) {
    const models::ModelInput in{v[i], nullptr};
    const double a = one->predict(in), b = free->predict(in);
    diff = std::max({diff, std::abs(rows[i][0] - a) / (1 + std::abs(a)), std::abs(rows[i][1] - b) / (1 + std::abs(b))});
    one->commit(in, d[i]);
    free->commit(in, b);
  }
  EXPECT_LT(diff, 1e-9);
}

void expect_rate_contract(const models::Model& m) {
  auto c = m.clone();
  const double other_step_s = 1.0 / 8.93;
  if (m.runs_at_any_rate()) {
    EXPECT_NO_THROW(c->set_step_s(other_step_s));
  } else {
    EXPECT_FALSE(m.fixed_rate_reason().empty());
    EXPECT_NO_THROW(c->set_step_s(1.0 / m.meta.sample_rate_hz));
    EXPECT_THROW(c->set_step_s(other_step_s), std::invalid_argument);
  }
}

}  // namespace

TEST(ModelConformance, EveryRegisteredKindMeetsTheModelContract) {
  const std::vector<std::string> kinds = models::model_kind_names();
  ASSERT_GE(kinds.size(), 12u);
  for (const std::string& kind : kinds) {
    SCOPED_TRACE(kind);
    // The registry and the fitters agree: every kind has a fitter unless it is a load-only kind.
    EXPECT_EQ(static_cast<bool>(training::fitter(kind)), kLoadOnlyKinds.count(kind) == 0);
    const models::ModelPtr m = make(kind);
    ASSERT_TRUE(m);
    EXPECT_EQ(m->kind(), kind);
    EXPECT_GT(m->num_parameters(), 0u);
    EXPECT_NEAR(m->meta.sample_rate_hz, data().train.sample_rate_hz(), 1e-9);
    expect_round_trip(*m);
    expect_clone_streams_equal(*m);
    if (models::model_kind(kind).export_c99) expect_c_export_matches(*m);
    expect_rate_contract(*m);
    std::cerr << kind << ": " << m->num_parameters() << " parameters, "
              << (m->runs_at_any_rate() ? "any rate" : "fixed rate: " + m->fixed_rate_reason()) << "\n";
  }
  EXPECT_THROW(training::fitter("no_such_kind"), std::runtime_error);
}
