// The prony creep kind (pi_creep_prony) and the scale-free PI fits, checked on physics the models were not
// written from: Preisach hysteresis with asymmetric relays and a spectrum of first-order creep modes, generated
// here independently of the simulator and of the model classes.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <random>

#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/models/registry.h"
#include "piezo_compensation/protocols/protocol.h"

using namespace piezo;
using models::PiCreepModel;

namespace {

// Preisach hysteresis: relays (up at α, down at β ≤ α) on a grid over [vmin, vmax], weight density over the
// centre c and half-width w (fractions of the half range) μ ∝ exp(−(c − c0)²/(2s²))·exp(−w/wd): the centre
// offset c0 makes the loops asymmetric, which no sum of symmetric play operators reproduces. Creep: first-order
// modes on the hysteretic output, y = H + Σ g_j·LP_τj(H). Encoder: Gaussian noise, then quantisation.
struct Physics {
  double vmin = -80, vmax = 80, stroke_nm = 2000;
  int grid = 40;
  double c0 = 0.25, spread = 0.45, width_decay = 0.25;
  std::vector<double> taus_s, gains;  // creep spectrum
  double noise_nm = 20.0, quant_nm = 20.0;
};

io::Dataset run_physics(const Physics& ph, io::Dataset d, double rate_hz, std::uint64_t seed) {
  io::AxisSeries& ax = d.axis("c");
  const std::vector<double>& V = ax.voltage_v;
  const double R = 0.5 * (ph.vmax - ph.vmin), mid = 0.5 * (ph.vmax + ph.vmin);
  struct Relay { double up, down, mu; bool on; };
  std::vector<Relay> relays;
  double mu_sum = 0;
  for (int i = 0; i < ph.grid; ++i)
    for (int j = 0; j <= i; ++j) {
      const double a = ph.vmin + (ph.vmax - ph.vmin) * (i + 0.5) / ph.grid;
      const double b = ph.vmin + (ph.vmax - ph.vmin) * (j + 0.5) / ph.grid;
      const double c = (0.5 * (a + b) - mid) / R, w = 0.5 * (a - b) / R;
      const double mu = std::exp(-(c - ph.c0) * (c - ph.c0) / (2 * ph.spread * ph.spread)) * std::exp(-w / ph.width_decay);
      relays.push_back({a, b, mu, V[0] >= a});
      mu_sum += mu;
    }
  for (auto& r : relays) r.mu *= ph.stroke_nm / mu_sum;
  auto hyst = [&](double v) {
    double h = 0;
    for (auto& r : relays) {
      if (v >= r.up) r.on = true;
      if (v <= r.down) r.on = false;
      if (r.on) h += r.mu;
    }
    return h;
  };
  const double h0 = hyst(V[0]);
  std::vector<double> l(ph.taus_s.size(), h0), a;
  for (double t : ph.taus_s) a.push_back(std::exp(-1.0 / (rate_hz * t)));
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, ph.noise_nm);
  ax.true_position_nm.resize(V.size());
  ax.position_nm.resize(V.size());
  for (std::size_t t = 0; t < V.size(); ++t) {
    const double h = hyst(V[t]);
    double y = h;
    for (std::size_t j = 0; j < l.size(); ++j) {
      l[j] = a[j] * l[j] + (1 - a[j]) * h;
      y += ph.gains[j] * l[j];
    }
    ax.true_position_nm[t] = y;
    ax.position_nm[t] = ph.quant_nm * std::round((y + noise(rng)) / ph.quant_nm);
  }
  return d;
}

io::Dataset slice(const io::Dataset& d, std::size_t b, std::size_t e) {
  io::Dataset s;
  s.time_s.assign(d.time_s.begin() + b, d.time_s.begin() + e);
  io::AxisSeries& ax = s.add_axis("c");
  const io::AxisSeries& src = d.axis("c");
  ax.voltage_v.assign(src.voltage_v.begin() + b, src.voltage_v.begin() + e);
  ax.position_nm.assign(src.position_nm.begin() + b, src.position_nm.begin() + e);
  ax.true_position_nm.assign(src.true_position_nm.begin() + b, src.true_position_nm.begin() + e);
  s.phase.assign(d.phase.begin() + b, d.phase.begin() + e);
  s.segment.assign(d.segment.begin() + b, d.segment.begin() + e);
  return s;
}

struct HoldScore {
  double mae_nm = 0, worst_end_nm = 0;
  int holds = 0;
};

