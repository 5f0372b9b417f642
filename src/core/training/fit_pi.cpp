// Fitting of kinds "pi", "pi_creep_*" (moved from models/pi_model.cpp; the model itself stays in models/).
#include <algorithm>
#include <cmath>
#include <functional>
#include <stdexcept>

#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

namespace {
inline double play(double v, double r, double prev) { return std::max(v - r, std::min(v + r, prev)); }
}  // namespace

Eigen::VectorXd nnls_gram(const Eigen::MatrixXd& G, const Eigen::VectorXd& c, const std::vector<bool>& constrained) {
  const Eigen::Index p = G.rows();
  std::vector<bool> free(p);
  for (Eigen::Index j = 0; j < p; ++j) free[j] = !constrained[j];
  auto solve_free = [&](Eigen::VectorXd& z) {
    std::vector<Eigen::Index> idx;
    for (Eigen::Index j = 0; j < p; ++j)
      if (free[j]) idx.push_back(j);
    z = Eigen::VectorXd::Zero(p);
    if (idx.empty()) return;
    Eigen::MatrixXd A(idx.size(), idx.size());
    Eigen::VectorXd b(idx.size());
    for (std::size_t a = 0; a < idx.size(); ++a) {
      b(a) = c(idx[a]);
      for (std::size_t d = 0; d < idx.size(); ++d) A(a, d) = G(idx[a], idx[d]);
    }
    const Eigen::VectorXd s = training::solve_normal(A, b, 1e-12 * A.diagonal().cwiseAbs().maxCoeff());
    for (std::size_t a = 0; a < idx.size(); ++a) z(idx[a]) = s(a);
  };
  Eigen::VectorXd x;
  solve_free(x);
  // Start feasible: unconstrained ones solved, constrained at 0.
  const double tol = 1e-10 * (1 + c.cwiseAbs().maxCoeff());
  for (int outer = 0; outer < 10 * p + 10; ++outer) {
    const Eigen::VectorXd grad = c - G * x;
    Eigen::Index best = -1;
    double best_g = tol;
    for (Eigen::Index j = 0; j < p; ++j)
      if (!free[j] && grad(j) > best_g) best_g = grad(j), best = j;
    if (best < 0) break;
    free[best] = true;
    for (int inner = 0; inner < 10 * p + 10; ++inner) {
      Eigen::VectorXd z;
      solve_free(z);
      double step = 1.0;
      bool ok = true;
      for (Eigen::Index j = 0; j < p; ++j)
        if (constrained[j] && free[j] && z(j) <= 0) {
          ok = false;
          const double den = x(j) - z(j);
          if (den > 0) step = std::min(step, x(j) / den);
        }
      if (ok) {
        x = z;
        break;
      }
      x += step * (z - x);
      for (Eigen::Index j = 0; j < p; ++j)
        if (constrained[j] && free[j] && x(j) <= 1e-15) {
          free[j] = false;
          x(j) = 0;
        }
    }
  }
  return x;
}

