// Shared pieces of the simulator residual tests (test_residual_sim*.cpp): 6 h of random walk at 11 Hz (4 h
// TRAIN, 2 h TEST) with one simulator effect switched on and never declared; the right family must come first
// and the TEST MAE after must be within 15 % of what the same model reaches on the same protocol without it.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <iostream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/util/fingerprint.h"

#include "test_reference_figure.h"
#include "test_residual_common.h"

namespace pa = piezo::analysis;

namespace residual_sim {
constexpr double kHours = 6.0;       // 4 h TRAIN, 2 h TEST of 11 Hz random walk
constexpr std::uint64_t kSeed = 8;

inline piezo::io::Dataset simulate(const std::string& effect) {
  YAML::Node p;
  p["duration_s"] = kHours * 3600.0;
  const auto proto = piezo::protocols::make_protocol("random_walk", p, 11.0, kSeed);
  piezo::sim::SimulatorConfig cfg = piezo::sim::default_simulator_config();
  if (!effect.empty()) piezo::sim::enable_effect(cfg, effect);
  piezo::sim::ManipulatorSimulator sim(cfg, kSeed);
  return sim.run(proto->program());
}

struct Split {
  piezo::io::Dataset train, test;
};
inline Split split(const piezo::io::Dataset& d) {
  const std::size_t cut = d.size() * 2 / 3;
  return {d.slice(0, cut), d.slice(cut, d.size())};
}

inline pa::ResidualOptions options() {
  pa::ResidualOptions o;
  o.axis = "c";
  if (std::getenv("PIEZO_RESIDUAL_VERBOSE")) o.log = [](const std::string& s) { std::cerr << s << "\n"; };
  return o;
}

inline piezo::models::ModelPtr fit_base(const piezo::io::Dataset& fit, const piezo::io::Dataset& val,
                                        const piezo::models::Model* previous = nullptr, bool same_structure = false);
inline piezo::models::ModelPtr fit_base(const piezo::io::Dataset& train, const pa::ResidualOptions& o) {
  const std::size_t n_fit = static_cast<std::size_t>(std::lround(static_cast<double>(train.size()) * (1.0 - o.validation_fraction)));
  return fit_base(train.slice(0, n_fit), train.slice(n_fit, train.size()));
}

inline piezo::models::ModelPtr fit_base(const piezo::io::Dataset& fit, const piezo::io::Dataset& val,
                                        const piezo::models::Model* previous, bool same_structure) {
  return piezo::test::fit_physics_base(fit, val, "pi_creep_lti", previous, same_structure);
}

// The same protocol without an effect: the base's TEST MAE there.
inline double clean_mae(const piezo::io::Dataset& clean) {
  const Split s = split(clean);
  const auto base = fit_base(s.train, options());
  const auto pred = [&] { piezo::models::StreamOptions so; so.warmup = &s.train; return piezo::models::stream_model(*base, s.test, "c", so).prediction; }();
  return pa::error_stats(pred, s.test.axis("c").position_nm).mae_nm;
}

// What clean_mae depends on, to check a figure the CTest fixture (test_residual_refs) wrote.
constexpr const char* kCleanRefEnv = "PIEZO_REF_RESIDUAL_SIM_CLEAN";
inline std::string clean_key(const piezo::io::Dataset& clean) {
  return "residual_sim clean " + piezo::util::fingerprint(clean) + " base " + piezo::test::physics_base_kind() +
         " validation_fraction " + std::to_string(options().validation_fraction);
}

inline double clean_mae() {
  static const double mae = [] {
    const piezo::io::Dataset clean = simulate("");
    return piezo::test::reference_figure(kCleanRefEnv, clean_key(clean), [&] { return clean_mae(clean); });
  }();
  return mae;
}

inline pa::ResidualResult trace(const std::string& effect) {
  const Split s = split(simulate(effect));
  pa::ResidualOptions o = options();
  o.refit_base = [&](const piezo::io::Dataset& fit, const piezo::io::Dataset& val, const piezo::models::Model& previous,
                     bool same_structure) {
    return fit_base(fit, val, &previous, same_structure);
  };
  const auto base = fit_base(s.train, o);
  return pa::trace_residual(*base, s.train, s.test, o);
}

inline void expect_found(const std::string& effect, const std::string& family) {
  const pa::ResidualResult r = trace(effect);
  const double clean = clean_mae();
  std::cerr << effect << ": TEST MAE " << r.before_test.mae_nm << " -> " << r.after_test.mae_nm << " nm (clean " << clean
            << " nm), effects:";
  for (const auto& e : r.effects) std::cerr << " " << e.family;
  std::cerr << "\n";
  EXPECT_TRUE(r.warm_started);
  if (r.effects.empty())
    for (const auto& f : r.final_ranking)
      std::cerr << "  " << f.family << ": significant " << f.significant << ", p " << f.p_value << ", validation gain "
                << f.validation_gain << ", " << f.note << "\n";
  ASSERT_FALSE(r.effects.empty()) << effect << ": nothing found";
  EXPECT_EQ(r.effects.front().family, family) << effect;
  EXPECT_LT(r.after_test.mae_nm, 1.15 * clean) << effect << ": before " << r.before_test.mae_nm << " nm";
}
}  // namespace residual_sim
