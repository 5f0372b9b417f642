// Several recordings as one data set: each its own history and zero. Joined and cut without losing a row; the one
// streaming path starts each from its own reset; a fit estimates each recording's zero jointly instead of learning it.
#include <gtest/gtest.h>

#include <cmath>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/training/fitters.h"

using namespace piezo;

namespace {

// A short walk on c from rest, its positions read against a counter zeroed at `zero_nm`.
io::Dataset walk(std::uint64_t seed, double zero_nm, double duration_s = 900) {
  auto cfg = sim::default_simulator_config();
  io::Dataset prog = protocols::make_protocol("random_walk", YAML::Load("{duration_s: " + std::to_string(duration_s) + "}"),
                                              cfg.sample_rate_hz, seed)->program();
  prog.axes = {prog.axis("c")};
  sim::ManipulatorSimulator s(cfg, seed);
  io::Dataset d = s.run(prog);
  for (double& y : d.axis("c").position_nm) y -= zero_nm;
  for (double& y : d.axis("c").true_position_nm) y -= zero_nm;
  d.source = "walk" + std::to_string(seed);
  return d;
}

}  // namespace

TEST(Recordings, JoinedAndCutWithoutLosingARow) {
  const io::Dataset a = walk(1, 0, 60), b = walk(2, 100, 30);
  std::vector<std::string> notes;
  const io::Dataset j = io::join_recordings({a, b}, &notes);
  ASSERT_EQ(j.recording_count(), 2u);
  EXPECT_EQ(j.size(), a.size() + b.size());
  EXPECT_NO_THROW(j.validate());
  EXPECT_TRUE(j.starts_recording(0));
  EXPECT_TRUE(j.starts_recording(a.size()));
  EXPECT_FALSE(j.starts_recording(a.size() + 1));
  EXPECT_NEAR(j.sample_period_s(), 1.0 / 11.0, 1e-9);  // the join steps one period between recordings
  const io::Dataset b2 = j.recording(1);
  EXPECT_EQ(b2.source, "walk2");
  ASSERT_EQ(b2.size(), b.size());
  EXPECT_DOUBLE_EQ(b2.time_s[0], b.time_s[0]);
  EXPECT_DOUBLE_EQ(b2.axis("c").position_nm.back(), b.axis("c").position_nm.back());
  const io::Dataset cut = j.slice(a.size() - 10, a.size() + 10);  // across the boundary: two recordings of 10 rows
  ASSERT_EQ(cut.recording_count(), 2u);
  EXPECT_EQ(cut.recording_rows(1).first, 10u);
  // an axis one file lacks is one error naming it
  io::Dataset other = b;
  other.axes[0].name = "a";
  try {
    io::join_recordings({a, other});
    FAIL();
  } catch (const io::DataError& e) {
    EXPECT_NE(std::string(e.what()).find("walk2: has no axis c"), std::string::npos) << e.what();
  }
  EXPECT_THROW(j.slice(0, 10).append(j), io::DataError);  // several recordings are never appended as one
}

TEST(Recordings, EachStreamsFromItsOwnReset) {
  const io::Dataset a = walk(3, 0, 120), b = walk(4, 0, 120);
  const io::Dataset j = io::join_recordings({a, b});
  const models::ModelPtr m = training::fit_model("linear", [&] {
    training::FitRequest r;
    r.train = &a;
    return r;
  }());
  auto x = m->clone(), y = m->clone();
  const auto joined = models::stream_model(*x, j, "c").prediction;
  const auto alone = models::stream_model(*y, b, "c").prediction;
  for (std::size_t i = 0; i < b.size(); ++i) ASSERT_NEAR(joined[a.size() + i], alone[i], 1e-9) << i;
}

