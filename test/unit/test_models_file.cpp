#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/registry.h"
#include "test_models_data.h"

using namespace piezo;
using namespace piezo::models;

namespace {
std::string tmp(const std::string& name) { return ::testing::TempDir() + "piezo_model_" + name; }

void write(const std::string& path, const std::string& text) { std::ofstream(path) << text; }

std::string load_error(const std::string& path) {
  try {
    load_model(path);
  } catch (const ModelFileError& e) {
    return e.what();
  }
  return "no error";
}

std::vector<ModelPtr> one_of_each_kind() {
  std::vector<ModelPtr> out;
  features::FeatureSpec spec = features::candidate_features();
  spec.mean.assign(spec.size(), 0.5);
  spec.scale.assign(spec.size(), 2.0);
  out.push_back(std::make_unique<LinearModel>(spec, 11.0, Eigen::VectorXd::LinSpaced(spec.size(), -1, 1), 3.0, "lasso"));
  CreepParams none, log, lti, frac;
  log.kind = CreepKind::kLog, log.gamma_nm_per_v = 0.3, log.t1_s = 2;
  lti.kind = CreepKind::kLti, lti.taus_s = {10, 100}, lti.gains_nm_per_v = {0.5, 0.25};
  frac.kind = CreepKind::kFractional, frac.alpha = 0.35, frac.b_nm_per_v = 0.2;
  frac.on_hysteresis = true;
  for (const auto& cp : {none, log, lti, frac})
    out.push_back(std::make_unique<PiCreepModel>(std::vector<double>{0, 10, 20}, std::vector<double>{5, 1, 0.5}, 2.0, cp, 11.0));
  for (auto& m : out) {
    m->meta.axis = "c";
    m->meta.training_fingerprint = "fnv1a64:0123456789abcdef:100";
    m->meta.training_source = "train.csv";
    m->meta.validation["one_step_mae_nm"] = 17.25;
    m->meta.created_utc = "2026-11-21T06:00:00Z";
    m->meta.train_voltage_min_v = -12.5;
    m->meta.train_voltage_max_v = 80.0;
  }
  return out;
}
}  // namespace

TEST(ModelFile, RoundTripEveryKindPredictsIdentically) {
  const auto v = testdata::random_walk_v(2000, 8);
  for (auto& m : one_of_each_kind()) {
    const std::string path = tmp(m->kind() + ".yaml");
    save_model(path, *m);
    ModelPtr back = load_model(path);
    ASSERT_EQ(back->kind(), m->kind());
    EXPECT_EQ(back->meta.training_fingerprint, m->meta.training_fingerprint);
    EXPECT_EQ(back->meta.training_source, "train.csv");
    EXPECT_EQ(back->meta.created_utc, m->meta.created_utc);
    EXPECT_DOUBLE_EQ(back->meta.validation.at("one_step_mae_nm"), 17.25);
    EXPECT_DOUBLE_EQ(back->meta.train_voltage_min_v, -12.5);
    EXPECT_DOUBLE_EQ(back->meta.train_voltage_max_v, 80.0);
    EXPECT_EQ(back->num_parameters(), m->num_parameters());
    m->reset(v[0], 1.0);
    back->reset(v[0], 1.0);
    for (std::size_t i = 0; i < v.size(); ++i) {
      const ModelInput in{v[i], nullptr};
      const double a = m->predict(in), b = back->predict(in);
      ASSERT_EQ(a, b) << m->kind() << " sample " << i;
      m->commit(in, a + 1.0);
      back->commit(in, b + 1.0);
    }
  }
}

