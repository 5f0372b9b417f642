// Fitting of kind "pi_creep_play" (models/pi_creep_play_model.h).
#include "piezo_compensation/training/fit_pi_creep_play.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "piezo_compensation/features/play_operator.h"
#include "piezo_compensation/models/creep_models.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_creep_play_model.h"
#include "piezo_compensation/models/yaml_fields.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::training {

namespace {

constexpr double kPlayMaxTauS = 1e5;
// The memory-free play's share of the total step slope, at least: keeps the model strictly increasing in V.
constexpr double kPlayMinLinearShare = 1e-3;
constexpr double kPlayDefaultMoveWeight = 4.0;

struct PlayLayout {
  std::vector<double> r, taus, a;
  std::size_t recordings = 1;
  bool bends = true;
  std::vector<double> lo, hi;  // the bends' ranges: each play's training range
  std::vector<std::size_t> horizons;  // the move horizons [samples]
  double move_weight = 0;
  std::size_t n() const { return r.size(); }
  std::size_t J() const { return taus.size(); }
  std::size_t bend_columns() const { return bends ? 2 * n() : 0; }
  std::size_t lowpass0() const { return n() + bend_columns(); }
  std::size_t constrained() const { return lowpass0() + n() * J(); }  // plays, bends and low-passes: ≥ 0
  std::size_t size() const { return constrained() + recordings; }
};

struct PlayGram {
  Eigen::MatrixXd G;
  Eigen::VectorXd c;
  std::vector<double> rows;  // per recording
};

// Writes the basis of one row into x: plays, bends, low-passes (advanced by this row) and the recording's
// intercept.
void play_row(const PlayLayout& L, double v, std::size_t k, std::vector<double>& p, std::vector<double>& l,
              double* x) {
  const std::size_t n = L.n(), J = L.J(), l0 = L.lowpass0();
  std::fill(x, x + L.size(), 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    const double q = features::play(v, L.r[i], p[i]);
    p[i] = q;
    x[i] = q;
    if (L.bends) {
      x[n + 2 * i] = models::play_bend_convex(q, L.lo[i], L.hi[i]);
      x[n + 2 * i + 1] = models::play_bend_concave(q, L.lo[i], L.hi[i]);
    }
    for (std::size_t j = 0; j < J; ++j) {
      double& s = l[i * J + j];
      s = L.a[j] * s + (1.0 - L.a[j]) * q;
      x[l0 + i * J + j] = s;
    }
  }
  x[L.constrained() + k] = 1.0;
}

// Each play's range over the training recordings (each from its own rest), the bends' [lo, hi].
void play_ranges(const io::Dataset& data, const std::string& axis, PlayLayout& L) {
  const io::AxisSeries& ax = data.axis(axis);
  L.lo.assign(L.n(), INFINITY);
  L.hi.assign(L.n(), -INFINITY);
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [b, e] = data.recording_rows(k);
    std::vector<double> p(L.n(), ax.voltage_v[b]);
    for (std::size_t t = b; t < e; ++t)
      for (std::size_t i = 0; i < L.n(); ++i) {
        p[i] = features::play(ax.voltage_v[t], L.r[i], p[i]);
        L.lo[i] = std::min(L.lo[i], p[i]);
        L.hi[i] = std::max(L.hi[i], p[i]);
      }
  }
  for (std::size_t i = 0; i < L.n(); ++i)
    L.hi[i] = std::max(L.hi[i], L.lo[i] + 1e-3);  // a play that never moved
}

