// What a model file must be for the compensator (compensation/model_check.h), what a model file and a data file
// record about simulated data (ModelMeta::fitted_on, io::Dataset::origin), and the rule for a simulated model on a
// real transport.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <functional>
#include <string>

#include "piezo_compensation/compensation/model_check.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fitters.h"

using namespace piezo;

namespace {

std::string tmp(const std::string& name) { return ::testing::TempDir() + "piezo_model_check_" + name; }

models::ModelPtr small_pi(const std::string& axis) {
  auto m = std::make_unique<models::PiCreepModel>(std::vector<double>{0, 10, 20}, std::vector<double>{5, 1, 0.5}, 2.0,
                                                  models::CreepParams{}, 11.0);
  m->meta.axis = axis;
  return m;
}

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "no error";
}

io::Dataset ramp(std::size_t n, bool truth) {
  io::Dataset d;
  for (std::size_t i = 0; i < n; ++i) d.time_s.push_back(static_cast<double>(i) / 11.0);
  auto& c = d.add_axis("c");
  for (std::size_t i = 0; i < n; ++i) {
    c.voltage_v[i] = 10.0 * std::sin(0.01 * static_cast<double>(i));
    c.position_nm[i] = 12.5 * c.voltage_v[i];
  }
  if (truth) c.true_position_nm = c.position_nm;
  return d;
}

}  // namespace

TEST(ModelCheck, LoadsADrivableModelAndNamesTheFileOtherwise) {
  const std::string path = tmp("c.yaml");
  models::save_model(path, *small_pi("c"));
  EXPECT_NE(compensation::load_compensator_model(path, "c"), nullptr);
  EXPECT_EQ(error_of([] { compensation::load_compensator_model(""); }), "no model file given");
  EXPECT_EQ(error_of([&] { compensation::load_compensator_model(path + ".none"); }), path + ".none: cannot open model file");
  const std::string other = error_of([&] { compensation::load_compensator_model(path, "a"); });
  EXPECT_NE(other.find(path), std::string::npos) << other;
  EXPECT_NE(other.find("axis c"), std::string::npos) << other;
  const std::string broken = tmp("broken.yaml");
  std::ofstream(broken) << "format_version: 1\nkind: nosuch\n";
  const std::string e = error_of([&] { compensation::load_compensator_model(broken); });
  EXPECT_EQ(e.rfind(broken, 0), 0u) << e;
}

TEST(ModelCheck, UnavailableModelPredictsNothing) {
  compensation::UnavailableModel m;
  EXPECT_TRUE(std::isnan(m.predict({1.0, nullptr})));
  EXPECT_EQ(m.clone()->kind(), "unavailable");
}

TEST(ModelCheck, ASimulatedModelIsRefusedOnARealTransportUnlessAllowed) {
  models::ModelMeta sim, rec, unknown;
  sim.fitted_on = models::kFittedOnSimulated;
  rec.fitted_on = models::kFittedOnRecorded;
  const std::string p = "m.yaml", param = "/mm1/predictor/allow_simulated_model";
  const compensation::TransportCheck refused = compensation::check_model_transport(sim, true, false, p, param);
  EXPECT_NE(refused.error.find(p), std::string::npos) << refused.error;
  EXPECT_NE(refused.error.find(param), std::string::npos) << refused.error;
  const compensation::TransportCheck allowed = compensation::check_model_transport(sim, true, true, p, param);
  EXPECT_TRUE(allowed.error.empty());
  EXPECT_NE(allowed.warning.find(param), std::string::npos) << allowed.warning;
  for (const auto* meta : {&sim, &rec, &unknown}) {
    const auto on_sim = compensation::check_model_transport(*meta, false, false, p, param);
    EXPECT_TRUE(on_sim.error.empty() && on_sim.warning.empty()) << "a simulated transport runs every model";
  }
  const auto recorded = compensation::check_model_transport(rec, true, false, p, param);
  EXPECT_TRUE(recorded.error.empty() && recorded.warning.empty());
  const auto old = compensation::check_model_transport(unknown, true, false, p, param);
  EXPECT_TRUE(old.error.empty()) << "a file without the field runs as recorded";
  EXPECT_NE(old.warning.find("training.fitted_on"), std::string::npos) << old.warning;
}

TEST(ModelCheck, FittedOnRoundTripsAndAnOldFileSaysNothing) {
  for (const std::string on : {models::kFittedOnSimulated, models::kFittedOnRecorded, ""}) {
    auto m = small_pi("c");
    m->meta.fitted_on = on;
    const std::string path = tmp("fitted_on.yaml");
    models::save_model(path, *m);
    EXPECT_EQ(models::load_model(path)->meta.fitted_on, on);
    EXPECT_EQ(models::model_to_file_yaml(*m)["training"]["fitted_on"].IsDefined(), !on.empty());
  }
  YAML::Node root = models::model_to_file_yaml(*small_pi("c"));
  root["training"]["fitted_on"] = "guessed";
  const std::string e = error_of([&] { models::model_from_file_yaml(root, "bad.yaml"); });
  EXPECT_NE(e.find("training.fitted_on"), std::string::npos) << e;
}

TEST(DataOrigin, TheDataSaysElseTheTruthIsTheSign) {
  io::Dataset d = ramp(50, false);
  EXPECT_FALSE(io::is_simulated(d));
  d.origin = io::kOriginSimulated;
  EXPECT_TRUE(io::is_simulated(d));
  EXPECT_TRUE(io::is_simulated(d.slice(10, 20)));
  io::Dataset t = ramp(50, true);
  EXPECT_TRUE(io::is_simulated(t)) << "the simulator's truth column is the fallback sign";
  t.origin = io::kOriginRecorded;
  EXPECT_FALSE(io::is_simulated(t)) << "the data's own word goes before the sign";
  // joined: simulated when a part is, recorded when every part says so
  io::Dataset r1 = ramp(50, false), r2 = ramp(50, false);
  r1.origin = r2.origin = io::kOriginRecorded;
  EXPECT_EQ(io::join_recordings({r1, r2}).origin, io::kOriginRecorded);
  EXPECT_TRUE(io::is_simulated(io::join_recordings({r1, ramp(50, true)})));
}

TEST(DataOrigin, CsvRoundTripsTheOriginLine) {
  const std::string path = tmp("origin.csv");
  io::Dataset d = ramp(20, false);
  d.origin = io::kOriginSimulated;
  io::write_csv(path, d);
  std::ifstream in(path);
  std::string first;
  std::getline(in, first);
  EXPECT_EQ(first, "# origin: simulated");
  EXPECT_EQ(io::read_csv(path).origin, io::kOriginSimulated);
  d.origin.clear();
  io::write_csv(path, d);
  EXPECT_EQ(io::read_csv(path).origin, "");
  std::ofstream(path) << "# made by hand\ntime_s,c_voltage_v,c_position_nm\n0,0,0\n0.1,1,1\n";
  const std::string e = error_of([&] { io::read_csv(path); });
  EXPECT_NE(e.find("row 1"), std::string::npos) << e;
}

TEST(DataOrigin, AFitRecordsWhatItWasFittedOn) {
  for (const bool simulated : {true, false}) {
    io::Dataset d = ramp(400, false);
    d.origin = simulated ? io::kOriginSimulated : io::kOriginRecorded;
    training::FitRequest r;
    r.train = &d;
    r.axis = "c";
    const models::ModelPtr m = training::fit_model("pi", r);
    ASSERT_NE(m, nullptr);
    EXPECT_EQ(m->meta.fitted_on, simulated ? models::kFittedOnSimulated : models::kFittedOnRecorded);
  }
}