// The start estimate's learned prior of the linear (creep) states is kept per state; a list that does not fit the
// model or holds a bad number is refused by name.
TEST(ModelFile, StatePriorRoundTripsAndIsChecked) {
  auto models = one_of_each_kind();
  Model& lti = *models[3];  // pi_creep_lti with two creep modes
  ASSERT_EQ(lti.linear_state_count(), 2u);
  lti.meta.state_prior = {{1.5, 0.25, 3.0}, {-4.0, 0.5, 0.0}};
  const std::string path = tmp("state_prior.yaml");
  save_model(path, lti);
  const ModelPtr back = load_model(path);
  ASSERT_EQ(back->meta.state_prior.size(), 2u);
  for (std::size_t k = 0; k < 2; ++k) {
    EXPECT_DOUBLE_EQ(back->meta.state_prior[k].intercept_nm, lti.meta.state_prior[k].intercept_nm);
    EXPECT_DOUBLE_EQ(back->meta.state_prior[k].slope_nm_per_v, lti.meta.state_prior[k].slope_nm_per_v);
    EXPECT_DOUBLE_EQ(back->meta.state_prior[k].sigma_nm, lti.meta.state_prior[k].sigma_nm);
  }
  const YAML::Node root = YAML::LoadFile(path);
  const std::vector<std::pair<std::string, std::function<void(YAML::Node&)>>> cases = {
      {"training.state_prior: 1 entries for a model with 2 linear (creep) states",
       [](YAML::Node& n) {
         YAML::Node one;
         one.push_back(YAML::Clone(n["training"]["state_prior"][0]));
         n["training"]["state_prior"] = one;
       }},
      {"training.state_prior[1].sigma_nm: expected a finite number >= 0",
       [](YAML::Node& n) { n["training"]["state_prior"][1]["sigma_nm"] = -1.0; }},
      {"training.state_prior[0].slope_nm_per_v: expected a finite number",
       [](YAML::Node& n) { n["training"]["state_prior"][0]["slope_nm_per_v"] = "steep"; }},
      {"training.state_prior: expected a list", [](YAML::Node& n) { n["training"]["state_prior"] = 3.0; }},
  };
  for (const auto& [expect, edit] : cases) {
    YAML::Node n = YAML::Clone(root);
    edit(n);
    write(path, YAML::Dump(n));
    const std::string err = load_error(path);
    EXPECT_EQ(err.rfind(path + ": ", 0), 0u) << err;
    EXPECT_NE(err.find(expect), std::string::npos) << err;
  }
}

TEST(ModelFile, MalformedFilesGiveOneClearErrorNamingFileAndKey) {
  auto models = one_of_each_kind();
  const std::string good = tmp("good.yaml");
  save_model(good, *models[0]);
  const YAML::Node root = YAML::LoadFile(good);
  auto variant = [&](const std::string& name, const std::function<void(YAML::Node&)>& edit) {
    YAML::Node n = YAML::Clone(root);
    edit(n);
    const std::string p = tmp(name + ".yaml");
    write(p, YAML::Dump(n));
    return std::make_pair(p, load_error(p));
  };
  struct Case {
    std::string name, expect;
    std::function<void(YAML::Node&)> edit;
  };
  const std::vector<Case> cases = {
      {"no_kind", "kind: missing key", [](YAML::Node& n) { n.remove("kind"); }},
      {"unknown_kind", "unknown model kind 'banana'", [](YAML::Node& n) { n["kind"] = "banana"; }},
      {"newer", "format_version: 99 is newer", [](YAML::Node& n) { n["format_version"] = 99; }},
      {"rate_type", "sample_rate_hz: expected a number", [](YAML::Node& n) { n["sample_rate_hz"] = "fast"; }},
      {"axis", "axis: expected one of a, b, c", [](YAML::Node& n) { n["axis"] = "z"; }},
      {"weights_size", "model.weights: expected", [](YAML::Node& n) { n["model"]["weights"] = std::vector<double>{1, 2}; }},
      {"weights_type", "model.weights[0]: expected a finite number",
       [](YAML::Node& n) { n["model"]["weights"][0] = "x"; }},
      {"no_bias", "model.bias_nm: missing key", [](YAML::Node& n) { n["model"].remove("bias_nm"); }},
      {"voltage_range", "training.voltage_min_v/voltage_max_v: expected two finite numbers, min <= max",
       [](YAML::Node& n) { n["training"]["voltage_min_v"] = 90.0; }},
      {"voltage_range_type", "training.voltage_min_v/voltage_max_v: expected two finite numbers",
       [](YAML::Node& n) { n["training"]["voltage_max_v"] = "high"; }},
      {"bad_feature", "model.features.features[0].type: unknown feature type",
       [](YAML::Node& n) { n["model"]["features"]["features"][0]["type"] = "nope"; }},
  };
  for (const auto& c : cases) {
    const auto [path, err] = variant(c.name, c.edit);
    EXPECT_EQ(err.rfind(path + ": ", 0), 0u) << c.name << ": " << err;
    EXPECT_NE(err.find(c.expect), std::string::npos) << c.name << ": " << err;
  }
  // PI kinds: the creep keys must fit the kind.
  const std::string lti = tmp("lti.yaml");
  save_model(lti, *models[3]);
  YAML::Node n = YAML::LoadFile(lti);
  n["kind"] = "pi_creep_log";
  write(lti, YAML::Dump(n));
  EXPECT_NE(load_error(lti).find("model.creep: kind pi_creep_log needs"), std::string::npos) << load_error(lti);
  n["kind"] = "pi_creep_lti";
  n["model"]["creep"]["gains_nm_per_v"] = std::vector<double>{1};
  write(lti, YAML::Dump(n));
  EXPECT_NE(load_error(lti).find("model.creep.gains_nm_per_v: expected 2 entries"), std::string::npos) << load_error(lti);
  // Not YAML / missing file.
  const std::string junk = tmp("junk.yaml");
  write(junk, "kind: [unclosed\n");
  EXPECT_NE(load_error(junk).find("not valid YAML"), std::string::npos);
  EXPECT_NE(load_error(tmp("does_not_exist.yaml")).find("cannot open"), std::string::npos);
}