TEST(Recordings, AFitEstimatesEachZeroInsteadOfLearningIt) {
  // Three recordings whose counters were zeroed 600 nm apart; a fourth, zeroed at 0, is the test.
  const std::vector<double> zeros = {0.0, 600.0, -600.0};
  std::vector<io::Dataset> parts;
  for (std::size_t k = 0; k < zeros.size(); ++k) parts.push_back(walk(10 + k, zeros[k]));
  const io::Dataset joined = io::join_recordings(parts);
  io::Dataset as_one = joined;
  as_one.recordings.clear();  // the same rows taken as one continuous recording
  const io::Dataset test = walk(20, 0);
  auto free_run_mae = [&](const models::Model& model) {
    auto m = model.clone();
    models::StreamOptions so;
    so.anchor_s = 60;  // the test recording's own zero from its first minute
    const models::StreamResult r = models::stream_model(*m, test, "c", so);
    const auto& truth = test.axis("c").true_position_nm;
    double s = 0;
    for (std::size_t i = r.first_scored; i < truth.size(); ++i) s += std::abs(r.prediction[i] - truth[i]);
    return s / static_cast<double>(truth.size() - r.first_scored);
  };
  training::FitRequest r;
  r.axis = "c";
  r.train = &joined;
  const models::ModelPtr separate = training::fit_model("pi_creep_lti", r);
  r.train = &as_one;
  const models::ModelPtr continuous = training::fit_model("pi_creep_lti", r);
  const double e_sep = free_run_mae(*separate), e_one = free_run_mae(*continuous);
  std::cout << "[recordings] free-run MAE vs truth on a fourth recording: separate zeros " << e_sep
            << " nm, taken as one recording " << e_one << " nm; offsets RMS "
            << separate->meta.validation.at("recording_offset_rms_nm") << " nm\n";
  EXPECT_NEAR(separate->meta.validation.at("recording_offset_rms_nm"), 600.0 * std::sqrt(2.0 / 3.0), 30.0);
  EXPECT_LT(e_sep, 0.2 * e_one);
}

TEST(Recordings, TheTrainingRowsAreKnownAgain) {
  const io::Dataset a = walk(30, 0, 300), b = walk(31, 0, 300);
  const io::Dataset train = a.slice(0, a.size() * 4 / 5), tail = a.slice(a.size() * 4 / 5, a.size());
  training::FitRequest r;
  r.train = &train;
  const models::ModelPtr m = training::fit_model("linear", r);
  ASSERT_EQ(m->meta.trained_on.size(), 1u);
  const std::string overlap = models::training_overlap(m->meta, a, "c", "m.yaml");
  std::cout << "[overlap] " << overlap << "\n";
  EXPECT_NE(overlap.find("walk30: rows 2-" + std::to_string(train.size() + 1)), std::string::npos) << overlap;
  EXPECT_NE(overlap.find("are rows m.yaml was trained on"), std::string::npos) << overlap;
  EXPECT_EQ(models::training_overlap(m->meta, tail, "c", "m.yaml"), "");  // the held-out part
  EXPECT_EQ(models::training_overlap(m->meta, b, "c", "m.yaml"), "");     // another recording, same times
  // among several recordings, and through the model file
  const io::Dataset joined = io::join_recordings({b, a});
  const std::string path = ::testing::TempDir() + "overlap_model.yaml";
  models::save_model(path, *m);
  const models::ModelPtr loaded = models::load_model(path);
  EXPECT_NE(models::training_overlap(loaded->meta, joined, "c", path).find("walk30: rows 2-"), std::string::npos);
}

TEST(Recordings, EachZeroAsThePredictionShowsIt) {
  const io::Dataset a = walk(40, 0, 30), b = walk(41, 0, 30);
  const io::Dataset j = io::join_recordings({a, b});
  std::vector<double> pred = j.axis("c").position_nm;
  for (std::size_t i = a.size(); i < pred.size(); ++i) pred[i] -= 250.0;  // the second recording's zero 250 nm up
  const auto d = models::recording_offsets(j, "c", pred);
  ASSERT_EQ(d.size(), 2u);
  EXPECT_NEAR(d[0], 0.0, 1e-9);
  EXPECT_NEAR(d[1], 250.0, 1e-9);
  EXPECT_EQ(models::recording_offsets(j, "c", pred, j.size())[1], 0.0);  // no row from `from` on: 0
  EXPECT_THROW(models::recording_offsets(j, "c", std::vector<double>(3)), std::invalid_argument);
}