// Free-run over all of `d` from rest at its first voltage; scored against the true position inside the holds of
// samples ≥ from: MAE, and per hold the mean error of its last 5 s.
HoldScore score_holds(const models::Model& fitted, const io::Dataset& d, std::size_t from, double rate_hz) {
  auto m = fitted.clone();
  const io::AxisSeries& ax = d.axis("c");
  m->reset(ax.voltage_v[0], ax.position_nm[0]);
  HoldScore s;
  double sum = 0;
  std::size_t n = 0;
  std::vector<double> err(ax.voltage_v.size(), 0.0);
  for (std::size_t t = 0; t < ax.voltage_v.size(); ++t) {
    models::ModelInput in{ax.voltage_v[t], nullptr};
    const double y = m->predict(in);
    m->commit(in, y);
    err[t] = y - ax.true_position_nm[t];
    if (t >= from && d.phase[t] == 1) sum += std::abs(err[t]), ++n;
  }
  s.mae_nm = n ? sum / n : INFINITY;
  const std::size_t last = static_cast<std::size_t>(5 * rate_hz);
  for (std::size_t t = from; t < err.size(); ++t) {
    const bool end_of_hold = d.phase[t] == 1 && (t + 1 == err.size() || d.phase[t + 1] != 1);
    if (!end_of_hold) continue;
    double e = 0;
    for (std::size_t k = t + 1 - last; k <= t; ++k) e += err[k];
    s.worst_end_nm = std::max(s.worst_end_nm, std::abs(e / last));
    ++s.holds;
  }
  return s;
}

}  // namespace

// Issue 12's done-when on independent physics: the creep protocol (each scenario a 30-min random history ending in
// a fast approach, then a 30-min hold) with Preisach hysteresis and a creep spectrum between seconds and hours,
// 11 Hz, σ 20 nm + 20 nm LSB. 12 scenarios instead of 15 (fast test): 7 train, 2 validation, 3 test; the model
// runs free over all of them and is scored in the test holds against the true position.
TEST(PronyCreep, HoldsWithinFiveNanometresOnPreisachWithACreepSpectrum) {
  const double rate = 11.0;
  YAML::Node p;
  p["scenarios"] = 12;
  const auto protocol = protocols::make_protocol("creep", p, rate, 20261124);
  io::Dataset program = protocol->program();
  Physics ph;
  ph.taus_s = {2.5, 35.0, 420.0, 3100.0, 26000.0};
  ph.gains = {0.05, 0.04, 0.06, 0.07, 0.09};
  io::Dataset d = run_physics(ph, program, rate, 77);
  if (const char* dump = std::getenv("PIEZO_TEST_DUMP")) io::write_csv(dump, d);
  const std::size_t per = d.time_s.size() / 12, n_train = 7 * per, n_val = 9 * per;
  const io::Dataset train = slice(d, 0, n_train), val = slice(d, n_train, n_val);

  models::FitRequest req;
  req.train = &train;
  req.validation = &val;
  auto prony = models::model_kind("pi_creep_prony").fit(req);
  const HoldScore s = score_holds(*prony, d, n_val, rate);
  std::cout << "pi_creep_prony: test-hold MAE vs truth " << s.mae_nm << " nm, worst end-of-hold " << s.worst_end_nm
            << " nm over " << s.holds << " holds\n";
  EXPECT_EQ(s.holds, 3);
  EXPECT_LE(s.mae_nm, 5.0);
  EXPECT_LE(s.worst_end_nm, 5.0);
  // Identifiable modes only: none faster than two samples, none slower than the training record.
  const auto& pm = dynamic_cast<const PiCreepModel&>(*prony);
  for (double tau : pm.mode_taus_s()) {
    EXPECT_GE(tau, 2.0 / rate * 0.999);
    EXPECT_LE(tau, n_train / rate * 1.001);
  }
  for (double g : pm.mode_gains()) EXPECT_GE(g, 0.0);
}