// A kind on lagged samples (linear) is refused on data at another rate, with its reason; a PI kind (time constants
// in seconds, Model::set_step_s) is not. Either is refused for another axis.
TEST(ModelFile, DataOfAnotherRateOrAxisIsRejected) {
  auto models = one_of_each_kind();
  io::Dataset d;
  d.add_axis("c");
  for (int i = 0; i < 10; ++i) {
    d.time_s.push_back(i / 22.0);
    d.axis("c").voltage_v.push_back(0);
    d.axis("c").position_nm.push_back(0);
  }
  try {
    check_model_matches_data(*models[0], d, "m.yaml");
    FAIL();
  } catch (const ModelFileError& e) {
    EXPECT_NE(std::string(e.what()).find("m.yaml: sample_rate_hz 11 Hz does not match the data's 22 Hz"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find(kLaggedSamplesReason), std::string::npos) << e.what();
  }
  EXPECT_NO_THROW(check_model_matches_data(*models[1], d, "m.yaml"));
  models[1]->meta.axis = "a";
  for (auto& t : d.time_s) t *= 2;
  EXPECT_THROW(check_model_matches_data(*models[1], d, "m.yaml"), ModelFileError);
  models[1]->meta.axis = "c";
  EXPECT_NO_THROW(check_model_matches_data(*models[1], d, "m.yaml"));
  EXPECT_NO_THROW(check_model_matches_data(*models[0], d, "m.yaml"));
}

// A model runs only on the axis it was fitted for: the refusal names the file and both axes.
TEST(ModelFile, ModelOfAnotherAxisIsRefusedNamingBothAxes) {
  auto models = one_of_each_kind();
  models[0]->meta.axis = "c";
  EXPECT_NO_THROW(check_model_axis(*models[0], "c", "m_c.yaml"));
  try {
    check_model_axis(*models[0], "a", "m_c.yaml");
    FAIL() << "a model of axis c was accepted for axis a";
  } catch (const ModelFileError& e) {
    EXPECT_NE(std::string(e.what()).find("m_c.yaml: model fitted for axis c, loaded for axis a"), std::string::npos)
        << e.what();
  }
  // the file's own axis, as load_model reads it
  const std::string path = tmp("axis_b.yaml");
  save_model(path, *models[0]);
  auto loaded = load_model(path);
  EXPECT_EQ(loaded->meta.axis, "c");
  EXPECT_THROW(check_model_axis(*loaded, "b", path), ModelFileError);
  std::remove(path.c_str());
}
