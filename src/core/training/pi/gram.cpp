// The PI and Preisach fits' Gram sums: NNLS on normal equations, the SIMD Gram kernels (4×4 tiles in registers,
// AVX2 and default clones giving the same bits), the search caches and the bounded solve.
#include "gram.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "piezo_compensation/training/fitters.h"

namespace piezo::training {

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

namespace pi {

using models::CreepKind;
using models::CreepParams;

namespace {

// The lower-triangle 4×4 tiles of XᵀX over a chunk of `rows` rows, added to A (both row-major with row stride ld,
// a multiple of 4; padding columns are zero). Tiles whose rows all lie before `skip_rows` are left out (their sums
// are kept from an earlier evaluation). Each pair's sum runs over the rows in order, one multiply and one add per
// row, in both clones (AVX2 has no FMA), so every CPU gives the same bits; the 4×4 tile stays in registers, where
// a dot product per pair reloaded both columns for every pair.
using Lanes4 = double __attribute__((vector_size(32)));
__attribute__((target_clones("avx2", "default"))) void chunk_gram(const double* __restrict X, std::size_t rows,
                                                                   std::size_t ld, std::size_t skip_rows,
                                                                   double* __restrict A) {
  for (std::size_t ib = 0; ib < ld; ib += 4) {
    if (ib + 4 <= skip_rows) continue;
    for (std::size_t jb = 0; jb <= ib; jb += 4) {
      Lanes4 t0 = {0, 0, 0, 0}, t1 = t0, t2 = t0, t3 = t0;
      for (std::size_t r = 0; r < rows; ++r) {
        const double* x = X + r * ld;
        Lanes4 xj;
        std::memcpy(&xj, x + jb, sizeof xj);
        t0 += x[ib] * xj, t1 += x[ib + 1] * xj, t2 += x[ib + 2] * xj, t3 += x[ib + 3] * xj;
      }
      const Lanes4* t[4] = {&t0, &t1, &t2, &t3};
      for (std::size_t k = 0; k < 4; ++k) {
        Lanes4 a;
        std::memcpy(&a, A + (ib + k) * ld + jb, sizeof a);
        a += *t[k];
        std::memcpy(A + (ib + k) * ld + jb, &a, sizeof a);
      }
    }
  }
}

// R rows from `i0` of A against M blocks of 4 columns from `jb`, over a chunk: R·M accumulators in registers, each
// summing its pair over the rows in order (the sums chunk_gram forms).
template <int R, int M>
__attribute__((always_inline)) inline void rows_against_blocks(const double* __restrict X, std::size_t rows,
                                                               std::size_t ld, std::size_t i0, std::size_t jb,
                                                               double* __restrict A) {
  Lanes4 t[R][M] = {};
  for (std::size_t r = 0; r < rows; ++r) {
    const double* x = X + r * ld;
    for (int m = 0; m < M; ++m) {
      Lanes4 xj;
      std::memcpy(&xj, x + jb + 4 * m, sizeof xj);
      for (int k = 0; k < R; ++k) t[k][m] += x[i0 + k] * xj;
    }
  }
  for (int k = 0; k < R; ++k)
    for (int m = 0; m < M; ++m) {
      double* a_row = A + (i0 + k) * ld + jb + 4 * m;
      Lanes4 a;
      std::memcpy(&a, a_row, sizeof a);
      a += t[k][m];
      std::memcpy(a_row, &a, sizeof a);
    }
}

template <int R>
__attribute__((always_inline)) inline void rows_against_all(const double* __restrict X, std::size_t rows,
                                                            std::size_t ld, std::size_t i0, double* __restrict A) {
  std::size_t jb = 0;
  for (; jb + 16 <= ld; jb += 16) rows_against_blocks<R, 4>(X, rows, ld, i0, jb, A);
  switch ((ld - jb) / 4) {
    case 3: rows_against_blocks<R, 3>(X, rows, ld, i0, jb, A); break;
    case 2: rows_against_blocks<R, 2>(X, rows, ld, i0, jb, A); break;
    case 1: rows_against_blocks<R, 1>(X, rows, ld, i0, jb, A); break;
    default: break;
  }
}

// chunk_gram for one or two physical rows from `from` of A alone, each against every column (the pairs beyond the
// diagonal land in A's unused upper triangle): the same sum per pair as chunk_gram forms, for a Gram where only the
// last rows change.
__attribute__((target_clones("avx2", "default"))) void chunk_gram_rows(const double* __restrict X, std::size_t rows,
                                                                        std::size_t ld, std::size_t from,
                                                                        std::size_t count, double* __restrict A) {
  if (count == 2) rows_against_all<2>(X, rows, ld, from, A);
  else rows_against_all<1>(X, rows, ld, from, A);
}

// The semantic index of fixed column i of a Gram [x (Y columns), y, 1] whose S leading columns are fixed: its leading
// position, S for y, S + 1 for the constant; -1 for the others.
Eigen::Index fixed_column(Eigen::Index i, Eigen::Index S, Eigen::Index Y) {
  return i < S ? i : i == Y ? S : i == Y + 1 ? S + 1 : -1;
}

// The fixed pairs of A (lower triangle): stored in `fixed` by the first evaluation of a search, taken from it by
// the later ones (reuse).
void keep_or_reuse(StaticGram& fixed, bool reuse, Eigen::Index Y, Eigen::MatrixXd& A) {
  const Eigen::Index S = static_cast<Eigen::Index>(fixed.n);
  if (!reuse) fixed.block = Eigen::MatrixXd::Zero(S + 2, S + 2);
  for (Eigen::Index i = 0; i < A.rows(); ++i)
    for (Eigen::Index j = 0; j <= i; ++j) {
      const Eigen::Index fi = fixed_column(i, S, Y), fj = fixed_column(j, S, Y);
      if (fi < 0 || fj < 0) continue;
      double& kept = fixed.block(std::max(fi, fj), std::min(fi, fj));
      if (reuse)
        A(i, j) = kept;
      else
        kept = A(i, j);
    }
}

// The sums of a Gram A of rows [x (P columns), y, 1] (lower triangle).
GramStats gram_stats(const Eigen::MatrixXd& A, std::size_t P) {
  const Eigen::Index Y = static_cast<Eigen::Index>(P), ONE = Y + 1;
  GramStats g(P);
  g.sxx = A.topLeftCorner(Y, Y);
  g.sxx = g.sxx.selfadjointView<Eigen::Lower>();
  g.sxy = A.row(Y).head(Y).transpose();
  g.sx = A.row(ONE).head(Y).transpose();
  g.syy = A(Y, Y);
  g.sy = A(ONE, Y);
  g.n = A(ONE, ONE);
  return g;
}

// The physical layout of kept rows: the columns that do not vary in semantic order, then y and 1, then the varying.
void keep_layout(ModeSearchRows& s, std::size_t P, const VaryingColumns& vc) {
  const std::size_t Q = P + 2;
  s.phys.assign(Q, 0);
  std::size_t pos = 0;
  for (std::size_t i = 0; i < P; ++i)
    if (i != vc.mode_col && static_cast<long>(i) != vc.init_col) s.phys[i] = pos++;
  s.phys[P] = pos++;
  s.phys[P + 1] = pos++;
  s.skip = pos;
  s.phys[vc.mode_col] = pos++;
  if (vc.init_col >= 0) s.phys[static_cast<std::size_t>(vc.init_col)] = pos++;
  s.ld = (Q + 3) / 4 * 4;
}

// The semantic Gram (lower triangle) of a physical one: semantic column i sits at phys[i].
Eigen::MatrixXd semantic_matrix(const std::vector<double>& AT, const std::vector<std::size_t>& phys, std::size_t ld) {
  const Eigen::Index Q = static_cast<Eigen::Index>(phys.size());
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(Q, Q);
  for (Eigen::Index i = 0; i < Q; ++i)
    for (Eigen::Index j = 0; j <= i; ++j) {
      const std::size_t pa = phys[static_cast<std::size_t>(i)], pb = phys[static_cast<std::size_t>(j)];
      A(i, j) = AT[std::max(pa, pb) * ld + std::min(pa, pb)];
    }
  return A;
}

}  // namespace

SearchStep search_step(ModeSearchRows* s, const CreepParams& cp, const std::vector<double>& t, const FitData& d,
                       std::size_t q) {
  if (!s || (cp.kind != CreepKind::kLti && cp.kind != CreepKind::kFractional)) return SearchStep::kFull;
  std::vector<char> slow(t.size());
  for (std::size_t k = 0; k < t.size(); ++k) slow[k] = slow_mode(t[k], d);
  const std::size_t ld = (q + 3) / 4 * 4;
  const bool fits = d.v->size() * (ld + (cp.kind == CreepKind::kFractional ? t.size() : 0)) * sizeof(double) <=
                    (std::size_t{256} << 20);
  SearchStep step = SearchStep::kFull;
  if (cp.kind == CreepKind::kFractional) {
    if (s->kept && s->fractional && s->taus == t && s->slow == slow) {
      step = SearchStep::kReuse;
    } else if (s->last_taus == t && fits) {
      step = SearchStep::kKeep;
      s->fractional = true;
      s->j = 0;
      s->taus = t;
      s->slow = slow;
    }
    s->last_taus = t;
    return step;
  }
  auto differ = [&](const std::vector<double>& ref, std::size_t except) {
    std::size_t n = 0, at = 0;
    for (std::size_t k = 0; k < t.size(); ++k)
      if (k != except && t[k] != ref[k]) ++n, at = k;
    return std::make_pair(n, at);
  };
  if (s->kept && !s->fractional && s->taus.size() == t.size() && s->slow == slow && differ(s->taus, s->j).first == 0) {
    step = SearchStep::kReuse;
  } else if (s->last_taus.size() == t.size()) {
    const auto [n, at] = differ(s->last_taus, t.size());
    if (n == 1 && fits) {
      step = SearchStep::kKeep;
      s->fractional = false;
      s->j = at;
      s->taus = t;
      s->slow = slow;
    }
  }
  s->last_taus = t;
  return step;
}

VaryingColumns varying_columns(const ModeSearchRows* s, const std::vector<double>& taus, const FitData& d,
                               std::size_t P0, std::size_t first_mode) {
  VaryingColumns vc;
  if (!s) return vc;
  vc.mode_col = first_mode + s->j;
  if (s->fractional) return vc;
  if (slow_mode(taus[s->j], d)) {
    std::size_t rank = 0;
    for (std::size_t k = 0; k < s->j; ++k) rank += slow_mode(taus[k], d);
    vc.init_col = static_cast<long>(P0 + rank);
  }
  return vc;
}

GramStats reuse_gram(ModeSearchRows& s, std::size_t N, std::size_t count, const std::vector<double>* weight,
                     std::size_t P, const std::function<void(std::size_t, double, double*)>& refill) {
  const std::size_t ld = s.ld, skip = s.skip;
  std::vector<double> AT(ld * ld, 0.0);
  const std::size_t kChunk = 32;
  for (std::size_t c0 = 0; c0 < N; c0 += kChunk) {
    const std::size_t rows = std::min(kChunk, N - c0);
    for (std::size_t t = c0; t < c0 + rows; ++t)
      refill(t, weight ? std::sqrt((*weight)[t]) : 1.0, s.rows.data() + t * ld + skip);
    chunk_gram_rows(s.rows.data() + c0 * ld, rows, ld, skip, count, AT.data());
  }
  for (std::size_t i = 0; i < skip; ++i)
    for (std::size_t k = 0; k <= i; ++k) AT[i * ld + k] = s.gram[i * ld + k];
  return gram_stats(semantic_matrix(AT, s.phys, ld), P);
}

GramStats stream_gram(std::size_t N, std::size_t P0, const std::function<double(std::size_t, double*)>& row,
                      const std::vector<double>& init, const std::vector<double>* weight, StaticGram* fixed,
                      ModeSearchRows* keep, const VaryingColumns& vc) {
  const std::size_t P = P0 + init.size();
  std::vector<double> e(init);
  // Each row is [x, y, 1]·√w, so one Gram of a chunk gives every sum at once (Σw·xxᵀ, Σw·xy, Σw·x, Σw·y², Σw·y,
  // Σw): 4×4 tiles of a 32-row chunk (chunk_gram), for the creep searches' 7–20 columns as for the Preisach
  // kinds' 100 or more (where its AVX2 clone is faster than Eigen's rank update, built for SSE2).
  const Eigen::Index Y = static_cast<Eigen::Index>(P), Q = Y + 2;  // columns: x, y, 1
  const Eigen::Index S = fixed ? static_cast<Eigen::Index>(fixed->n) : 0;
  const bool reuse = fixed && fixed->block.rows() == S + 2;
  std::vector<double> x(static_cast<std::size_t>(Y) + 1);  // the row's x, then its target y
  // Tile layout: the fixed columns first (the S leading ones, y, 1), then the others, so the fixed pairs are whole
  // tiles that a reuse skips; kept rows: keep_layout. phys[i]: where semantic column i sits in a row.
  const std::size_t ld = (static_cast<std::size_t>(Q) + 3) / 4 * 4;
  std::vector<std::size_t> phys(static_cast<std::size_t>(Q));
  if (keep) {
    keep_layout(*keep, P, vc);
    phys = keep->phys;
  } else {
    for (Eigen::Index i = 0; i < Q; ++i) {
      const Eigen::Index fi = fixed_column(i, S, Y);
      phys[static_cast<std::size_t>(i)] = static_cast<std::size_t>(fi >= 0 ? fi : i + 2);
    }
  }
  // The rows of a chunk: a 32-row buffer, or (kept) their place among all N rows.
  const std::size_t kChunk = 32;
  std::vector<double> R(keep ? 0 : kChunk * ld, 0.0), AT(ld * ld, 0.0);
  if (keep) keep->rows.resize(N * ld);  // every element written below (padding columns as zeros)
  const std::size_t skip_rows = reuse && !keep ? static_cast<std::size_t>(S + 2) : 0;
  for (std::size_t c0 = 0; c0 < N; c0 += kChunk) {
    const std::size_t rows = std::min(kChunk, N - c0);
    double* chunk = keep ? keep->rows.data() + c0 * ld : R.data();
    for (std::size_t t = c0; t < c0 + rows; ++t) {
      x[Y] = row(t, x.data());
      for (std::size_t j = 0; j < e.size(); ++j) {
        x[P0 + j] = e[j];
        // A decayed initial state is set to 0 before it turns subnormal: its products would underflow on every
        // remaining row, each a slow microcode assist (on hours of data, most of a creep-on-H fit's time).
        e[j] = e[j] < 1e-100 ? 0.0 : e[j] * init[j];
      }
      const double sw = weight ? std::sqrt((*weight)[t]) : 1.0;
      double* r = chunk + (t - c0) * ld;
      for (Eigen::Index i = 0; i <= Y; ++i) r[phys[static_cast<std::size_t>(i)]] = x[static_cast<std::size_t>(i)] * sw;
      r[phys[static_cast<std::size_t>(Y + 1)]] = sw;
      for (std::size_t i = static_cast<std::size_t>(Q); i < ld; ++i) r[i] = 0.0;
    }
    chunk_gram(chunk, rows, ld, skip_rows, AT.data());
  }
  if (keep) {
    keep->gram = AT;
    keep->kept = true;
  }
  Eigen::MatrixXd A = semantic_matrix(AT, phys, ld);
  if (fixed && !keep) keep_or_reuse(*fixed, reuse, Y, A);
  return gram_stats(A, P);
}

EvalResult solve(const GramStats& g, std::vector<bool> constrained, const std::vector<double>& lower,
                 const std::vector<std::pair<std::size_t, std::size_t>>& pairs, double smoothing) {
  const std::size_t used = constrained.size();
  constrained.resize(static_cast<std::size_t>(g.sx.size()), false);  // initial-state columns are free
  Eigen::MatrixXd G = g.centered_xx();
  if (smoothing > 0 && !pairs.empty()) {
    double diag = 0;
    for (const auto& pr : pairs) diag += G(pr.first, pr.first) + G(pr.second, pr.second);
    const double lambda = smoothing * diag / (2.0 * pairs.size());
    for (const auto& pr : pairs) {
      const auto a = static_cast<Eigen::Index>(pr.first), b = static_cast<Eigen::Index>(pr.second);
      G(a, a) += lambda, G(b, b) += lambda, G(a, b) -= lambda, G(b, a) -= lambda;
    }
  }
  Eigen::VectorXd c = g.centered_xy();
  const Eigen::Index P = G.rows();
  Eigen::VectorXd lo = Eigen::VectorXd::Zero(P);
  for (std::size_t j = 0; j < lower.size() && j < used; ++j)
    if (constrained[j]) lo(static_cast<Eigen::Index>(j)) = lower[j];
  c -= G * lo;  // w = lower + w' with w' ≥ 0 (a minimum slope keeps the inverse well defined)
  Eigen::VectorXd s(P);
  for (Eigen::Index j = 0; j < P; ++j) s(j) = G(j, j) > 0 ? 1.0 / std::sqrt(G(j, j)) : 1.0;
  Eigen::MatrixXd Gs = s.asDiagonal() * G * s.asDiagonal();
  Gs.diagonal().array() += 1e-9;
  Eigen::VectorXd x = s.asDiagonal() * nnls_gram(Gs, s.asDiagonal() * c, constrained);
  x += lo;
  EvalResult res;
  res.b = g.mean_y() - g.mean_x().dot(x);
  res.sse = g.sse(x, res.b);
  res.theta.assign(x.data(), x.data() + used);  // caller splits; initial-state terms are dropped
  return res;
}

}  // namespace pi
}  // namespace piezo::training
