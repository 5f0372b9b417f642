// The exported C99 header, compiled with the C compiler into a small program, must reproduce the C++ model
// sample by sample (one-step and free-run) and its inverse.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <sstream>

#include "piezo_compensation/features/feature_specs.h"
#include "piezo_compensation/models/c_export.h"
#include "piezo_compensation/models/linear_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "test_c_export.h"
#include "test_models_data.h"

using namespace piezo;
using namespace piezo::models;

namespace {

void expect_equal_to_cpp(Model& m, bool has_inverse) {
  const auto v = testdata::random_walk_v(3000, 12);
  std::vector<double> d;
  for (std::size_t i = 0; i < v.size(); ++i) d.push_back(15 * v[i] + std::sin(0.1 * i) * 30);
  const auto rows = run_c(m, v, d);
  ASSERT_EQ(rows.size(), v.size()) << m.kind();
  auto one = m.clone(), free = m.clone();
  one->reset(v[0], d[0]);
  free->reset(v[0], d[0]);
  double max_diff = 0;
  for (std::size_t i = 0; i < v.size(); ++i) {
    const ModelInput in{v[i], nullptr};
    if (has_inverse) {
      double inv;
      if (auto* pi = dynamic_cast<PiCreepModel*>(one.get())) {
        inv = pi->inverse(100.0);
      } else {
        const double f0 = one->predict({0.0, nullptr}), f1 = one->predict({1.0, nullptr});
        inv = (100.0 - f0) / (f1 - f0);
      }
      max_diff = std::max(max_diff, std::abs(rows[i][2] - inv) / (1 + std::abs(inv)));
    }
    const double a = one->predict(in), b = free->predict(in);
    max_diff = std::max(max_diff, std::abs(rows[i][0] - a) / (1 + std::abs(a)));
    max_diff = std::max(max_diff, std::abs(rows[i][1] - b) / (1 + std::abs(b)));
    one->commit(in, d[i]);
    free->commit(in, b);
  }
  EXPECT_LT(max_diff, 1e-10) << m.kind();
}

}  // namespace

TEST(CExport, LinearWithEveryFeatureTypeMatchesCpp) {
  features::FeatureSpec spec = features::candidate_features();
  for (const auto& f : features::study_features().features) spec.features.push_back(f);
  features::FeatureDef hinge;
  hinge.type = "play_hinge", hinge.threshold_v = 0.4, hinge.knot_v = 0.3;
  spec.features.push_back(hinge);
  spec.mean.clear();
  for (std::size_t j = 0; j < spec.size(); ++j) spec.mean.push_back(0.1 * j), spec.scale.push_back(1.0 + j);
  Eigen::VectorXd w = Eigen::VectorXd::LinSpaced(spec.size(), -2, 3);
  for (std::size_t j = 0; j < spec.size(); ++j)  // small position weights keep the free-run stable
    if (spec.features[j].type == "lagged_position" || spec.features[j].type == "position_mean") w(j) = 0.05;
  LinearModel m(spec, 11.0, w, 7.0);
  ASSERT_FALSE(m.is_affine_in_voltage());
  expect_equal_to_cpp(m, false);
  LinearModel affine(features::study_features(), 11.0, Eigen::VectorXd::LinSpaced(6, 0.5, 1.5), -3.0);
  ASSERT_TRUE(affine.is_affine_in_voltage());
  expect_equal_to_cpp(affine, true);
}

TEST(CExport, PiAndCreepKindsMatchCpp) {
  CreepParams none, log, lti, frac;
  log.kind = CreepKind::kLog, log.gamma_nm_per_v = 0.3, log.t1_s = 2;
  lti.kind = CreepKind::kLti, lti.taus_s = {10, 100}, lti.gains_nm_per_v = {0.5, 0.25};
  frac.kind = CreepKind::kFractional, frac.alpha = 0.35, frac.b_nm_per_v = 0.2;
  for (bool on_h : {false, true})
    for (auto cp : {none, log, lti, frac}) {
      cp.on_hysteresis = on_h;
      PiCreepModel m({0, 10, 20, 35}, {5, 1, 0.5, 0.25}, 2.0, cp, 11.0);
      expect_equal_to_cpp(m, true);
      // with an input map (the memory-free play in pieces)
      PiCreepModel mapped({0, 10, 20, 35}, {3, 5, 8, 6, 1, 0.5, 0.25}, 2.0, cp, 11.0, {{-30, 0, 30}, {}, {}, {}}, true);
      expect_equal_to_cpp(mapped, true);
      // with an output map (a monotone cubic of the hysteresis output; the inverse bisects through it)
      models::OutputMap om;
      om.lo_nm = -150, om.hi_nm = 150, om.quadratic_nm = 20, om.cubic_nm = -12;
      m.set_output_map(om);
      expect_equal_to_cpp(m, true);
    }
}

TEST(CExport, PreisachKindsMatchCpp) {
  CreepParams none, prony;
  prony.kind = CreepKind::kProny, prony.tau_min_s = 0.5, prony.tau_max_s = 500, prony.modes_per_decade = 1;
  prony.gains_nm_per_v = {0.1, 0.2, 0.05, 0.3};
  const std::vector<std::vector<double>> knots = {{-30, 0, 30}, {-10, 10}, {}, {5}};
  for (bool on_h : {false, true})
    for (auto cp : {none, prony}) {
      cp.on_hysteresis = on_h;
      PiCreepModel m({0, 10, 20, 35}, {5, 4, 6, 7, 1, 0.5, 2, 0.25, 0.1, 0.4}, 2.0, cp, 11.0, knots);
      expect_equal_to_cpp(m, true);
    }
}

TEST(CExport, BadPrefixAndAuxAreRefused) {
  PiCreepModel m({0}, {1}, 0, {}, 11.0);
  EXPECT_THROW(export_c99(m, "9abc"), std::runtime_error);
  features::FeatureSpec spec;
  features::FeatureDef aux;
  aux.type = "aux";
  aux.signal = "temperature_c";
  spec.features.push_back(aux);
  LinearModel lin(spec, 11.0, Eigen::VectorXd::Ones(1), 0);
  EXPECT_THROW(export_c99(lin, "pz"), std::runtime_error);
}
