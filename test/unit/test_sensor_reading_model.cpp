// A sensor effect goes into the estimator's reading model, not into the feedforward. The stage of the hold-trim tests (config/stages/mm3e_foreign_hold_stage.yaml, its shipped model
// config/models/mm3e_foreign_c.yaml) with an encoder interpolation error periodic in the position (25 nm at 350 nm):
// the residual loop's term for it, sin/cos of the position fitted to the readings on one recording, is put in the
// model three ways and the compensator runs a recording of another seed. As a sensor term (acts_on: readings) the
// fused estimate comes nearer the truth than without it, and the feedforward voltages are the model's without it;
// as a stage term the feedforward chases the encoder's error.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>
#include <cstdio>
#include <string>

#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/sim/stage.h"

namespace {

using namespace piezo;

constexpr double kPeriodNm = 350.0;

io::Dataset recording(std::uint64_t seed) {
  sim::StageConfig st = sim::load_stage(std::string(PIEZO_SOURCE_DIR) + "/config/stages/mm3e_foreign_hold_stage.yaml");
  sim::enable_effect(st.simulator, "encoder_periodic");
  st.simulator.encoder_periodic.amplitude_nm = 25.0;
  st.simulator.encoder_periodic.period_nm = kPeriodNm;
  st.simulator.encoder_periodic.phase_rad = 0.7;
  return sim::simulate_stage(st, seed, 1.5 * 3600.0);
}

// The loop's term for the error: sin/cos of the (corrected) position, fitted to readings − prediction.
models::EffectTerm periodic_term(const models::Model& base, const io::Dataset& d) {
  models::ModelPtr m = base.clone();
  const std::vector<double> p = models::stream_model(*m, d, "c").prediction;
  const auto& y = d.axis("c").position_nm;
  Eigen::MatrixXd X(static_cast<Eigen::Index>(p.size()), 3);
  Eigen::VectorXd r(static_cast<Eigen::Index>(p.size()));
  for (std::size_t i = 0; i < p.size(); ++i) {
    const double ph = 2.0 * M_PI * p[i] / kPeriodNm;
    X.row(static_cast<Eigen::Index>(i)) << std::sin(ph), std::cos(ph), 1.0;
    r[static_cast<Eigen::Index>(i)] = y[i] - p[i];
  }
  const Eigen::VectorXd w = X.colPivHouseholderQr().solve(r);
  models::EffectTerm t;
  t.family = "position_periodic";
  t.type = "sincos";
  t.signal = models::kSignalPosition;
  t.period = kPeriodNm;
  t.center = {0.0, 0.0};
  t.scale = {1.0, 1.0};
  t.weight = {w[0], w[1]};
  t.acts_on = models::kActsOnReadings;
  return t;
}

struct Replay {
  double fused_mae_nm = 0.0;
  std::vector<double> send_v;  // the feedforward voltage for the next sample's intent, once a second
};

Replay run(models::ModelPtr m, const compensation::IdealLine& line, const io::Dataset& d) {
  compensation::AxisCompensatorConfig cfg;
  cfg.hold_trim.enabled = false;  // the trim acts on the fused estimate: the feedforward alone is compared here
  compensation::AxisCompensator comp(std::move(m), line, cfg);
  const auto& ax = d.axis("c");
  Replay r;
  double n = 0;
  for (std::size_t i = 0; i + 1 < d.size(); ++i) {
    const compensation::SampleUpdate u = comp.on_sample(ax.voltage_v[i], ax.position_nm[i], true);
    if (d.time_s[i] - d.time_s[0] >= 300.0) r.fused_mae_nm += std::fabs(u.fused_nm - ax.true_position_nm[i]), n += 1;
    if (i % 11 == 0) {
      comp.set_intended_voltage(ax.voltage_v[i + 1]);
      r.send_v.push_back(comp.command(true).send_v);
    }
  }
  r.fused_mae_nm /= n;
  return r;
}

models::ModelPtr with_term(const models::Model& base, models::EffectTerm t, const char* acts_on) {
  t.acts_on = acts_on;
  auto m = std::make_unique<models::AugmentedModel>(base.clone(), std::vector<models::EffectTerm>{t}, 0.0, 11.0);
  m->meta.estimator = base.meta.estimator;
  return m;
}

TEST(SensorReadingModel, PeriodicEncoderErrorGoesToTheReadingModelNotTheFeedforward) {
  models::ModelPtr base = models::load_model(std::string(PIEZO_SOURCE_DIR) + "/config/models/mm3e_foreign_c.yaml");
  const io::Dataset fit = recording(811), test = recording(812);
  base->meta.estimator = analysis::identify_estimator(*base, fit, "c").to_yaml();
  const models::EffectTerm term = periodic_term(*base, fit);
  const double amplitude = std::hypot(term.weight[0], term.weight[1]);
  EXPECT_NEAR(amplitude, 25.0, 5.0) << "the fitted term is not the planted error";

  compensation::IdealLineOptions lo;
  const compensation::IdealLine line = compensation::ideal_line_from_model(*base, lo);
  const Replay plain = run(base->clone(), line, test);
  const Replay sensor = run(with_term(*base, term, models::kActsOnReadings), line, test);
  const Replay stage = run(with_term(*base, term, models::kActsOnPosition), line, test);
  double ff_sensor = 0.0, ff_stage = 0.0;
  for (std::size_t k = 0; k < plain.send_v.size(); ++k) {
    ff_sensor = std::max(ff_sensor, std::fabs(sensor.send_v[k] - plain.send_v[k]));
    ff_stage = std::max(ff_stage, std::fabs(stage.send_v[k] - plain.send_v[k]));
  }
  std::printf("fused MAE vs truth: without the term %.2f nm, as a sensor term %.2f nm, as a stage term %.2f nm; "
              "feedforward change: sensor term %.3g V, stage term %.3g V (term amplitude %.1f nm)\n",
              plain.fused_mae_nm, sensor.fused_mae_nm, stage.fused_mae_nm, ff_sensor, ff_stage, amplitude);
  EXPECT_LT(sensor.fused_mae_nm, 0.9 * plain.fused_mae_nm);
  EXPECT_LT(sensor.fused_mae_nm, stage.fused_mae_nm);
  EXPECT_LT(ff_sensor, 1e-9);  // the feedforward is the stage model's: the sensor term is not in it
  EXPECT_GT(ff_stage, 0.05);   // a stage term would move the tip to chase the encoder's error
}

}  // namespace
