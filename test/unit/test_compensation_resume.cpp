// Resuming a model on its recorded history (compensation/resume.h; docs/predictor.md, "Resume"): the resumed state is
// the continued run's, across a hold the node was down for, and every refusal names its reason.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <string>

#include "piezo_compensation/compensation/axis_compensator.h"
#include "piezo_compensation/compensation/resume.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/sim/stage.h"

using namespace piezo;

namespace {

const std::string kSrc = PIEZO_SOURCE_DIR;

// The hold-trim stage (creep modes up to hours; the model fitted on another seed of it), 40 min at 11 Hz.
const io::Dataset& recording() {
  static const io::Dataset d = [] {
    const sim::StageConfig stage = sim::load_stage(kSrc + "/config/stages/mm3e_foreign_hold_stage.yaml");
    return sim::simulate_stage(stage, 404, 2400.0);
  }();
  return d;
}

models::ModelPtr model() { return models::load_model(kSrc + "/config/models/mm3e_foreign_c.yaml"); }

// The first row after `after_s` inside a hold that lasts at least `rows` more rows: [first, first + rows] one voltage.
std::size_t hold_row(const io::Dataset& d, double after_s, std::size_t rows) {
  const auto& v = d.axis("c").voltage_v;
  for (std::size_t i = 1; i + rows < d.size(); ++i) {
    if (d.time_s[i] < after_s || v[i] != v[i - 1]) continue;
    bool held = true;
    for (std::size_t k = 1; k <= rows && held; ++k) held = v[i + k] == v[i];
    if (held) return i;
  }
  return d.size();
}

}  // namespace

// Cut in a hold: the history up to row i (exclusive), now at row j > i in the same hold (the node down for j − i
// samples). The resumed model, fed rows j… by the compensator, predicts what the model that ran through everything
// predicts there, exactly: the same stream, the missed samples held.
TEST(Resume, TheResumedStateIsTheContinuedRun) {
  const io::Dataset& d = recording();
  const std::size_t i = hold_row(d, 1200.0, 60);
  ASSERT_LT(i, d.size());
  const std::size_t j = i + 40;
  const io::Dataset history = d.slice(0, i), after = d.slice(j, d.size());
  const models::ModelPtr m = model();
  const std::vector<double> whole = models::stream_model(*m->clone(), d, "c").prediction;

  const compensation::Resume r =
      compensation::resume_model(*m, history, "c", d.time_s[j], d.axis("c").voltage_v[j]);
  ASSERT_TRUE(r.resumed) << r.status;
  ASSERT_TRUE(r.model);
  EXPECT_NEAR(r.gap_s, d.time_s[j] - d.time_s[i - 1], 1e-9);
  EXPECT_EQ(r.history_rows, i);
  EXPECT_NE(r.status.find("resumed on"), std::string::npos) << r.status;
  EXPECT_NEAR(r.predicted_nm, whole[j - 1], 1e-6);

  const compensation::IdealLine line = compensation::ideal_line_from_model(*m, {});
  compensation::AxisCompensatorConfig cfg;
  cfg.start_estimate_s = 30.0;  // not made: the history is known
  compensation::AxisCompensator resumed(m->clone(), line, cfg);
  resumed.start_resumed(r.model->clone(), r.last_voltage_v, r.predicted_nm, r.status);
  compensation::AxisCompensator cold(m->clone(), line, cfg);
  double worst = 0, cold_mae = 0, resumed_mae = 0;
  const auto& ax = after.axis("c");
  for (std::size_t k = 0; k < after.size(); ++k) {
    const double p = resumed.on_sample(ax.voltage_v[k], ax.position_nm[k], true).predicted_nm;
    const double c = cold.on_sample(ax.voltage_v[k], ax.position_nm[k], true).predicted_nm;
    worst = std::max(worst, std::abs(p - whole[j + k]));
    resumed_mae += std::abs(p - ax.true_position_nm[k]) / static_cast<double>(after.size());
    cold_mae += std::abs(c - ax.true_position_nm[k]) / static_cast<double>(after.size());
  }
  std::cout << "after the restart, MAE against the truth: resumed " << resumed_mae << " nm, from rest " << cold_mae
            << " nm\n";
  EXPECT_LT(worst, 1e-6);
  EXPECT_TRUE(resumed.resumed());
  EXPECT_EQ(resumed.start_estimate(), nullptr);
  EXPECT_NE(resumed.start_estimate_status().find("no start estimate: resumed on"), std::string::npos);
  EXPECT_LT(resumed_mae, 0.5 * cold_mae);
  EXPECT_THROW(resumed.start_resumed(r.model->clone(), 0.0, 0.0, "again"), std::logic_error);
}