// The Gram sums of the levels (each recording with its own intercept) plus move_weight × those of the changes over
// each move horizon (the intercepts cancel there), each recording streamed from its own rest.
PlayGram play_gram(const io::Dataset& data, const std::string& axis, const PlayLayout& L) {
  const io::AxisSeries& ax = data.axis(axis);
  const Eigen::Index P = static_cast<Eigen::Index>(L.size());
  PlayGram g{Eigen::MatrixXd::Zero(P, P), Eigen::VectorXd::Zero(P), {}};
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [b, e] = data.recording_rows(k);
    const Eigen::Index N = static_cast<Eigen::Index>(e - b);
    g.rows.push_back(static_cast<double>(N));
    Eigen::MatrixXd X(P, N);
    Eigen::VectorXd y(N);
    std::vector<double> p(L.n(), ax.voltage_v[b]), l(L.n() * L.J(), ax.voltage_v[b]);
    for (std::size_t t = b; t < e; ++t) {
      play_row(L, ax.voltage_v[t], k, p, l, X.col(static_cast<Eigen::Index>(t - b)).data());
      y(static_cast<Eigen::Index>(t - b)) = ax.position_nm[t];
    }
    g.G.selfadjointView<Eigen::Lower>().rankUpdate(X);
    g.c.noalias() += X * y;
    for (std::size_t h : L.horizons) {
      const Eigen::Index H = static_cast<Eigen::Index>(h);
      if (H >= N) continue;
      const Eigen::MatrixXd D = X.rightCols(N - H) - X.leftCols(N - H);
      g.G.selfadjointView<Eigen::Lower>().rankUpdate(D, L.move_weight);
      g.c.noalias() += L.move_weight * (D * (y.tail(N - H) - y.head(N - H)));
    }
  }
  g.G = g.G.selfadjointView<Eigen::Lower>();
  return g;
}

// NNLS on the plays and low-passes, with x_0 ≥ lower_w0.
Eigen::VectorXd play_solve(const PlayGram& g, const PlayLayout& L, double lower_w0) {
  std::vector<bool> constrained(L.size(), false);
  std::fill(constrained.begin(), constrained.begin() + static_cast<std::ptrdiff_t>(L.constrained()), true);
  Eigen::VectorXd c = g.c - g.G.col(0) * lower_w0;
  Eigen::VectorXd x = nnls_gram(g.G, c, constrained);
  x(0) += lower_w0;
  return x;
}

double step_slope(const Eigen::VectorXd& x, const PlayLayout& L, std::size_t i) {
  double s = x(static_cast<Eigen::Index>(i));
  for (std::size_t j = 0; j < L.J(); ++j)
    s += x(static_cast<Eigen::Index>(L.lowpass0() + i * L.J() + j)) * (1.0 - L.a[j]);
  return s;
}

PlayLayout play_layout(const FitRequest& req) {
  const io::AxisSeries& ax = req.train->axis(req.axis);
  PlayLayout L;
  const YAML::Node& o = req.options;
  if (o && o["thresholds_v"]) {
    L.r = models::yaml_numbers(o, "thresholds_v", -1, "option");
    if (L.r.empty() || L.r[0] != 0)
      throw std::runtime_error("option 'thresholds_v': expected 0 first, then increasing");
  } else {
    const int n = option_int(o, "n_play", 10);
    if (n < 1 || n > models::kMaxPlayOperators)
      throw std::runtime_error("option 'n_play': expected 1.." + std::to_string(models::kMaxPlayOperators));
    const auto [mn, mx] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
    const double half_range = std::max(1e-6, 0.5 * (*mx - *mn));
    for (int i = 0; i < n; ++i) L.r.push_back(half_range * i / n);
  }
  const double rate = req.train->sample_rate_hz();
  if (o && o["taus_s"]) {
    L.taus = models::yaml_numbers(o, "taus_s", -1, "option");
  } else {  // the defaults the training data can identify: none slower than its duration (the first one always)
    const double duration = req.train->time_s.empty() ? 0.0 : req.train->time_s.back() - req.train->time_s.front();
    for (double t : default_play_creep_taus_s())
      if (L.taus.empty() || t <= duration) L.taus.push_back(t);
  }
  if (L.taus.empty() || L.taus.size() > static_cast<std::size_t>(models::kMaxCreepModes))
    throw std::runtime_error("option 'taus_s': expected 1.." + std::to_string(models::kMaxCreepModes) +
                             " time constants");
  for (double t : L.taus) {
    if (!(t >= 1.0 / rate && t <= kPlayMaxTauS))
      throw std::runtime_error("option 'taus_s': " + std::to_string(t) + " s is outside [1 sample, 1e5 s]");
    L.a.push_back(std::exp(-1.0 / (rate * t)));
  }
  L.bends = option_bool(o, "bends", true);
  L.move_weight = option_num(o, "move_weight", kPlayDefaultMoveWeight);
  if (!(L.move_weight >= 0) || !std::isfinite(L.move_weight))
    throw std::runtime_error("option 'move_weight': expected a number >= 0");
  const std::vector<double> hs =
      o && o["move_horizons_s"] ? models::yaml_numbers(o, "move_horizons_s", -1, "option") : std::vector<double>{10, 60};
  for (double h : hs) {
    if (!(h * rate >= 1)) throw std::runtime_error("option 'move_horizons_s': each horizon at least one sample");
    L.horizons.push_back(static_cast<std::size_t>(std::lround(h * rate)));
  }
  L.recordings = req.train->recording_count();
  if (L.bends) play_ranges(*req.train, req.axis, L);
  return L;
}

}  // namespace