namespace {

struct FitData {
  const std::vector<double>* v;
  const std::vector<double>* y;
  double rate;
  bool initial_state_terms = true;
};

struct EvalResult {
  double sse = INFINITY;
  std::vector<double> w, theta;
  double b = 0;
};

// Gram sums of rows produced one sample at a time: row(t, x) fills x (P values) and returns the target.
// Extra columns a_j^(t+1) for the poles in `init` absorb the unknown initial state of slow modes: a recording
// never starts from the rest the model's reset assumes, and without them the first hours bias the creep fit.
training::GramStats stream_gram(std::size_t N, std::size_t P0, const std::function<double(std::size_t, double*)>& row,
                                const std::vector<double>& init = {}) {
  const std::size_t P = P0 + init.size();
  std::vector<double> e(init);
  training::GramStats g(P);
  constexpr std::size_t kChunk = 2048;
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> X(kChunk, P);
  Eigen::VectorXd yc(kChunk);
  std::size_t fill = 0;
  auto flush = [&]() {
    if (!fill) return;
    auto Xc = X.topRows(fill);
    auto yy = yc.head(fill);
    g.n += double(fill);
    g.sy += yy.sum();
    g.syy += yy.squaredNorm();
    g.sx += Xc.colwise().sum().transpose();
    g.sxy.noalias() += Xc.transpose() * yy;
    g.sxx.selfadjointView<Eigen::Lower>().rankUpdate(Xc.transpose());
    fill = 0;
  };
  for (std::size_t t = 0; t < N; ++t) {
    double* x = X.row(fill).data();
    yc(fill) = row(t, x);
    for (std::size_t j = 0; j < e.size(); ++j) {
      x[P0 + j] = e[j];
      e[j] *= init[j];
    }
    if (++fill == kChunk) flush();
  }
  flush();
  g.sxx = g.sxx.selfadjointView<Eigen::Lower>();
  return g;
}

// Least squares on the Gram sums; columns flagged constrained stay ≥ 0, column 0 ≥ min_w0 when constrained.
EvalResult solve(const training::GramStats& g, std::vector<bool> constrained, double min_w0) {
  const std::size_t used = constrained.size();
  constrained.resize(static_cast<std::size_t>(g.sx.size()), false);  // initial-state columns are free
  Eigen::MatrixXd G = g.centered_xx();
  Eigen::VectorXd c = g.centered_xy();
  const double shift = constrained[0] ? min_w0 : 0.0;
  c -= shift * G.col(0);  // w_0 = min_w0 + w_0' with w_0' ≥ 0 keeps the inverse well defined
  Eigen::VectorXd x = nnls_gram(G, c, constrained);
  x(0) += shift;
  EvalResult res;
  res.b = g.mean_y() - g.mean_x().dot(x);
  res.sse = g.sse(x, res.b);
  res.theta.assign(x.data(), x.data() + used);  // caller splits; initial-state terms are dropped
  return res;
}

std::vector<double> poles_of(const std::vector<double>& taus, double rate) {
  std::vector<double> a;
  for (double t : taus) a.push_back(std::exp(-1.0 / (rate * t)));
  return a;
}

// Poles of the modes whose initial state is worth estimating: slower than 10 s, and faster than a third of the
// record (slower ones are indistinguishable from the bias there).
std::vector<double> init_poles(const std::vector<double>& taus, const FitData& d) {
  std::vector<double> out;
  if (!d.initial_state_terms) return out;
  const double span_s = d.v->size() / d.rate;
  for (double t : taus)
    if (t >= 10.0 && t <= span_s / 3) out.push_back(std::exp(-1.0 / (d.rate * t)));
  return out;
}

// Creep on the voltage: play outputs and creep basis columns, all weights at once (play weights ≥ 0).
EvalResult evaluate(const FitData& d, const std::vector<double>& r, const CreepParams& cp, double min_w0) {
  std::vector<double> taus;
  std::vector<std::vector<double>> B;
  cp.basis(taus, B);
  const std::size_t np = r.size(), nm = taus.size(), nk = B.size();
  const std::vector<double> a = poles_of(taus, d.rate);
  const std::vector<double>& V = *d.v;
  std::vector<double> p(np, V[0]), l(nm, V[0]);
  const auto g = stream_gram(V.size(), np + nk, [&](std::size_t t, double* x) {
    const double v = V[t];
    for (std::size_t i = 0; i < np; ++i) x[i] = p[i] = play(v, r[i], p[i]);
    for (std::size_t j = 0; j < nm; ++j) l[j] = a[j] * l[j] + (1 - a[j]) * v;
    for (std::size_t k = 0; k < nk; ++k) {
      double s = 0;
      for (std::size_t j = 0; j < nm; ++j) s += B[k][j] * l[j];
      x[np + k] = s;
    }
    return (*d.y)[t];
  }, init_poles(taus, d));
  std::vector<bool> constrained(np + nk, false);
  for (std::size_t i = 0; i < np; ++i) constrained[i] = true;
  EvalResult res = solve(g, constrained, min_w0);
  res.w.assign(res.theta.begin(), res.theta.begin() + np);
  res.theta.erase(res.theta.begin(), res.theta.begin() + np);
  return res;
}

// Creep on H with the play weights fixed up to a common scale: y = b + s·H + Σ_k θ_k·(basis of LP_j(H)).
// The free scale s lets the alternation move along the valley where a larger H and a smaller fast-creep gain
// explain the data almost equally well. Returns w·s and θ/s (gains relative to the rescaled H).
EvalResult evaluate_creep_on_h(const FitData& d, const std::vector<double>& r, const std::vector<double>& w,
                               const CreepParams& cp) {
  std::vector<double> taus;
  std::vector<std::vector<double>> B;
  cp.basis(taus, B);
  const std::size_t np = r.size(), nm = taus.size(), nk = B.size();
  const std::vector<double> a = poles_of(taus, d.rate);
  const std::vector<double>& V = *d.v;
  std::vector<double> p(np, V[0]);
  double h0 = 0;
  for (double wi : w) h0 += wi * V[0];
  std::vector<double> l(nm, h0);
  const auto g = stream_gram(V.size(), nk + 1, [&](std::size_t t, double* x) {
    double h = 0;
    for (std::size_t i = 0; i < np; ++i) h += w[i] * (p[i] = play(V[t], r[i], p[i]));
    for (std::size_t j = 0; j < nm; ++j) l[j] = a[j] * l[j] + (1 - a[j]) * h;
    x[0] = h;
    for (std::size_t k = 0; k < nk; ++k) {
      double s = 0;
      for (std::size_t j = 0; j < nm; ++j) s += B[k][j] * l[j];
      x[1 + k] = s;
    }
    return (*d.y)[t];
  }, init_poles(taus, d));
  EvalResult res = solve(g, std::vector<bool>(nk + 1, false), 0.0);
  const double scale = res.theta[0] > 1e-6 ? res.theta[0] : 1.0;  // a non-positive scale would break invertibility
  res.w = w;
  for (double& x : res.w) x *= scale;
  res.theta.erase(res.theta.begin());
  for (double& x : res.theta) x /= scale;
  return res;
}

// Creep on H with the creep gains fixed: y = b + Σ_i w_i·(F_i + Σ_j g_j·LP_j(F_i)), play weights ≥ 0.
EvalResult evaluate_w_given_creep_on_h(const FitData& d, const std::vector<double>& r, const CreepParams& cp,
                                       double min_w0) {
  std::vector<double> taus, gains;
  cp.modes(taus, gains);
  const std::size_t np = r.size(), nm = taus.size();
  const std::vector<double> a = poles_of(taus, d.rate);
  const std::vector<double>& V = *d.v;
  std::vector<double> p(np, V[0]), l(np * nm, V[0]);
  const auto g = stream_gram(V.size(), np, [&](std::size_t t, double* x) {
    for (std::size_t i = 0; i < np; ++i) {
      p[i] = play(V[t], r[i], p[i]);
      double s = p[i];
      for (std::size_t j = 0; j < nm; ++j) {
        double& lj = l[i * nm + j];
        lj = a[j] * lj + (1 - a[j]) * p[i];
        s += gains[j] * lj;
      }
      x[i] = s;
    }
    return (*d.y)[t];
  }, init_poles(taus, d));
  EvalResult res = solve(g, std::vector<bool>(np, true), min_w0);
  res.w = res.theta;
  res.theta.clear();
  return res;
}

// Golden-section minimisation of f on [lo, hi].
template <class F>
double golden(F&& f, double lo, double hi, int iters) {
  const double g = (std::sqrt(5.0) - 1) / 2;
  double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo);
  double f1 = f(x1), f2 = f(x2);
  for (int i = 0; i < iters; ++i) {
    if (f1 < f2) {
      hi = x2, x2 = x1, f2 = f1;
      x1 = hi - g * (hi - lo);
      f1 = f(x1);
    } else {
      lo = x1, x1 = x2, f1 = f2;
      x2 = lo + g * (hi - lo);
      f2 = f(x2);
    }
  }
  return f1 < f2 ? x1 : x2;
}