// The estimator resumes too: its state after the history's readings, held at rest for the gap. After the restart
// the fused position is as good as before it at once, where a cold start spends its first minute pinning the error.
TEST(Resume, TheEstimatorKeepsItsState) {
  const io::Dataset& d = recording();
  const std::size_t i = hold_row(d, 1200.0, 700);
  ASSERT_LT(i, d.size());
  const std::size_t j = i + 40;
  const io::Dataset history = d.slice(0, i), after = d.slice(j, d.size());
  const models::ModelPtr m = model();
  const compensation::Resume r = compensation::resume_model(*m, history, "c", d.time_s[j], d.axis("c").voltage_v[j]);
  ASSERT_TRUE(r.resumed) << r.status;
  ASSERT_TRUE(r.filter.has_value()) << r.status;
  EXPECT_NE(r.status.find("estimator resumed at 1σ"), std::string::npos) << r.status;
  const compensation::IdealLine line = compensation::ideal_line_from_model(*m, {});
  compensation::AxisCompensator resumed(m->clone(), line, {}), cold(m->clone(), line, {});
  resumed.start_resumed(r.model->clone(), r.last_voltage_v, r.predicted_nm, r.status, &*r.filter);
  const auto& ax = after.axis("c");
  double resumed_mae = 0, cold_mae = 0, first_sigma_resumed = 0, first_sigma_cold = 0;
  const std::size_t minute = 660;
  for (std::size_t k = 0; k < minute; ++k) {
    const auto a = resumed.on_sample(ax.voltage_v[k], ax.position_nm[k], true);
    const auto b = cold.on_sample(ax.voltage_v[k], ax.position_nm[k], true);
    if (k == 0) first_sigma_resumed = a.fused_sigma_nm, first_sigma_cold = b.fused_sigma_nm;
    resumed_mae += std::abs(a.fused_nm - ax.true_position_nm[k]) / minute;
    cold_mae += std::abs(b.fused_nm - ax.true_position_nm[k]) / minute;
  }
  std::cout << "first minute after the restart, fused MAE: resumed " << resumed_mae << " nm (1σ " << first_sigma_resumed
            << " nm at once), cold " << cold_mae << " nm (1σ " << first_sigma_cold << " nm)\n";
  EXPECT_LT(first_sigma_resumed, 0.25 * first_sigma_cold);  // one reading alone gives the reading σ
  EXPECT_LT(resumed_mae, 0.5 * cold_mae);
  EXPECT_TRUE(resumed.estimator()->zero_known());
}

// Every refusal leaves no model and says why in one line.
TEST(Resume, RefusesWhatIsNotTheRunBefore) {
  const io::Dataset& d = recording();
  const std::size_t i = hold_row(d, 1200.0, 60);
  ASSERT_LT(i, d.size());
  const io::Dataset history = d.slice(0, i);
  const double end = d.time_s[i - 1], v = d.axis("c").voltage_v[i - 1];
  const models::ModelPtr m = model();
  auto why = [&](const io::Dataset& h, double now_s, double now_v, const std::string& axis = "c",
                 compensation::ResumeOptions o = {}) {
    const compensation::Resume r = compensation::resume_model(*m, h, axis, now_s, now_v, o);
    EXPECT_FALSE(r.resumed);
    EXPECT_FALSE(r.model);
    EXPECT_EQ(r.status.rfind("not resumed: ", 0), 0u) << r.status;
    return r.status;
  };
  EXPECT_NE(why(history, end + 10.0, v + 1.0).find("the stage moved"), std::string::npos);
  EXPECT_NE(why(history, end - 10.0, v).find("before the end"), std::string::npos);
  compensation::ResumeOptions short_gap;
  short_gap.max_gap_s = 60.0;
  EXPECT_NE(why(history, end + 120.0, v, "c", short_gap).find("more than 60 s"), std::string::npos);
  io::Dataset only_c = history;
  only_c.axes.erase(std::remove_if(only_c.axes.begin(), only_c.axes.end(), [](const auto& a) { return a.name != "c"; }),
                    only_c.axes.end());
  EXPECT_NE(why(only_c, end + 1.0, v, "a").find("no axis a"), std::string::npos);
  EXPECT_NE(why(history.slice(0, 1), end + 1.0, v).find("fewer than 2 rows"), std::string::npos);
  EXPECT_NE(why(history, NAN, v).find("not finite"), std::string::npos);
  io::Dataset broken = history;
  broken.axis("c").voltage_v[i / 2] = NAN;
  EXPECT_NE(why(broken, end + 1.0, v).find("non-finite voltage of c at row"), std::string::npos);
  EXPECT_NE(why(history, end + 0.01, v).find("within half a sample period"), std::string::npos);
  // Within the tolerance it resumes; a long gap is held in chunks (here 3 h at 11 Hz: 118 800 rows).
  const compensation::Resume ok = compensation::resume_model(*m, history, "c", end + 10800.0, v + 0.01);
  EXPECT_TRUE(ok.resumed) << ok.status;
  EXPECT_TRUE(std::isfinite(ok.predicted_nm));
}
