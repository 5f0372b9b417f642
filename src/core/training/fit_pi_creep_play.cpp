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
constexpr std::size_t kPlayChunkRows = 256;

struct PlayLayout {
  std::vector<double> r, taus, a;
  std::size_t recordings = 1;
  bool start_terms = true;
  std::size_t n() const { return r.size(); }
  std::size_t J() const { return taus.size(); }
  std::size_t transients() const { return start_terms ? recordings * J() : 0; }
  std::size_t size() const { return n() + n() * J() + transients() + recordings; }
  std::size_t constrained() const { return n() + n() * J(); }  // plays and low-passes: ≥ 0
};

struct PlayGram {
  Eigen::MatrixXd G;
  Eigen::VectorXd c;
  std::vector<double> rows;  // per recording
};

// Writes the basis of one row into x: plays, low-passes (advanced by this row), the recording's start transients
// and its intercept.
void play_row(const PlayLayout& L, double v, std::size_t k, std::size_t t, std::vector<double>& p,
              std::vector<double>& l, double* x) {
  const std::size_t n = L.n(), J = L.J();
  std::fill(x, x + L.size(), 0.0);
  for (std::size_t i = 0; i < n; ++i) {
    const double q = features::play(v, L.r[i], p[i]);
    p[i] = q;
    x[i] = q;
    for (std::size_t j = 0; j < J; ++j) {
      double& s = l[i * J + j];
      s = L.a[j] * s + (1.0 - L.a[j]) * q;
      x[n + i * J + j] = s;
    }
  }
  if (L.start_terms)
    for (std::size_t j = 0; j < J; ++j) x[n + n * J + k * J + j] = std::pow(L.a[j], static_cast<double>(t));
  x[L.size() - L.recordings + k] = 1.0;
}

PlayGram play_gram(const io::Dataset& data, const std::string& axis, const PlayLayout& L) {
  const io::AxisSeries& ax = data.axis(axis);
  const Eigen::Index P = static_cast<Eigen::Index>(L.size());
  PlayGram g{Eigen::MatrixXd::Zero(P, P), Eigen::VectorXd::Zero(P), {}};
  Eigen::MatrixXd X(P, static_cast<Eigen::Index>(kPlayChunkRows));
  Eigen::VectorXd y(static_cast<Eigen::Index>(kPlayChunkRows));
  for (std::size_t k = 0; k < data.recording_count(); ++k) {
    const auto [b, e] = data.recording_rows(k);
    g.rows.push_back(static_cast<double>(e - b));
    std::vector<double> p(L.n(), ax.voltage_v[b]), l(L.n() * L.J(), ax.voltage_v[b]);
    for (std::size_t t0 = b; t0 < e; t0 += kPlayChunkRows) {
      const std::size_t m = std::min(kPlayChunkRows, e - t0);
      for (std::size_t t = t0; t < t0 + m; ++t) {
        play_row(L, ax.voltage_v[t], k, t - b, p, l, X.col(static_cast<Eigen::Index>(t - t0)).data());
        y(static_cast<Eigen::Index>(t - t0)) = ax.position_nm[t];
      }
      const Eigen::Index mi = static_cast<Eigen::Index>(m);
      g.G.selfadjointView<Eigen::Lower>().rankUpdate(X.leftCols(mi));
      g.c.noalias() += X.leftCols(mi) * y.head(mi);
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
  for (std::size_t j = 0; j < L.J(); ++j) s += x(static_cast<Eigen::Index>(L.n() + i * L.J() + j)) * (1.0 - L.a[j]);
  return s;
}

PlayLayout play_layout(const FitRequest& req, const io::AxisSeries& ax) {
  PlayLayout L;
  const YAML::Node& o = req.options;
  if (o && o["thresholds_v"]) {
    L.r = models::yaml_numbers(o, "thresholds_v", -1, "option");
    if (L.r.empty() || L.r[0] != 0) throw std::runtime_error("option 'thresholds_v': expected 0 first, then increasing");
  } else {
    const int n = option_int(o, "n_play", 10);
    if (n < 1 || n > models::kMaxPlayOperators)
      throw std::runtime_error("option 'n_play': expected 1.." + std::to_string(models::kMaxPlayOperators));
    const auto [mn, mx] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
    const double half_range = std::max(1e-6, 0.5 * (*mx - *mn));
    for (int i = 0; i < n; ++i) L.r.push_back(half_range * i / n);
  }
  L.taus = o && o["taus_s"] ? models::yaml_numbers(o, "taus_s", -1, "option") : default_play_creep_taus_s();
  const double rate = req.train->sample_rate_hz();
  if (L.taus.empty() || L.taus.size() > static_cast<std::size_t>(models::kMaxCreepModes))
    throw std::runtime_error("option 'taus_s': expected 1.." + std::to_string(models::kMaxCreepModes) + " time constants");
  for (double t : L.taus) {
    if (!(t >= 1.0 / rate && t <= kPlayMaxTauS))
      throw std::runtime_error("option 'taus_s': " + std::to_string(t) + " s is outside [1 sample, 1e5 s]");
    L.a.push_back(std::exp(-1.0 / (rate * t)));
  }
  L.start_terms = option_bool(o, "start_terms", true);
  L.recordings = req.train->recording_count();
  return L;
}

}  // namespace

std::vector<double> default_play_creep_taus_s() { return {1, 5, 20, 60, 200, 600, 2000}; }

models::ModelPtr fit_pi_creep_play(const FitRequest& req) {
  if (!req.train) throw std::runtime_error("pi_creep_play fit: no training data");
  const io::AxisSeries& ax = req.train->axis(req.axis);
  if (ax.voltage_v.size() < 10) throw std::runtime_error("pi_creep_play fit: need at least 10 samples");
  const PlayLayout L = play_layout(req, ax);
  const PlayGram g = play_gram(*req.train, req.axis, L);
  Eigen::VectorXd x = play_solve(g, L, 0.0);
  double total = 0;
  for (std::size_t i = 0; i < L.n(); ++i) total += step_slope(x, L, i);
  if (!(total > 0)) throw std::runtime_error("pi_creep_play fit: the position does not rise with the voltage");
  if (step_slope(x, L, 0) < kPlayMinLinearShare * total) x = play_solve(g, L, kPlayMinLinearShare * total);
  const std::size_t n = L.n(), J = L.J();
  std::vector<double> w(x.data(), x.data() + n), gains(x.data() + n, x.data() + n + n * J);
  double bias = 0, rows = 0;
  for (std::size_t k = 0; k < L.recordings; ++k) {
    bias += g.rows[k] * x(static_cast<Eigen::Index>(L.size() - L.recordings + k));
    rows += g.rows[k];
  }
  auto m = std::make_unique<models::PiCreepPlayModel>(L.r, w, L.taus, gains, bias / rows, req.train->sample_rate_hz());
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
