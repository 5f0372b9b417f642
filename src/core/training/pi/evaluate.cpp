#include "evaluate.h"

#include <algorithm>
#include <cmath>

namespace piezo::training::pi {

using models::CreepParams;

namespace {

// Where a fractional search being kept stores every row's mode states (null: not stored, or not fractional).
double* kept_modes(ModeSearchRows* s, std::size_t N, std::size_t nm) {
  if (!s || !s->fractional) return nullptr;
  s->modes.resize(N * nm);
  return s->modes.data();
}

// reuse_gram of a kept search: LTI mode j filtered from u0 over the input U (and its initial-state column, when kept
// with one); fractional: the creep column Σ_j B_j·l_j from the kept mode states.
GramStats reuse_search_gram(ModeSearchRows& s, const CreepBasis& cb, const std::vector<double>& U, double u0,
                            const std::vector<double>* weight, std::size_t P) {
  const std::size_t N = U.size();
  if (s.fractional) {
    const std::vector<double>& B = cb.B[0];
    const std::size_t nm = B.size();
    return reuse_gram(s, N, 1, weight, P, [&](std::size_t t, double sw, double* out) {
      const double* l = s.modes.data() + t * nm;
      double c = 0;
      for (std::size_t j = 0; j < nm; ++j) c += B[j] * l[j];
      out[0] = c * sw;
    });
  }
  const double a = cb.poles[s.j];
  const bool init = s.slow[s.j] != 0;
  double l = u0, e = a;
  return reuse_gram(s, N, init ? 2 : 1, weight, P, [&](std::size_t t, double sw, double* out) {
    l = a * l + (1 - a) * U[t];
    out[0] = l * sw;
    if (init) {
      out[1] = e * sw;
      e = e < 1e-100 ? 0.0 : e * a;
    }
  });
}

// Play pieces (≥ their lower bounds, smoothed) then nk creep columns (then initial-state columns): w and θ.
EvalResult solve_pieces_and_creep(const training::GramStats& g, const Basis& hb, std::size_t nk, const CreepParams& cp,
                                  double min_w0) {
  const std::size_t np = hb.pieces();
  std::vector<bool> constrained(np + nk, signed_creep(cp));
  for (std::size_t i = 0; i < np; ++i) constrained[i] = true;
  EvalResult res = solve(g, constrained, hb.lower(min_w0), hb.neighbours(), hb.smoothing);
  res.w.assign(res.theta.begin(), res.theta.begin() + np);
  res.theta.erase(res.theta.begin(), res.theta.begin() + np);
  return res;
}

// One sample of every piece's creep filters: l_ji ← a_j·l_ji + (1 − a_j)·f_i, x_i = f_i + Σ_j g_j·l_ji (modes in
// order j = 0, 1, …; the pieces are independent, so the inner loop vectorises). An AVX2 clone runs where the CPU has
// it: the same IEEE operations per element as the SSE2 default (no FMA), so the same results, twice as wide.
__attribute__((target_clones("avx2", "default"))) void filter_pieces(
    std::size_t np, std::size_t nm, const double* __restrict f, const double* __restrict a,
    const double* __restrict one_minus_a, const double* __restrict g, double* __restrict l, double* __restrict x) {
  for (std::size_t i = 0; i < np; ++i) x[i] = f[i];
  for (std::size_t j = 0; j < nm; ++j) {
    double* __restrict lj = l + j * np;
    const double aj = a[j], bj = one_minus_a[j], gj = g[j];
    for (std::size_t i = 0; i < np; ++i) {
      lj[i] = aj * lj[i] + bj * f[i];
      x[i] += gj * lj[i];
    }
  }
}

}  // namespace

EvalResult evaluate(const FitData& d, const Basis& hb, const CreepParams& cp, double min_w0, StaticGram* fixed,
                    ModeSearchRows* search) {
  const CreepBasis cb(cp, d.rate);
  const std::size_t np = hb.pieces(), nm = cb.taus.size(), nk = cb.B.size();
  const std::vector<double>& V = *d.v;
  const std::vector<double> init = init_poles(cb.taus, d);
  const SearchStep step = search_step(search, cp, cb.taus, d, np + nk + init.size() + 2);
  if (step == SearchStep::kReuse) {
    const auto g = reuse_search_gram(*search, cb, V, V[0], d.weight, np + nk + init.size());
    return solve_pieces_and_creep(g, hb, nk, cp, min_w0);
  }
  ModeSearchRows* keep = step == SearchStep::kKeep ? search : nullptr;
  std::vector<double> p(hb.r.size(), V[0]), l(nm, V[0]);
  double* keep_modes = kept_modes(keep, V.size(), nm);
  const auto g = stream_gram(V.size(), np + nk, [&](std::size_t t, double* x) {
    const double v = V[t];
    hb.columns(v, p, x);
    creep_columns(cb, l, v, x + np);
    if (keep_modes) std::copy(l.begin(), l.end(), keep_modes + t * nm);
    return (*d.y)[t];
  }, init, d.weight, fixed, keep, varying_columns(keep, cb.taus, d, np + nk, np));
  return solve_pieces_and_creep(g, hb, nk, cp, min_w0);
}

std::vector<double> hysteresis_series(const FitData& d, const Basis& hb, const std::vector<double>& w) {
  const std::size_t np = hb.pieces();
  const std::vector<double>& V = *d.v;
  std::vector<double> p(hb.r.size(), V[0]), f(np), h(V.size());
  for (std::size_t t = 0; t < V.size(); ++t) {
    hb.columns(V[t], p, f.data());
    double s = 0;
    for (std::size_t i = 0; i < np; ++i) s += w[i] * f[i];
    h[t] = s;
  }
  return h;
}

EvalResult evaluate_creep_on_h(const FitData& d, const std::vector<double>& H, const std::vector<double>& w,
                               const CreepParams& cp, ModeSearchRows* search) {
  const CreepBasis cb(cp, d.rate);
  const std::size_t nm = cb.taus.size(), nk = cb.B.size();
  const std::vector<double> init = init_poles(cb.taus, d);
  const SearchStep step = H.empty() ? SearchStep::kFull : search_step(search, cp, cb.taus, d, nk + 1 + init.size() + 2);
  // The modes start at rest at the H of the first sample's play states (every play at V[0]).
  const double h0 = H.empty() ? 0.0 : H[0];
  std::vector<double> l(nm, h0);
  ModeSearchRows* keep = step == SearchStep::kKeep ? search : nullptr;
  double* keep_modes = kept_modes(keep, H.size(), nm);
  const auto g = step == SearchStep::kReuse
                     ? reuse_search_gram(*search, cb, H, h0, d.weight, nk + 1 + init.size())
                     : stream_gram(H.size(), nk + 1, [&](std::size_t t, double* x) {
                         const double h = H[t];
                         x[0] = h;
                         creep_columns(cb, l, h, x + 1);
                         if (keep_modes) std::copy(l.begin(), l.end(), keep_modes + t * nm);
                         return (*d.y)[t];
                       }, init, d.weight, nullptr, keep, varying_columns(keep, cb.taus, d, nk + 1, 1));
  std::vector<bool> constrained(nk + 1, signed_creep(cp));
  constrained[0] = false;
  EvalResult res = solve(g, constrained);
  const double scale = res.theta[0] > 1e-6 ? res.theta[0] : 1.0;  // a non-positive scale would break invertibility
  res.w = w;
  for (double& x : res.w) x *= scale;
  res.theta.erase(res.theta.begin());
  for (double& x : res.theta) x /= scale;
  return res;
}

EvalResult evaluate_joint_on_h(const FitData& d, const Basis& hb, const std::vector<double>& w_prev,
                               const CreepParams& cp, double min_w0) {
  const CreepBasis cb(cp, d.rate);
  const std::size_t np = hb.pieces(), nm = cb.taus.size(), nk = cb.B.size();
  const std::vector<double>& V = *d.v;
  std::vector<double> p(hb.r.size(), V[0]);
  std::vector<double> f(np);
  hb.columns(V[0], p, f.data());
  double h0 = 0;
  for (std::size_t i = 0; i < np; ++i) h0 += w_prev[i] * f[i];
  std::vector<double> l(nm, h0);
  p.assign(hb.r.size(), V[0]);
  const auto g = stream_gram(V.size(), np + nk, [&](std::size_t t, double* x) {
    hb.columns(V[t], p, x);
    double h = 0;
    for (std::size_t i = 0; i < np; ++i) h += w_prev[i] * x[i];
    creep_columns(cb, l, h, x + np);
    for (std::size_t k = 0; k < nk; ++k) {
      double bk = 0;
      for (std::size_t j = 0; j < nm; ++j) bk += cb.B[k][j];
      x[np + k] -= bk * h;
    }
    return (*d.y)[t];
  }, init_poles(cb.taus, d), d.weight);
  return solve_pieces_and_creep(g, hb, nk, cp, min_w0);
}

EvalResult evaluate_w_given_creep_on_h(const FitData& d, const Basis& hb, const CreepParams& cp, double min_w0) {
  std::vector<double> taus, gains;
  cp.modes(taus, gains);
  const std::size_t np = hb.pieces(), nm = taus.size();
  const std::vector<double> a = poles_of(taus, d.rate);
  const std::vector<double>& V = *d.v;
  std::vector<double> p(hb.r.size(), V[0]), f(np);
  hb.columns(V[0], p, f.data());
  // Mode-major states (l[j·np + i]) and the loop over pieces innermost: each piece's sum still adds the modes in
  // order j = 0, 1, …, but the pieces are independent, so the loop vectorises (np × nm filters a sample, a
  // thousand or more on the Preisach kinds).
  std::vector<double> l(np * nm), one_minus_a(nm);
  for (std::size_t j = 0; j < nm; ++j) {
    one_minus_a[j] = 1 - a[j];
    std::copy(f.begin(), f.end(), l.begin() + static_cast<std::ptrdiff_t>(j * np));
  }
  p.assign(hb.r.size(), V[0]);
  const auto g = stream_gram(V.size(), np, [&](std::size_t t, double* x) {
    hb.columns(V[t], p, f.data());
    filter_pieces(np, nm, f.data(), a.data(), one_minus_a.data(), gains.data(), l.data(), x);
    return (*d.y)[t];
  }, init_poles(taus, d), d.weight);
  EvalResult res = solve(g, std::vector<bool>(np, true), hb.lower(min_w0), hb.neighbours(), hb.smoothing);
  res.w = res.theta;
  res.theta.clear();
  return res;
}

}  // namespace piezo::training::pi