// The failure of issue 11: a short, fast, low-voltage recording (0–3.6 V, ~50 µm, 200 Hz, 40 s). Every PI kind
// must give a bias and weights of the data's own scale (no cancelling pair), no mode the data cannot see, and a
// free-run error on a later file that starts mid-motion far below the travel.
TEST(PronyCreep, ShortLowVoltageRecordingGivesSaneParametersForEveryPiKind) {
  const double rate = 200.0;
  Physics ph;
  ph.vmin = 0, ph.vmax = 3.6, ph.stroke_nm = 50000, ph.grid = 30;
  ph.taus_s = {0.05, 0.8, 12.0, 300.0, 9000.0};
  ph.gains = {0.03, 0.04, 0.05, 0.05, 0.08};
  ph.noise_nm = 10, ph.quant_nm = 5;
  auto make = [&](std::size_t n, std::uint64_t seed) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    io::Dataset d;
    io::AxisSeries& ax = d.add_axis("c");
    double v = 1.8, target = 1.8, speed = 1.0;
    for (std::size_t i = 0; i < n; ++i) {
      if (std::abs(v - target) < 1e-9) target = 3.6 * u(rng), speed = 0.2 + 4.0 * u(rng);
      const double step = speed / rate;
      v = std::abs(target - v) < step ? target : v + (target > v ? step : -step);
      d.time_s.push_back(i / rate);
      ax.voltage_v.push_back(v);
    }
    return run_physics(ph, d, rate, seed + 1);
  };
  const io::Dataset all = make(static_cast<std::size_t>(40 * rate), 5);
  io::Dataset test_full = make(static_cast<std::size_t>(75 * rate), 9);
  // The test file starts 5 s into its motion (unknown state).
  io::Dataset test;
  const std::size_t cut = static_cast<std::size_t>(5 * rate);
  test.time_s.assign(test_full.time_s.begin() + cut, test_full.time_s.end());
  io::AxisSeries& tx = test.add_axis("c");
  const io::AxisSeries& fx = test_full.axis("c");
  tx.voltage_v.assign(fx.voltage_v.begin() + cut, fx.voltage_v.end());
  tx.position_nm.assign(fx.position_nm.begin() + cut, fx.position_nm.end());
  tx.true_position_nm.assign(fx.true_position_nm.begin() + cut, fx.true_position_nm.end());
  const auto [mn, mx] = std::minmax_element(tx.true_position_nm.begin(), tx.true_position_nm.end());
  const double range = *mx - *mn;

  io::Dataset train, val;
  const std::size_t n_train = static_cast<std::size_t>(32 * rate);
  for (auto* part : {&train, &val}) part->add_axis("c");
  const io::AxisSeries& ax = all.axis("c");
  for (std::size_t t = 0; t < ax.voltage_v.size(); ++t) {
    io::Dataset& dst = t < n_train ? train : val;
    dst.time_s.push_back(all.time_s[t]);
    dst.axis("c").voltage_v.push_back(ax.voltage_v[t]);
    dst.axis("c").position_nm.push_back(ax.position_nm[t]);
  }
  const auto [pmn, pmx] = std::minmax_element(ax.position_nm.begin(), ax.position_nm.end());
  for (const char* kind : {"pi", "pi_creep_log", "pi_creep_lti", "pi_creep_fractional", "pi_creep_prony"}) {
    models::FitRequest req;
    req.train = &train;
    req.validation = &val;
    auto m = models::model_kind(kind).fit(req);
    const auto& pm = dynamic_cast<const PiCreepModel&>(*m);
    EXPECT_LT(std::abs(pm.bias_nm()), 2 * (std::abs(*pmn) + std::abs(*pmx))) << kind;
    double sum_w = 0;
    for (double w : pm.weights()) sum_w += w;
    // Σw·span is the hysteretic travel: within a few times the measured travel.
    EXPECT_LT(sum_w * 3.6, 3 * (*pmx - *pmn)) << kind;
    for (double tau : pm.mode_taus_s()) {
      EXPECT_GE(tau, 2.0 / rate * 0.999) << kind;
      EXPECT_LE(tau, 32.0 * 1.001) << kind;
    }
    auto run = m->clone();
    run->reset(tx.voltage_v[0], tx.position_nm[0]);
    double sum = 0, worst = 0;
    std::size_t n = 0;
    for (std::size_t t = 0; t < tx.voltage_v.size(); ++t) {
      models::ModelInput in{tx.voltage_v[t], nullptr};
      const double y = run->predict(in);
      run->commit(in, y);
      if (t < static_cast<std::size_t>(rate)) continue;  // the first second belongs to the unknown state
      const double e = std::abs(y - tx.true_position_nm[t]);
      sum += e, ++n, worst = std::max(worst, e);
    }
    std::cout << kind << ": free-run MAE " << 100 * sum / n / range << " % of range, max " << 100 * worst / range
              << " %\n";
    EXPECT_LT(sum / n, 0.05 * range) << kind;
  }
}

TEST(PronyCreep, ModelFileRoundTripsAndBoundsItsSizes) {
  models::CreepParams cp;
  cp.kind = models::CreepKind::kProny;
  cp.tau_min_s = 0.2, cp.tau_max_s = 2000, cp.modes_per_decade = 2;
  cp.gains_nm_per_v.assign(cp.num_coefficients(), 0.0);
  for (std::size_t j = 0; j < cp.gains_nm_per_v.size(); ++j) cp.gains_nm_per_v[j] = 0.01 * (j + 1);
  PiCreepModel m({0, 10, 20}, {5, 1, 0.5}, 3.0, cp, 11.0);
  YAML::Emitter em;
  em << models::model_to_file_yaml(m);
  const std::string text = em.c_str();
  auto from_string = [](const std::string& t) { return models::model_from_file_yaml(YAML::Load(t), "test"); };
  auto back = from_string(text);
  ASSERT_EQ(back->kind(), "pi_creep_prony");
  const auto& b = dynamic_cast<const PiCreepModel&>(*back);
  EXPECT_EQ(b.mode_taus_s(), m.mode_taus_s());
  EXPECT_EQ(b.mode_gains(), m.mode_gains());
  auto load_error = [&](const std::string& from, const std::string& to) {
    std::string t = text;
    const auto at = t.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    t.replace(at, from.size(), to);
    try {
      from_string(t);
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("loaded");
  };
  EXPECT_NE(load_error("modes_per_decade: 2", "modes_per_decade: 500").find("modes_per_decade"), std::string::npos);
  EXPECT_NE(load_error("tau_max_s: 2000", "tau_max_s: 1e30").find("decades"), std::string::npos);
  EXPECT_NE(load_error("tau_max_s: 2000", "tau_max_s: 20000").find("mode_gains"), std::string::npos);
}
