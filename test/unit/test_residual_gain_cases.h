// Gain effects on a stage with physics the base is not written from: Preisach hysteresis (asymmetric
// relay hysterons) and a creep spectrum of four first-order modes (config/stages/mm3e_preisach_creep.yaml), 11 Hz,
// 20.8 nm encoder noise, 6 h of random walk (the first 70 % TRAIN, the rest TEST), fitted with a
// preisach_creep_prony base (play-operator pieces + a Prony creep series). Axis a (the simulator's default
// physics) walks too, so another axis' voltage and position are in the file. The stroke of axis c is scaled by
// 1 + f(signal) about its rest position at 0 V (what a stroke change scales); the effect is never declared.
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <random>
#include <string>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/util/fingerprint.h"

#include "test_reference_figure.h"
#include "test_residual_common.h"

namespace piezo::test::gain {

namespace pa = piezo::analysis;

constexpr double kHours = 6.0;
constexpr double kTrainFraction = 0.7;
constexpr std::uint64_t kSeed = 21;

inline std::string stage_file(const std::string& name) {
  return (std::filesystem::path(PIEZO_SOURCE_DIR) / "config" / "stages" / name).string();
}

inline const io::Dataset& stage() {
  static const io::Dataset d = [] {
    sim::StageConfig st = sim::load_stage(stage_file("mm3e_preisach_creep.yaml"));
    st.axes = {"a", "c"};
    return sim::simulate_stage(st, kSeed, kHours * 3600.0);
  }();
  return d;
}

// kTemperatureAndCoupling: two effects at once, a 2 %/°C stroke gain on the lagged temperature and an additive
// a → c coupling of 0.4 nm per volt of axis a, 1 s late (test_residual_two_effects.cpp).
enum class Gain { kNone, kTemperature, kTime, kOtherAxis, kHiddenTemperature, kTemperatureAndCoupling };

// Temperature: slow sine + random walk; the stage feels it through a 45 s lag and a 240 s low-pass.
inline std::vector<double> temperature(const io::Dataset& d) {
  std::mt19937_64 rng(kSeed + 7);
  std::normal_distribution<double> g(0.0, 1.0);
  std::vector<double> t(d.size());
  double w = 0;
  for (std::size_t i = 0; i < d.size(); ++i) {
    w += 0.0006 * g(rng);
    t[i] = 22.0 + 0.9 * std::sin(6.283185307179586 * d.time_s[i] / 7200.0 + 0.3) + w;
  }
  return t;
}

inline io::Dataset with_gain(Gain kind) {
  io::Dataset d = stage();
  auto& c = d.axis("c");
  const double fs = d.sample_rate_hz();
  // Rest position at 0 V: the truth where the voltage is near zero.
  double y0 = 0, k0 = 0;
  for (std::size_t i = 0; i < d.size(); ++i)
    if (std::fabs(c.voltage_v[i]) < 2.0) y0 += c.true_position_nm[i], k0 += 1;
  y0 = k0 > 0 ? y0 / k0 : 0.0;
  const std::vector<double> temp = temperature(d);
  const std::size_t lag = static_cast<std::size_t>(45 * fs);
  const double alpha = std::exp(-1.0 / (240.0 * fs));
  double tlp = temp[0];
  const auto& a = d.axis("a");
  double a_mean = 0;
  for (double x : a.true_position_nm) a_mean += x;
  a_mean /= static_cast<double>(d.size());
  for (std::size_t i = 0; i < d.size(); ++i) {
    tlp = alpha * tlp + (1 - alpha) * temp[i >= lag ? i - lag : 0];
    double f = 0.0;
    switch (kind) {
      case Gain::kNone: break;
      case Gain::kTemperature:
      case Gain::kHiddenTemperature: f = 0.04 * (tlp - 22.0); break;                        // 4 %/°C
      case Gain::kTime: f = -0.10 * d.time_s[i] / (kHours * 3600.0); break;                // −10 % over 6 h
      case Gain::kOtherAxis: f = 0.015 * (a.true_position_nm[i] - a_mean) / 1000.0; break;  // 1.5 %/µm
      case Gain::kTemperatureAndCoupling: f = 0.02 * (tlp - 22.0); break;                  // 2 %/°C
    }
    double dy = f * (c.true_position_nm[i] - y0);
    if (kind == Gain::kTemperatureAndCoupling) dy += 0.4 * a.voltage_v[i >= 11 ? i - 11 : 0];
    c.true_position_nm[i] += dy;
    c.position_nm[i] += dy;
  }
  if (kind == Gain::kTemperature || kind == Gain::kNone || kind == Gain::kTemperatureAndCoupling) d.aux.push_back({"temperature_c", temp});
  return d;
}

inline pa::ResidualOptions options() {
  pa::ResidualOptions o;
  o.axis = "c";
  o.permutations = 20;  // half the default: these runs are long
  if (std::getenv("PIEZO_RESIDUAL_VERBOSE")) o.log = [](const std::string& s) { std::cerr << s << "\n"; };
  return o;
}

inline models::ModelPtr fit_base(const io::Dataset& fit, const io::Dataset& val,
                                 const models::Model* previous = nullptr, bool same_structure = false) {
  return fit_physics_base(fit, val, "preisach_creep_prony", previous, same_structure);
}

struct Split {
  io::Dataset train, test;
  std::size_t n_fit = 0;
};
inline Split split(const io::Dataset& d) {
  const std::size_t cut = static_cast<std::size_t>(static_cast<double>(d.size()) * kTrainFraction);
  Split s{d.slice(0, cut), d.slice(cut, d.size())};
  s.n_fit = static_cast<std::size_t>(std::lround(static_cast<double>(s.train.size()) * (1.0 - options().validation_fraction)));
  return s;
}

inline pa::ResidualResult trace(Gain kind) {
  const Split s = split(with_gain(kind));
  pa::ResidualOptions o = options();
  o.refit_base = [](const io::Dataset& fit, const io::Dataset& val, const models::Model& previous, bool same) {
    return fit_base(fit, val, &previous, same);
  };
  const auto base = fit_base(s.train.slice(0, s.n_fit), s.train.slice(s.n_fit, s.train.size()));
  return pa::trace_residual(*base, s.train, s.test, o);
}

// (d)'s free-run TEST MAE against the truth when the loop adds nothing there (asserted by the (d) test): the
// base alone, warm-started from TRAIN as the loop runs TEST.
inline double clean_base_truth_mae(const io::Dataset& clean) {
  const Split s = split(clean);
  const auto base = fit_base(s.train.slice(0, s.n_fit), s.train.slice(s.n_fit, s.train.size()));
  models::StreamOptions so;
  so.warmup = &s.train;
  const auto pred = models::stream_model(*base, s.test, "c", so).prediction;
  const double m = pa::error_stats(pred, s.test.axis("c").true_position_nm).mae_nm;
  std::cerr << "(d) base alone: TEST MAE vs truth " << m << " nm\n";
  return m;
}

// What clean_base_truth_mae depends on, to check a figure the CTest fixture (test_residual_refs) wrote.
constexpr const char* kCleanRefEnv = "PIEZO_REF_RESIDUAL_GAIN_BASE";
inline std::string clean_key(const io::Dataset& clean) {
  return "residual_gain base alone " + util::fingerprint(clean) + " base " + physics_base_kind("preisach_creep_prony") +
         " train_fraction " + std::to_string(kTrainFraction) + " validation_fraction " +
         std::to_string(options().validation_fraction);
}

inline double clean_base_truth_mae() {
  static const double mae = [] {
    const io::Dataset clean = with_gain(Gain::kNone);
    return reference_figure(kCleanRefEnv, clean_key(clean), [&] { return clean_base_truth_mae(clean); });
  }();
  return mae;
}

inline void print(const char* name, const pa::ResidualResult& r) {
  std::cerr << name << ": TEST MAE vs truth " << r.before_test_truth.mae_nm << " -> " << r.after_test_truth.mae_nm
            << " nm, effects:";
  for (const auto& e : r.effects) {
    std::cerr << " " << e.family;
    for (const auto& [k, v] : e.labels) std::cerr << " " << k << "=" << v;
    for (const auto& [k, v] : e.parameters) std::cerr << " " << k << "=" << v;
  }
  std::cerr << "; remainder " << (r.remainder.explained ? "explained" : "NOT explained") << " "
            << r.remainder.structure_nm << " nm (σ " << r.remainder.noise_sigma_nm << " nm)\n";
}

// Each added effect must earn ≥ 2 % of TEST MAE against the truth: a real gap of the base, not a false find.
inline void expect_each_step_gains(const char* name, const pa::ResidualResult& r) {
  double prev = r.before_test_truth.mae_nm;
  for (const auto& e : r.effects) {
    EXPECT_GE(1.0 - e.test_after_truth.mae_nm / prev, 0.02) << name << ": added " << e.family << " for < 2 % TEST MAE";
    prev = e.test_after_truth.mae_nm;
  }
}

// Named as a gain of the right family and signal, nothing else added, within `within` × (d)'s MAE vs truth.
inline pa::ResidualResult expect_gain(Gain kind, const char* name, const std::string& family, const std::string& signal,
                                      double clean_mae, double within = 1.10) {
  pa::ResidualResult r = trace(kind);
  print(name, r);
  std::size_t gains = 0;
  for (const auto& e : r.effects) {
    if (pa::is_gain_family(e.family)) {
      ++gains;
      EXPECT_EQ(e.family, family) << name;
      // The other axis' voltage and position carry the same information (its position follows its voltage):
      // either names the right cause, axis a.
      if (!signal.empty()) {
        EXPECT_EQ(e.labels.at("signal").rfind(signal, 0), 0u) << name << ": " << e.labels.at("signal");
      }
    } else {
      ADD_FAILURE() << name << ": added " << e.family << " besides the gain";
    }
  }
  EXPECT_EQ(gains, 1u) << name << ": expected exactly one gain effect";
  expect_each_step_gains(name, r);
  std::cerr << name << ": " << r.after_test_truth.mae_nm / clean_mae << " × (d)'s " << clean_mae << " nm\n";
  EXPECT_LT(r.after_test_truth.mae_nm, within * clean_mae) << name << ": before " << r.before_test_truth.mae_nm << " nm";
  return r;
}

}  // namespace piezo::test::gain