std::vector<double> default_play_creep_taus_s() { return {1, 5, 20, 60, 200, 600, 2000}; }

models::ModelPtr fit_pi_creep_play(const FitRequest& req) {
  if (!req.train) throw std::runtime_error("pi_creep_play fit: no training data");
  const io::AxisSeries& ax = req.train->axis(req.axis);
  if (ax.voltage_v.size() < 10) throw std::runtime_error("pi_creep_play fit: need at least 10 samples");
  const PlayLayout L = play_layout(req);
  const PlayGram g = play_gram(*req.train, req.axis, L);
  Eigen::VectorXd x = play_solve(g, L, 0.0);
  double total = 0;
  for (std::size_t i = 0; i < L.n(); ++i) total += step_slope(x, L, i);
  if (!(total > 0))
    throw std::runtime_error("pi_creep_play fit: the position does not rise with the voltage");
  if (step_slope(x, L, 0) < kPlayMinLinearShare * total) x = play_solve(g, L, kPlayMinLinearShare * total);
  const std::size_t n = L.n(), J = L.J();
  std::vector<double> w(x.data(), x.data() + n), gains(x.data() + L.lowpass0(), x.data() + L.constrained());
  models::PlayBends bends;
  if (L.bends) {
    bends.lo_v = L.lo, bends.hi_v = L.hi;
    for (std::size_t i = 0; i < n; ++i) {
      bends.convex_nm_per_v.push_back(x(static_cast<Eigen::Index>(n + 2 * i)));
      bends.concave_nm_per_v.push_back(x(static_cast<Eigen::Index>(n + 2 * i + 1)));
    }
  }
  double bias = 0, rows = 0;
  for (std::size_t k = 0; k < L.recordings; ++k) {
    bias += g.rows[k] * x(static_cast<Eigen::Index>(L.constrained() + k));
    rows += g.rows[k];
  }
  auto m = std::make_unique<models::PiCreepPlayModel>(L.r, w, L.taus, gains, bias / rows,
                                                      req.train->sample_rate_hz(), bends);
  m->meta = make_meta(req);
  m->meta.validation["fit_play_operators"] = static_cast<double>(n);
  m->meta.validation["fit_creep_time_constants"] = static_cast<double>(J);
  if (req.validation && req.validation->has_axis(req.axis) && req.validation->size() > 0) {
    const auto pred = models::free_run_prediction(*m, *req.validation, req.axis);
    const auto off = models::recording_offsets(*req.validation, req.axis, pred);
    const auto idx = req.validation->recording_index();
    const auto& y = req.validation->axis(req.axis).position_nm;
    double s = 0;
    for (std::size_t i = 0; i < pred.size(); ++i) s += std::abs(y[i] - pred[i] - off[idx[i]]);
    m->meta.validation["validation_free_run_mae_nm"] = s / static_cast<double>(pred.size());
  }
  return m;
}

}  // namespace piezo::training