// Grid then golden refinement of a 1-D parameter.
template <class F>
double search_1d(F&& f, double lo, double hi, int grid, int iters) {
  double best = lo, best_f = INFINITY;
  const double step = (hi - lo) / (grid - 1);
  for (int i = 0; i < grid; ++i) {
    const double x = lo + step * i;
    const double v = f(x);
    if (v < best_f) best_f = v, best = x;
  }
  return golden(f, std::max(lo, best - step), std::min(hi, best + step), iters);
}

}  // namespace

namespace {
double cp_pairs_hint(const YAML::Node& o) {
  if (o && o["taus_s"] && o["taus_s"].IsSequence()) return double(o["taus_s"].size());
  return double(training::option_int(o, "n_pairs", 2));
}
}  // namespace

models::ModelPtr fit_pi_creep(const FitRequest& req, models::CreepKind kind) {
  using namespace training;
  if (!req.train) throw std::runtime_error("PI fit: no training data");
  const io::AxisSeries& ax = req.train->axis(req.axis);
  if (ax.voltage_v.size() < 10) throw std::runtime_error("PI fit: need at least 10 samples");
  FitData d{&ax.voltage_v, &ax.position_nm, req.train->sample_rate_hz()};
  const YAML::Node& o = req.options;
  d.initial_state_terms = option_str(o, "initial_state_terms", "true") != "false";

  std::vector<double> r;
  if (o && o["thresholds_v"]) {
    r = yaml_numbers(o, "thresholds_v");
  } else {
    const int n = option_int(o, "n_play", 12);
    if (n < 1 || n > 200) throw std::runtime_error("option 'n_play': expected 1..200");
    const auto [mn, mx] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
    const double half_range = std::max(1e-6, 0.5 * (*mx - *mn));
    for (int i = 0; i < n; ++i) r.push_back(half_range * i / n);
  }
  // Smallest allowed initial slope: a fraction of the overall voltage→position slope.
  double min_w0 = 0;
  {
    double mv = 0, my = 0;
    const std::size_t N = ax.voltage_v.size();
    for (std::size_t t = 0; t < N; ++t) mv += ax.voltage_v[t], my += ax.position_nm[t];
    mv /= N, my /= N;
    double cvy = 0, cvv = 0;
    for (std::size_t t = 0; t < N; ++t) {
      cvy += (ax.voltage_v[t] - mv) * (ax.position_nm[t] - my);
      cvv += (ax.voltage_v[t] - mv) * (ax.voltage_v[t] - mv);
    }
    if (cvv > 0 && cvy > 0) min_w0 = option_num(o, "min_slope_fraction", 0.01) * cvy / cvv;
  }

  CreepParams cp;
  cp.kind = kind;
  cp.decades = option_int(o, "decades", 5);
  cp.modes_per_decade = option_int(o, "modes_per_decade", kind == CreepKind::kFractional ? 2 : 3);
  cp.tau_min_s = option_num(o, "tau_min_s", 1.0);
  cp.tau_max_s = option_num(o, "tau_max_s", 1e5);
  int evals = 0;
  double total = 1;
  auto report = [&](const char* what) {
    ++evals;
    if (req.progress) req.progress(std::min<double>(evals, total), total, what);
  };
  // Searches the law's nonlinear parameters (t1, α or the τ_j) for the least SSE of `sse_fn`.
  const bool fixed = o && (o["t1_s"] || o["alpha"] || (o["taus_s"] && o["fix_taus"]));
  auto search = [&](const std::function<double(const CreepParams&)>& sse_fn, bool refine_only) {
  auto sse_of = [&](const CreepParams& c) {
    report("PI + creep fit");
    return sse_fn(c);
  };
  switch (kind) {
    case CreepKind::kNone: break;
    case CreepKind::kLog:
      if (o && o["t1_s"]) {
        cp.t1_s = option_num(o, "t1_s", 1.0);
      } else {
        const double cur = std::log10(cp.t1_s);
        cp.t1_s = std::pow(10.0, search_1d([&](double lg) { CreepParams c = cp; c.t1_s = std::pow(10.0, lg); return sse_of(c); },
                                           refine_only ? cur - 0.3 : -1.0, refine_only ? cur + 0.3 : 2.5, refine_only ? 5 : 15, 12));
      }
      break;
    case CreepKind::kFractional:
      if (o && o["alpha"]) {
        cp.alpha = option_num(o, "alpha", 0.5);
      } else {
        const double cur = cp.alpha;
        cp.alpha = search_1d([&](double al) { CreepParams c = cp; c.alpha = al; return sse_of(c); },
                             refine_only ? std::max(0.02, cur - 0.1) : 0.03, refine_only ? std::min(0.98, cur + 0.1) : 0.97,
                             refine_only ? 5 : 19, 12);
      }
      break;
    case CreepKind::kLti: {
      if (refine_only) {
      } else if (o && o["taus_s"]) {
        cp.taus_s = yaml_numbers(o, "taus_s");
      } else {
        const int n = option_int(o, "n_pairs", 2);
        if (n < 1 || n > 6) throw std::runtime_error("option 'n_pairs': expected 1..6");
        for (int j = 0; j < n; ++j) cp.taus_s.push_back(std::pow(10.0, 1.0 + 3.0 * (j + 0.5) / n));
      }
      if (cp.gains_nm_per_v.size() != cp.taus_s.size()) cp.gains_nm_per_v.assign(cp.taus_s.size(), 0.0);
      const int rounds = refine_only ? 1 : option_int(o, "search_rounds", 3);
      const double lo = std::log10(2.0 / d.rate), hi = 5.0;
      for (int round = refine_only ? 1 : 0; round < (refine_only ? 2 : rounds) && !(o && o["taus_s"] && o["fix_taus"]); ++round)
        for (std::size_t j = 0; j < cp.taus_s.size(); ++j) {
          auto f = [&](double lg) { CreepParams c = cp; c.taus_s[j] = std::pow(10.0, lg); return sse_of(c); };
          const double cur = std::log10(cp.taus_s[j]);
          // First round scans the whole range; later rounds refine around the current value.
          const double a = round == 0 ? lo : std::max(lo, cur - 0.5), b = round == 0 ? hi : std::min(hi, cur + 0.5);
          cp.taus_s[j] = std::pow(10.0, search_1d(f, a, b, 11, 10));
        }
      std::sort(cp.taus_s.begin(), cp.taus_s.end());
      break;
    }
  }
  };
  (void)fixed;

  const std::string input = option_str(o, "creep_input", "hysteresis");
  if (input != "voltage" && input != "hysteresis")
    throw std::runtime_error("option 'creep_input': expected voltage or hysteresis, got '" + input + "'");
  const int iters = kind == CreepKind::kNone || input == "voltage" ? 0 : option_int(o, "alternations", 6);
  const double per_search = kind == CreepKind::kNone ? 0 : kind == CreepKind::kLti ? 21.0 * cp_pairs_hint(o) : 17;
  total = per_search * (kind == CreepKind::kLti ? 3 : 1.8) + iters * (per_search + 2) + 1;
  // Creep on the voltage: weights and creep coefficients are jointly linear.
  search([&](const CreepParams& c) { return evaluate(d, r, c, min_w0).sse; }, false);
  EvalResult best = evaluate(d, r, cp, min_w0);
  cp.set_coefficients(best.theta);
  if (iters > 0) {
    // Creep on H is bilinear (w and g): alternate the two linear problems, refining the law's nonlinear
    // parameters once, starting from the voltage-input solution.
    cp.on_hysteresis = true;
    std::vector<double> w = best.w;
    // Voltage-input gains are in nm/V; as gains on H they are about (nm/V)/(Σw) nm/nm.
    double sum_w = 0;
    for (double x : w) sum_w += x;
    std::vector<double> theta = best.theta;
    for (double& t : theta) t /= std::max(1e-12, sum_w);
    cp.set_coefficients(theta);
    for (int it = 0; it < iters; ++it) {
      search([&](const CreepParams& c) { return evaluate_creep_on_h(d, r, w, c).sse; }, true);
      EvalResult cr = evaluate_creep_on_h(d, r, w, cp);
      report("PI + creep fit");
      cp.set_coefficients(cr.theta);
      w = cr.w;
      best = evaluate_w_given_creep_on_h(d, r, cp, min_w0);
      report("PI + creep fit");
      w = best.w;
    }
  }
  auto m = std::make_unique<PiCreepModel>(r, best.w, best.b, cp, d.rate);
  m->meta = make_meta(req);
  return m;
}

}  // namespace piezo::training
