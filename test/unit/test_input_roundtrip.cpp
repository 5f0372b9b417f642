// One input resolver for every tool: a residual model reading any input kind it can be given — the data's
// time, an aux column, another axis' voltage, another axis' position — is saved, loaded and scored through the path
// `piezo eval` takes (CSV read and validated, model file loaded, check_model_for_eval, evaluate_model) on the same
// three-axis CSV, and its predictions there are the base's plus the term on the input as the resolver defines it
// (another axis' position: the reading of the previous row).
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"

using namespace piezo;

namespace {

constexpr double kRateHz = 11.0;
constexpr double kWeight = 0.5;  // nm per unit of the input

std::string tmp(const std::string& name) {
  return ::testing::TempDir() + "piezo_input_roundtrip_" + std::to_string(::getpid()) + "_" + name;
}

// Three axes (a, b, c) with a temperature column, as `piezo simulate` writes them.
io::Dataset three_axis_data() {
  io::Dataset d;
  const std::size_t n = 400;
  for (std::size_t i = 0; i < n; ++i) d.time_s.push_back(100.0 + i / kRateHz);
  for (const char* name : {"a", "b", "c"}) {
    io::AxisSeries& ax = d.add_axis(name);  // sized to the time column
    ax.true_position_nm.resize(n);
    const double phase = name[0] - 'a';
    for (std::size_t i = 0; i < n; ++i) {
      const double v = 40.0 * std::sin(0.013 * i + phase) + 7.0 * std::sin(0.11 * i);
      ax.voltage_v[i] = v;
      ax.position_nm[i] = 12.0 * v + 3.0 * std::cos(0.05 * i + phase);
      ax.true_position_nm[i] = 12.0 * v;
    }
  }
  io::AuxSignal temp{"temperature_c", {}};
  for (std::size_t i = 0; i < n; ++i) temp.values.push_back(22.0 + 0.4 * std::sin(0.004 * i));
  d.aux.push_back(temp);
  d.validate();
  return d;
}

models::ModelPtr augmented_on(const std::string& signal) {
  auto base = std::make_unique<models::PiCreepModel>(std::vector<double>{0, 10, 20}, std::vector<double>{9, 2, 1},
                                                     4.0, models::CreepParams{}, kRateHz);
  base->meta.axis = "c";
  base->meta.sample_rate_hz = kRateHz;
  models::EffectTerm t;
  t.type = "linear";
  t.signal = signal;
  t.family = "roundtrip";
  t.center = {0.0};
  t.scale = {1.0};
  t.weight = {kWeight};
  auto m = std::make_unique<models::AugmentedModel>(std::move(base), std::vector<models::EffectTerm>{t}, 1.5, kRateHz);
  m->meta.axis = "c";
  m->meta.sample_rate_hz = kRateHz;
  return m;
}

struct InputCase {
  const char* signal;
  models::InputSource::Kind kind;
};

}  // namespace

TEST(InputRoundTrip, EveryInputKindOfAResidualModelIsScoredByEvalOnTheSameCsv) {
  const std::string csv = tmp("three_axis.csv");
  io::write_csv(csv, three_axis_data());
  // `piezo eval` reads a CSV with io::read_csv and validates it (ros_io::read_data).
  io::Dataset test = io::read_csv(csv);
  test.validate();
  ASSERT_EQ(test.axes.size(), 3u);
  const std::vector<double> base_pred = [&] {
    auto m = augmented_on("time_s");
    const auto& base = dynamic_cast<const models::AugmentedModel&>(*m).base();
    auto b = base.clone();
    return models::stream_model(*b, test, "c").prediction;
  }();

  const InputCase cases[] = {
      {"time_s", models::InputSource::Kind::kTime},
      {"temperature_c", models::InputSource::Kind::kAux},
      {"a_voltage_v", models::InputSource::Kind::kAxisVoltage},
      {"a_position_nm", models::InputSource::Kind::kAxisPosition},
  };
  for (const auto& ic : cases) {
    SCOPED_TRACE(ic.signal);
    const std::string path = tmp(std::string(ic.signal) + ".yaml");
    models::save_model(path, *augmented_on(ic.signal));
    const models::ModelPtr m = models::load_model(path);
    ASSERT_EQ(m->kind(), "augmented");
    ASSERT_EQ(m->aux_inputs(), std::vector<std::string>{ic.signal});
    // The resolver's reading of the name, the one every tool uses.
    models::InputResolver resolver(test, m->aux_inputs(), "c");
    ASSERT_EQ(resolver.sources().at(0).kind, ic.kind);
    ASSERT_NO_THROW(analysis::check_model_for_eval(*m, path, "c", test, nullptr));
    analysis::EvalOptions eo;
    eo.axis = "c";
    const analysis::ModelEvaluation ev = analysis::evaluate_model(*m, "roundtrip", test, nullptr, eo);
    ASSERT_EQ(ev.test.one_step.size(), test.size());
    // The same column as the resolver reads it, by hand.
    const std::vector<double>& col = ic.kind == models::InputSource::Kind::kTime          ? test.time_s
                                     : ic.kind == models::InputSource::Kind::kAux         ? test.find_aux(ic.signal)->values
                                     : ic.kind == models::InputSource::Kind::kAxisVoltage ? test.axis("a").voltage_v
                                                                                          : test.axis("a").position_nm;
    const bool lagged = ic.kind == models::InputSource::Kind::kAxisPosition;
    double worst = 0;
    for (std::size_t i = 0; i < test.size(); ++i) {
      const double input = col[lagged && i > 0 ? i - 1 : i];
      const double expect = base_pred[i] + 1.5 + kWeight * input;
      worst = std::max({worst, std::abs(ev.test.one_step[i] - expect), std::abs(ev.test.free_run[i] - expect)});
    }
    EXPECT_LT(worst, 1e-9 * (1 + std::abs(base_pred.back())));
    EXPECT_TRUE(ev.hysteresis.free_run.vs_measured.valid());
    EXPECT_TRUE(ev.hysteresis.free_run.vs_truth.valid());
    std::remove(path.c_str());
  }

  // What can never be an input is refused by eval with the column named: the own axis' position, a true position.
  for (const char* forbidden : {"c_position_nm", "a_true_position_nm"}) {
    SCOPED_TRACE(forbidden);
    const auto m = augmented_on(forbidden);
    try {
      analysis::check_model_for_eval(*m, "m.yaml", "c", test, nullptr);
      ADD_FAILURE() << "accepted";
    } catch (const models::ModelFileError& e) {
      EXPECT_NE(std::string(e.what()).find(forbidden), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("m.yaml"), std::string::npos) << e.what();
    }
  }
  // A column the data does not have is named too.
  try {
    analysis::check_model_for_eval(*augmented_on("humidity_pct"), "m.yaml", "c", test, nullptr);
    ADD_FAILURE() << "accepted a missing column";
  } catch (const models::ModelFileError& e) {
    EXPECT_NE(std::string(e.what()).find("humidity_pct"), std::string::npos) << e.what();
  }
  std::remove(csv.c_str());
}
