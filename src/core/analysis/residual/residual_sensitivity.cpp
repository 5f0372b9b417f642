// The residual loop's sensitivity harness: simulated stages with one planted effect of a known size, the loop
// run blind on each (analysis/residual/residual_sensitivity.h).
#include "piezo_compensation/analysis/residual/residual_sensitivity.h"

#include <algorithm>
#include <chrono>
#include <map>
#include <memory>
#include <cmath>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/sim/stage.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"
#include "piezo_compensation/sim/simulator_config.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::analysis {

namespace {

constexpr double kTwoPiS = 6.283185307179586;

struct Planted {
  SensitivityFamily family;
  double size_sigma;
};

double sd_of(const std::vector<double>& v) {
  double m = 0, s = 0;
  for (double x : v) m += x / static_cast<double>(v.size());
  for (double x : v) s += (x - m) * (x - m) / static_cast<double>(v.size());
  return std::sqrt(s);
}

// The c encoder's reading noise: Gaussian σ and the quantisation step's q²/12.
double reading_sigma_nm(const sim::SimulatorConfig& cfg) {
  const auto& c = cfg.axes[2];
  return std::sqrt(c.encoder_noise_sigma_nm * c.encoder_noise_sigma_nm +
                   c.encoder_quantisation_nm * c.encoder_quantisation_nm / 12.0);
}

io::Dataset simulate(const sim::SimulatorConfig& cfg, double hours, std::uint64_t seed) {
  YAML::Node p;
  p["duration_s"] = hours * 3600.0;
  const auto proto = protocols::make_protocol("random_walk", p, cfg.sample_rate_hz, seed);
  sim::ManipulatorSimulator s(cfg, seed);
  return s.run(proto->program());
}

// Adds a first-order Gauss–Markov wander of SD `sd` and correlation time `corr_s` to x (started at its stationary
// spread).
void add_gauss_markov(std::vector<double>& x, double sd, double corr_s, double fs, std::mt19937_64& rng) {
  std::normal_distribution<double> g(0.0, 1.0);
  const double rho = std::exp(-1.0 / (corr_s * fs));
  double w = sd * g(rng);
  for (double& v : x) {
    w = rho * w + sd * std::sqrt(1.0 - rho * rho) * g(rng);
    v += w;
  }
}

// A temperature the stage may feel: a first-order Gauss–Markov wander (σ 0.5 °C, correlation 400 s; a periodic one
// would make the circular-shift null as wide as its period allows), felt through a 20-s delay and a 60-s low-pass.
void temperature(const io::Dataset& d, std::uint64_t seed, std::vector<double>& t, std::vector<double>& felt) {
  std::mt19937_64 rng(seed * 7919 + 13);
  const double fs = d.sample_rate_hz();
  t.assign(d.size(), 22.0);
  felt.resize(d.size());
  add_gauss_markov(t, 0.5, 400.0, fs, rng);
  const std::size_t lag = static_cast<std::size_t>(20.0 * fs);
  const double a = std::exp(-1.0 / (60.0 * fs));
  double lp = t[0];
  for (std::size_t i = 0; i < d.size(); ++i) felt[i] = lp = a * lp + (1 - a) * t[i >= lag ? i - lag : 0];
}

// Adds dy to axis c's truth and readings (an effect in the stage's motion).
void add_motion(io::Dataset& d, const std::vector<double>& dy) {
  auto& c = d.axis("c");
  for (std::size_t i = 0; i < d.size(); ++i) c.true_position_nm[i] += dy[i], c.position_nm[i] += dy[i];
}

// A temperature-driven effect on c: additive (RMS = size σ) or a stroke gain about the rest position at 0 V.
void plant_thermal(io::Dataset& d, bool gain, double rms_nm, const std::vector<double>& felt) {
  const auto& c = d.axis("c");
  double y0 = 0, k0 = 0;
  for (std::size_t i = 0; i < d.size(); ++i)
    if (std::fabs(c.voltage_v[i]) < 2.0) y0 += c.true_position_nm[i], k0 += 1;
  y0 = k0 > 0 ? y0 / k0 : 0.0;
  std::vector<double> shape(d.size());
  for (std::size_t i = 0; i < d.size(); ++i) shape[i] = (felt[i] - 22.0) * (gain ? c.true_position_nm[i] - y0 : 1.0);
  const double s = sd_of(shape);
  if (!(s > 0)) return;
  double mean = 0;
  for (double x : shape) mean += x / static_cast<double>(shape.size());
  for (double& x : shape) x = rms_nm / s * (gain ? x : x - mean);
  add_motion(d, shape);
}

io::Dataset make_stage(const Planted* p, double hours, std::uint64_t seed, double& sigma_nm) {
  sim::SimulatorConfig cfg = sim::default_simulator_config();
  sigma_nm = reading_sigma_nm(cfg);
  const double rms = p ? p->size_sigma * sigma_nm : 0.0;
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::mt19937_64 rng(seed * 104729 + 7);
  if (p && p->family == SensitivityFamily::kPeriodic) {
    sim::enable_effect(cfg, "encoder_periodic");
    cfg.encoder_periodic.amplitude_nm = std::sqrt(2.0) * rms;
    cfg.encoder_periodic.period_nm = 250.0 + 200.0 * u(rng);
    cfg.encoder_periodic.phase_rad = kTwoPiS * u(rng);
  } else if (p && p->family == SensitivityFamily::kCrossAxis) {
    // The coupling's gain from axis a's displacement on the same stage without it (a is not changed by it).
    const io::Dataset clean = simulate(cfg, hours, seed);
    const double s = sd_of(clean.axis("a").true_position_nm);
    sim::enable_effect(cfg, "cross_axis");
    cfg.cross_axis.gain = s > 0 ? rms / s : 0.0;
  }
  io::Dataset d = simulate(cfg, hours, seed);
  std::vector<double> t, felt;
  temperature(d, seed, t, felt);
  if (p && (p->family == SensitivityFamily::kAuxSignal || p->family == SensitivityFamily::kGain))
    plant_thermal(d, p->family == SensitivityFamily::kGain, rms, felt);
  d.aux.push_back({"temperature_c", t});
  return d;
}

bool names(const FoundEffect& e, SensitivityFamily f) {
  const auto it = e.labels.find("signal");
  const std::string sig = it == e.labels.end() ? "" : it->second;
  switch (f) {
    case SensitivityFamily::kPeriodic: return e.family == "position_periodic";
    case SensitivityFamily::kCrossAxis:
      return (e.family == "cross_axis" || e.family == "cross_axis_gain") && sig.rfind("a_", 0) == 0;
    case SensitivityFamily::kAuxSignal: return e.family == "aux_signal" && sig == "temperature_c";
    case SensitivityFamily::kGain: return e.family == "aux_gain" && sig == "temperature_c";
  }
  return false;
}

// The base of axis ro.axis fitted on TRAIN's first part, and the refit backfitting uses, as `piezo residual` does
// (a base fitted on data that hold the effect has absorbed part of it).
models::ModelPtr loop_base(const io::Dataset& train, ResidualOptions& ro, const std::string& kind) {
  const std::size_t n_fit =
      static_cast<std::size_t>(std::lround(static_cast<double>(train.size()) * (1.0 - ro.validation_fraction)));
  ModelCandidate fitted{kind, kind, YAML::Node(), false};
  models::ModelPtr base = kind == "auto" ? fit_auto(train, n_fit, ro.axis, ro.seed, &fitted)
                                         : fit_axis_model(train, n_fit, ro.axis, kind, ro.seed, false);
  ro.refit_base = [fitted, axis = ro.axis, seed = ro.seed](const io::Dataset& f, const io::Dataset& v,
                                                           const models::Model& previous, bool same_structure) {
    training::FitRequest r;
    r.train = &f;
    r.validation = &v;
    r.axis = axis;
    r.seed = seed;
    r.options = training::refit_options(previous, fitted.options, same_structure);
    return training::fit_model(fitted.kind, r);
  };
  return base;
}

std::vector<FoundEffect> run_trial(const Planted* p, const SensitivityOptions& o, std::uint64_t seed, double& sigma_nm) {
  const io::Dataset d = make_stage(p, o.hours, seed, sigma_nm);
  const std::size_t cut = static_cast<std::size_t>(static_cast<double>(d.size()) * o.train_fraction);
  const io::Dataset train = d.slice(0, cut), test = d.slice(cut, d.size());
  ResidualOptions ro;
  ro.axis = "c";
  ro.permutations = o.permutations;
  ro.max_effects = 3;
  ro.seed = seed;
  ro.log = o.loop_log;
  const models::ModelPtr base = loop_base(train, ro, o.base_kind);
  return trace_residual(*base, train, test, ro).effects;
}

std::string added_text(const std::vector<FoundEffect>& effects) {
  std::string s;
  for (const auto& e : effects) {
    const auto it = e.labels.find("signal");
    s += (s.empty() ? "" : ", ") + e.family + (it == e.labels.end() ? "" : "(" + it->second + ")");
  }
  return s.empty() ? "nothing" : s;
}

// The comparison's stage: c from the stage file (or the default simulator), a driven with c's physics and coarse steps.
sim::StageConfig comparison_stage(const ComparisonOptions& o) {
  sim::StageConfig st;
  if (!o.stage_path.empty()) st = sim::load_stage(o.stage_path);
  else st.simulator = sim::default_simulator_config();
  st.axes = {"a", "c"};
  const std::string name = st.simulator.axes[0].name;
  st.simulator.axes[0] = st.simulator.axes[2];
  st.simulator.axes[0].name = name;
  st.simulator.axes[0].encoder_quantisation_nm = o.encoder_step_a_nm;
  return st;
}

bool planted(const ComparisonOptions& o, const char* name) {
  return std::find(o.effects.begin(), o.effects.end(), name) != o.effects.end();
}

io::Dataset comparison_data(const ComparisonOptions& o, bool with_effects, double& sigma_nm) {
  sim::StageConfig st = comparison_stage(o);
  sigma_nm = reading_sigma_nm(st.simulator);
  const double rms = o.size_sigma * sigma_nm;
  std::mt19937_64 rng(o.seed * 104729 + 7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  if (with_effects && planted(o, "periodic")) {
    sim::enable_effect(st.simulator, "encoder_periodic");
    st.simulator.encoder_periodic.amplitude_nm = std::sqrt(2.0) * rms;
    st.simulator.encoder_periodic.period_nm = 250.0 + 200.0 * u(rng);
    st.simulator.encoder_periodic.phase_rad = kTwoPiS * u(rng);
  }
  if (with_effects && planted(o, "cross_axis")) {
    const io::Dataset clean = sim::simulate_stage(st, o.seed, o.hours * 3600.0);
    const double s = sd_of(clean.axis("a").true_position_nm);
    sim::enable_effect(st.simulator, "cross_axis");
    st.simulator.cross_axis.gain = s > 0 ? rms / s : 0.0;
  }
  io::Dataset d = sim::simulate_stage(st, o.seed, o.hours * 3600.0);
  // The room's temperature: a 2-h cycle of 0.9 °C and a random walk (and the optional wander), felt through a
  // first-order lag.
  std::vector<double> t(d.size()), felt(d.size());
  {
    std::mt19937_64 trng(o.seed * 7919 + 29), wrng(o.seed * 6271 + 3);
    std::normal_distribution<double> g(0.0, 1.0);
    const double phase = kTwoPiS * u(rng), a = std::exp(-1.0 / (o.gain_lag_s * d.sample_rate_hz()));
    double w = 0.0;
    for (std::size_t i = 0; i < d.size(); ++i) {
      w += 0.0006 * g(trng);
      t[i] = 22.0 + 0.9 * std::sin(kTwoPiS * d.time_s[i] / 7200.0 + phase) + w;
    }
    // Its own generator and distribution: the walk above is the same with or without the wander.
    add_gauss_markov(t, o.temperature_wander_c, 400.0, d.sample_rate_hz(), wrng);
    for (std::size_t i = 0; i < d.size(); ++i) felt[i] = i == 0 ? t[0] : a * felt[i - 1] + (1.0 - a) * t[i];
  }
  if (with_effects && planted(o, "gain")) plant_thermal(d, true, rms, felt);
  if (with_effects && planted(o, "slips")) {
    std::vector<double> dy(d.size(), 0.0);
    for (std::size_t i = 0; i < d.size(); ++i)
      dy[i] = (i >= d.size() * 8 / 10 ? 60.0 : 0.0) + (i >= d.size() * 9 / 10 ? -45.0 : 0.0);
    add_motion(d, dy);
  }
  d.aux.push_back({"temperature_c", t});
  return d;
}


ComparisonRun compare_once(const ComparisonOptions& o, bool with_effects, double& sigma_nm) {
  const io::Dataset d = comparison_data(o, with_effects, sigma_nm);
  const std::size_t cut = static_cast<std::size_t>(static_cast<double>(d.size()) * o.train_fraction);
  io::Dataset train = d.slice(0, cut), test = d.slice(cut, d.size());
  ResidualOptions ro;
  ro.axis = "c";
  ro.permutations = o.permutations;
  ro.seed = o.seed;
  ro.log = o.loop_log;
  const std::size_t n_fit =
      static_cast<std::size_t>(std::lround(static_cast<double>(train.size()) * (1.0 - ro.validation_fraction)));
  if (o.fused_other_axis) {
    std::map<std::string, std::shared_ptr<const models::Model>> others;
    others["a"] = fit_axis_model(train, n_fit, "a", o.base_kind, o.seed, true);
    add_fused_positions(train, test, others, "c", ro.warm_start, o.loop_log);
    if (o.loop_log) {
      std::ostringstream os;
      os << "a's fused position against its truth: MAE TRAIN "
         << error_stats(train.find_aux("a_fused_position_nm")->values, train.axis("a").true_position_nm).mae_nm
         << " nm, TEST " << error_stats(test.find_aux("a_fused_position_nm")->values, test.axis("a").true_position_nm).mae_nm
         << " nm (its readings: " << error_stats(test.axis("a").position_nm, test.axis("a").true_position_nm).mae_nm << " nm)";
      o.loop_log(os.str());
    }
  }
  const models::ModelPtr base = loop_base(train, ro, o.base_kind);
  const ResidualResult res = trace_residual(*base, train, test, ro);
  return ComparisonRun{res.before_test_truth.mae_nm, res.after_test_truth.mae_nm, res.effects};
}

void effect_lines(std::ostringstream& f, const std::vector<FoundEffect>& effects) {
  if (effects.empty()) f << "  nothing added\n";
  for (const auto& e : effects) {
    f << "  " << e.family << (e.in_readings ? " (sensor effect: in the readings)" : " (stage effect)") << ":";
    for (const auto& [k, v] : e.labels) f << " " << k << "=" << v;
    for (const auto& [k, v] : e.parameters) f << " " << k << "=" << v;
    f << "\n";
  }
}

}  // namespace

ComparisonResult run_comparison(const ComparisonOptions& o) {
  for (const auto& e : o.effects)
    if (e != "cross_axis" && e != "gain" && e != "periodic" && e != "slips")
      throw std::invalid_argument("unknown planted effect '" + e + "' (valid: cross_axis, gain, periodic, slips)");
  if (!(o.hours >= 0.5) || !(o.train_fraction > 0.3 && o.train_fraction < 0.95) || !(o.size_sigma > 0) ||
      !(o.gain_lag_s > 0) || !(o.encoder_step_a_nm >= 0) || !(o.temperature_wander_c >= 0))
    throw std::invalid_argument(
        "comparison: hours ≥ 0.5, train fraction in (0.3, 0.95), size, gain lag > 0, step ≥ 0, wander ≥ 0");
  const auto t0 = std::chrono::steady_clock::now();
  ComparisonResult r;
  r.with_effects = compare_once(o, true, r.noise_sigma_nm);
  r.clean = o.effects.empty() ? r.with_effects : compare_once(o, false, r.noise_sigma_nm);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

std::string comparison_text(const ComparisonResult& r, const ComparisonOptions& o) {
  std::ostringstream f;
  f.precision(4);
  f << "stage " << (o.stage_path.empty() ? "default simulator" : o.stage_path) << ", axes a (" << o.encoder_step_a_nm
    << "-nm steps) and c, " << o.hours << " h, seed " << o.seed << ", base " << o.base_kind << ", a "
    << (o.fused_other_axis ? "through its fused position" : "through its readings and voltage") << "\n";
  f << "planted:";
  for (const auto& e : o.effects) f << " " << e;
  if (o.effects.empty()) f << " nothing";
  f << " (" << o.size_sigma << " σ each, σ " << r.noise_sigma_nm << " nm; gain lag " << o.gain_lag_s << " s";
  if (o.temperature_wander_c > 0) f << "; temperature wander " << o.temperature_wander_c << " °C";
  f << ")\n";
  f << "with effects: TEST MAE vs truth " << r.with_effects.before_truth_nm << " -> " << r.with_effects.after_truth_nm << " nm\n";
  effect_lines(f, r.with_effects.effects);
  f << "clean stage: TEST MAE vs truth " << r.clean.before_truth_nm << " -> " << r.clean.after_truth_nm << " nm\n";
  effect_lines(f, r.clean.effects);
  f << "ratio (with effects / clean, after the loop): " << r.with_effects.after_truth_nm / r.clean.after_truth_nm << "\n";
  f << r.seconds << " s wall\n";
  return f.str();
}

const char* sensitivity_family_name(SensitivityFamily f) {
  switch (f) {
    case SensitivityFamily::kPeriodic: return "periodic";
    case SensitivityFamily::kCrossAxis: return "cross_axis";
    case SensitivityFamily::kAuxSignal: return "aux_signal";
    case SensitivityFamily::kGain: return "gain";
  }
  return "?";
}

SensitivityFamily parse_sensitivity_family(const std::string& name) {
  for (SensitivityFamily f : {SensitivityFamily::kPeriodic, SensitivityFamily::kCrossAxis, SensitivityFamily::kAuxSignal,
                              SensitivityFamily::kGain})
    if (name == sensitivity_family_name(f)) return f;
  throw std::invalid_argument("unknown sensitivity family '" + name + "' (valid: periodic, cross_axis, aux_signal, gain)");
}

io::Dataset sensitivity_stage(const SensitivityFamily* family, double size_sigma, double hours, std::uint64_t seed,
                              double* sigma_nm) {
  double sigma = 0.0;
  const Planted p{family ? *family : SensitivityFamily::kPeriodic, size_sigma};
  io::Dataset d = make_stage(family ? &p : nullptr, hours, seed, sigma);
  if (sigma_nm) *sigma_nm = sigma;
  return d;
}

SensitivityResult run_sensitivity(const SensitivityOptions& o) {
  if (!(o.hours >= 0.5) || !(o.train_fraction > 0.3 && o.train_fraction < 0.95) || o.trials < 0 || o.clean_trials < 0)
    throw std::invalid_argument("sensitivity: hours must be ≥ 0.5, train fraction in (0.3, 0.95), trials ≥ 0");
  const auto t0 = std::chrono::steady_clock::now();
  SensitivityResult r;
  auto say = [&](const std::string& s) {
    if (o.progress) o.progress(s);
  };
  for (int t = 0; t < o.clean_trials; ++t) {
    const std::vector<FoundEffect> e = run_trial(nullptr, o, o.seed + static_cast<std::uint64_t>(t), r.noise_sigma_nm);
    ++r.clean_trials;
    if (!e.empty()) ++r.clean_false;
    for (const auto& x : e) r.clean_added.push_back(x.family);
    say("clean, seed " + std::to_string(o.seed + t) + ": " + added_text(e));
  }
  for (SensitivityFamily f : o.families)
    for (double size : o.sizes_sigma) {
      SensitivityCell cell{f, size, 0, 0, 0};
      const Planted p{f, size};
      for (int t = 0; t < o.trials; ++t) {
        const std::vector<FoundEffect> e = run_trial(&p, o, o.seed + static_cast<std::uint64_t>(t), r.noise_sigma_nm);
        ++cell.trials;
        bool hit = false;
        for (const auto& x : e) hit = hit || names(x, f);
        cell.detected += hit;
        cell.other += !hit && !e.empty();
        std::ostringstream os;
        os << sensitivity_family_name(f) << " " << size << " σ, seed " << o.seed + t << ": " << added_text(e)
           << (hit ? " (named)" : "");
        say(os.str());
      }
      r.cells.push_back(cell);
    }
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

std::string sensitivity_table(const SensitivityResult& r, const SensitivityOptions& o) {
  std::ostringstream f;
  f.precision(3);
  f << "| family (named as) |";
  for (double s : o.sizes_sigma) f << " " << s << " σ |";
  f << "\n|---|";
  for (std::size_t i = 0; i < o.sizes_sigma.size(); ++i) f << "---|";
  f << "\n";
  const char* named[] = {"position_periodic", "cross_axis(_gain) on a", "aux_signal on temperature_c",
                         "aux_gain on temperature_c"};
  for (SensitivityFamily fam : o.families) {
    f << "| " << sensitivity_family_name(fam) << " (" << named[static_cast<int>(fam)] << ") |";
    for (const auto& c : r.cells)
      if (c.family == fam)
        f << " " << c.detected << "/" << c.trials << (c.other ? " (+" + std::to_string(c.other) + " other)" : "") << " |";
    f << "\n";
  }
  f << "\nClean stages: " << r.clean_false << " of " << r.clean_trials << " had anything added";
  if (r.clean_trials > 0) f << " (false-positive rate " << 100.0 * r.clean_false / r.clean_trials << " %)";
  if (!r.clean_added.empty()) {
    f << ":";
    for (const auto& a : r.clean_added) f << " " << a;
  }
  f << ". Sizes are the effect's RMS on the readings over the reading noise σ = " << r.noise_sigma_nm << " nm; "
    << o.hours << " h stages, TRAIN " << o.train_fraction * 100 << " %, base " << o.base_kind << ", seeds " << o.seed
    << " … " << o.seed + static_cast<std::uint64_t>(std::max(o.trials, o.clean_trials)) - 1 << "; " << r.seconds
    << " s wall.\n";
  return f.str();
}

}  // namespace piezo::analysis
