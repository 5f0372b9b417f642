// Fitting of kinds "pi", "pi_creep_*" (moved from models/pi_model.cpp; the model itself stays in models/).
#include <algorithm>
#include <cmath>
#include <cstring>
#include <functional>
#include <stdexcept>

#include "piezo_compensation/models/model_file.h"
#include "piezo_compensation/features/play_operator.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"
#include "piezo_compensation/io/dataset.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

namespace {
using features::play;
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
  const std::vector<double>* weight = nullptr;  // per-sample weight (hold weighting); null = all 1
};

struct EvalResult {
  double sse = INFINITY;
  std::vector<double> w, theta;
  double b = 0;
};

// The Gram entries among a row's leading `n` columns, the target and the constant, kept from the first evaluation
// of a search that re-solves with other trailing (creep) columns on the same data, basis and weights: those entries
// do not change, so later evaluations form only the pairs with a trailing column. Semantic order: the n columns, y, 1.
struct StaticGram {
  std::size_t n = 0;
  Eigen::MatrixXd block;  // (n + 2)², lower triangle; empty until the first evaluation filled it
};

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
training::GramStats gram_stats(const Eigen::MatrixXd& A, std::size_t P) {
  const Eigen::Index Y = static_cast<Eigen::Index>(P), ONE = Y + 1;
  training::GramStats g(P);
  g.sxx = A.topLeftCorner(Y, Y);
  g.sxx = g.sxx.selfadjointView<Eigen::Lower>();
  g.sxy = A.row(Y).head(Y).transpose();
  g.sx = A.row(ONE).head(Y).transpose();
  g.syy = A(Y, Y);
  g.sy = A(ONE, Y);
  g.n = A(ONE, ONE);
  return g;
}

// A 1-D search over one LTI mode's time constant (search_lti_taus) changes two columns of the creep fit's rows:
// that mode's filter state and its initial-state column; a search over the fractional law's α (search_alpha), only
// the creep column (the modes' weights, not the modes). Every other column, the target and their Gram pairs are the
// same for all evaluations of the search, so the rows are kept (weighted, the varying columns last) with their Gram;
// later evaluations refill the varying columns and form only their pairs, in the same 32-row chunks (the same sums,
// bit for bit, at a fraction of the cost). One per search: data, basis, creep input and weights fixed.
struct ModeSearchRows {
  std::vector<double> last_taus;   // the previous evaluation's time constants
  std::vector<double> taus;        // those the rows were kept for (mode j's entry varies)
  std::vector<char> slow;          // the modes with an initial-state column then
  std::size_t j = 0;               // the mode searched
  std::size_t ld = 0, skip = 0;    // row stride; physical columns before the varying ones (the others, y, 1)
  std::vector<std::size_t> phys;   // semantic column → physical
  std::vector<double> rows, gram;  // N × ld weighted rows; their ld × ld Gram (physical, lower triangle)
  bool kept = false;
  bool fractional = false;         // kept for an α search: the modes' states of every row are kept too
  std::vector<double> modes;       // fractional: N × (number of modes)
};

// Modes with an initial-state column: slower than 10 s, and faster than a third of the record (slower ones are
// indistinguishable from the bias there).
bool slow_mode(double tau, const FitData& d) {
  return d.initial_state_terms && tau >= 10.0 && tau <= d.v->size() / d.rate / 3;
}

// The columns a kept search varies: mode j's state (semantic index mode_col) and, when it has one, its initial-state
// column (init_col, else -1).
struct VaryingColumns {
  std::size_t mode_col = 0;
  long init_col = -1;
};

enum class SearchStep { kFull, kKeep, kReuse };

// How to evaluate the law `cp` (modes `t`, CreepBasis::taus) within a search. LTI: reuse the kept rows when only
// mode j changed since they were kept, keep them when exactly one mode changed since the last evaluation.
// Fractional: reuse them when the modes are those they were kept for, keep them when the last evaluation had the
// same modes. Else a full evaluation. `q`: the Gram's columns (x, y, 1); rows over 256 MB are not stored.
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

// The varying columns of a kept search over mode j (search->j): the mode's column (first_mode + j) and its
// initial-state column (after the P0 columns, at its rank among the slow modes) when it has one; of an α search,
// the creep column (first_mode).
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

// The semantic Gram (lower triangle) of a physical one: semantic column i sits at phys[i].
Eigen::MatrixXd semantic_matrix(const std::vector<double>& AT, const std::vector<std::size_t>& phys, std::size_t ld) {
  const Eigen::Index Q = static_cast<Eigen::Index>(phys.size());
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(Q, Q);
  for (Eigen::Index i = 0; i < Q; ++i)
    for (Eigen::Index j = 0; j <= i; ++j) {
      const std::size_t pi = phys[static_cast<std::size_t>(i)], pj = phys[static_cast<std::size_t>(j)];
      A(i, j) = AT[std::max(pi, pj) * ld + std::min(pi, pj)];
    }
  return A;
}

// The Gram of the kept rows with the varying columns (`count`) refilled by refill(t, weight_sqrt, out).
template <class Refill>
training::GramStats reuse_gram(ModeSearchRows& s, std::size_t N, std::size_t count, const std::vector<double>* weight,
                               std::size_t P, Refill&& refill) {
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

// Weighted Gram sums of rows produced one sample at a time: row(t, x) fills x (P values) and returns the target.
// Extra columns a_j^(t+1) for the poles in `init` absorb the unknown initial state of slow modes: a recording
// never starts from the rest the model's reset assumes, and without them the first hours bias the creep fit.
// `fixed` (optional): its leading columns' entries are taken from it once it holds them (and stored there first).
// `keep` (optional): the rows are kept there in its layout (keep_layout, for the columns `vc`), with their Gram.
training::GramStats stream_gram(std::size_t N, std::size_t P0, const std::function<double(std::size_t, double*)>& row,
                                const std::vector<double>& init = {}, const std::vector<double>* weight = nullptr,
                                StaticGram* fixed = nullptr, ModeSearchRows* keep = nullptr,
                                const VaryingColumns& vc = {}) {
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

// Least squares on the Gram sums; columns flagged constrained stay ≥ their lower bound (`lower`, 0 where it is
// shorter). Solved on unit-diagonal (Jacobi-scaled) normal equations with a small ridge, so volts, nanometres and
// slow near-collinear mode columns do not set the conditioning, and no pair of columns can cancel at huge values.
// `pairs` (optional): column pairs whose weight difference is penalised by `smoothing` × the mean diagonal of those
// columns (the preisach pieces of one play: a smooth map of the play output, PI when the data show nothing else).
EvalResult solve(const training::GramStats& g, std::vector<bool> constrained, const std::vector<double>& lower = {},
                 const std::vector<std::pair<std::size_t, std::size_t>>& pairs = {}, double smoothing = 0.0) {
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

// The hysteresis basis of a fit: play thresholds and, for the preisach kinds, the knots of each play output.
struct Basis {
  std::vector<double> r;
  std::vector<std::vector<double>> knots;  // empty: PI (one piece per play)
  std::size_t pieces() const {
    if (knots.empty()) return r.size();
    std::size_t n = 0;
    for (const auto& k : knots) n += features::play_piece_count(k.size());
    return n;
  }
  // Advances the play states p by v and writes every piece to x.
  void columns(double v, std::vector<double>& p, double* x) const {
    for (std::size_t i = 0; i < r.size(); ++i) {
      p[i] = play(v, r[i], p[i]);
      if (knots.empty()) {
        *x++ = p[i];
      } else {
        features::play_pieces(p[i], knots[i].data(), knots[i].size(), x);
        x += features::play_piece_count(knots[i].size());
      }
    }
  }
  // The minimum slope applies to every piece of the threshold-0 play (the one without memory).
  std::vector<double> lower(double min_w0) const {
    std::vector<double> lo(pieces(), 0.0);
    const std::size_t n0 = knots.empty() ? 1 : features::play_piece_count(knots[0].size());
    std::fill(lo.begin(), lo.begin() + static_cast<std::ptrdiff_t>(n0), min_w0);
    return lo;
  }
  // Neighbouring pieces of each play (the smoothing penalty's pairs).
  std::vector<std::pair<std::size_t, std::size_t>> neighbours() const {
    std::vector<std::pair<std::size_t, std::size_t>> out;
    std::size_t at = 0;
    for (const auto& k : knots) {
      for (std::size_t j = 0; j < k.size(); ++j) out.emplace_back(at + j, at + j + 1);
      at += features::play_piece_count(k.size());
    }
    return out;
  }
  double smoothing = 0;    // weight of the penalty on neighbouring pieces' differences (solve)
  bool input_map = false;  // a PI kind's input map: knots on the first play only
  std::unique_ptr<PiCreepModel> model(const std::vector<double>& w, double b, const CreepParams& cp,
                                      double rate) const {
    return std::make_unique<PiCreepModel>(r, w, b, cp, rate, knots, input_map);
  }
};

std::vector<double> poles_of(const std::vector<double>& taus, double rate) {
  std::vector<double> a;
  for (double t : taus) a.push_back(std::exp(-1.0 / (rate * t)));
  return a;
}

// Poles of the modes whose initial state is worth estimating (slow_mode).
std::vector<double> init_poles(const std::vector<double>& taus, const FitData& d) {
  std::vector<double> out;
  for (double t : taus)
    if (slow_mode(t, d)) out.push_back(std::exp(-1.0 / (d.rate * t)));
  return out;
}

// Creep coefficients with a physical sign: the prony spectrum's weights and the LTI pairs' compliances g_j = 1/k_j
// (creep follows its input). Signed LTI gains let two poles the record cannot separate cancel at huge values
// (−1.9e5 nm/V pairs on the 40-s creep-free lowvolt_pi recording).
bool signed_creep(const CreepParams& cp) { return cp.kind == CreepKind::kProny || cp.kind == CreepKind::kLti; }

// The creep basis of `cp` on the data's sample clock: mode time constants, basis matrix and discrete poles
// (shared by the creep-on-V and creep-on-H evaluations). The Prony and LTI bases are the identity (one column per
// mode), which creep_columns copies instead of multiplying.
struct CreepBasis {
  std::vector<double> taus, poles;
  std::vector<std::vector<double>> B;
  bool identity = false;
  CreepBasis(const CreepParams& cp, double rate) {
    cp.basis(taus, B);
    poles = poles_of(taus, rate);
    identity = B.size() == taus.size();
    for (std::size_t k = 0; k < B.size() && identity; ++k)
      for (std::size_t j = 0; j < B[k].size(); ++j) identity = identity && B[k][j] == (j == k ? 1.0 : 0.0);
  }
};

// Advances the first-order creep modes l by input u and writes the basis projections Σ_j B[k][j]·l[j] (with the
// identity basis l itself: the same values, as the other terms of each sum are exact zeros).
void creep_columns(const CreepBasis& cb, std::vector<double>& l, double u, double* out) {
  const std::vector<double>& a = cb.poles;
  for (std::size_t j = 0; j < l.size(); ++j) l[j] = a[j] * l[j] + (1 - a[j]) * u;
  if (cb.identity) {
    std::copy(l.begin(), l.end(), out);
    return;
  }
  for (std::size_t k = 0; k < cb.B.size(); ++k) {
    double s = 0;
    for (std::size_t j = 0; j < l.size(); ++j) s += cb.B[k][j] * l[j];
    out[k] = s;
  }
}

// Where a fractional search being kept stores every row's mode states (null: not stored, or not fractional).
double* kept_modes(ModeSearchRows* s, std::size_t N, std::size_t nm) {
  if (!s || !s->fractional) return nullptr;
  s->modes.resize(N * nm);
  return s->modes.data();
}

// reuse_gram of a kept search: LTI mode j filtered from u0 over the input U (and its initial-state column, when kept
// with one); fractional: the creep column Σ_j B_j·l_j from the kept mode states.
training::GramStats reuse_search_gram(ModeSearchRows& s, const CreepBasis& cb, const std::vector<double>& U, double u0,
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

// Creep on the voltage: play pieces and creep basis columns, all weights at once (play weights ≥ 0).
// `fixed` (optional): the play pieces' Gram entries, shared by the evaluations of one creep-law search.
// `search` (optional): the rows kept over a search of one LTI time constant or of α (ModeSearchRows).
EvalResult evaluate(const FitData& d, const Basis& hb, const CreepParams& cp, double min_w0, StaticGram* fixed = nullptr,
                    ModeSearchRows* search = nullptr) {
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

// The hysteresis output H = Σ_i w_i·F_i of every sample for play weights w (fixed while a creep law is searched on H,
// so it is computed once per search, not once per evaluation).
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

// Creep on H with the play weights fixed up to a common scale: y = b + s·H + Σ_k θ_k·(basis of LP_j(H)).
// The free scale s lets the alternation move along the valley where a larger H and a smaller fast-creep gain
// explain the data almost equally well. H = hysteresis_series(d, hb, w). Returns w·s and θ/s (gains relative to
// the rescaled H).
EvalResult evaluate_creep_on_h(const FitData& d, const std::vector<double>& H, const std::vector<double>& w,
                               const CreepParams& cp, ModeSearchRows* search = nullptr) {
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

// Creep on H, all weights at once given the previous play weights w_prev: y = b + Σ_i w_i·F_i + Σ_k θ_k·(basis of
// LP_j(H_prev) − H_prev), H_prev = Σ_i w_prev,i·F_i. The creep columns are the modes' lags behind H, so a fast mode
// cannot stand in for H itself. Iterated to w ∝ w_prev it is the creep-on-H model (fit_with converts the gains);
// each step is one Gram of the voltage-input size (the alternation's w-step needs n_pieces × n_modes filter states
// per sample). θ is per nm of H_prev.
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

// Creep on H with the creep gains fixed: y = b + Σ_i w_i·(F_i + Σ_j g_j·LP_j(F_i)), F_i the play pieces, w_i ≥ 0.
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

// Protocol phase code of a hold (protocols::Phase::kHold; io stores the integer).
constexpr int kHoldPhase = 1;

// Hold samples: the phase markers where present, else runs of constant voltage of at least max(2 s, 20 samples)
// (tolerance 1e-4 of the voltage span, so a read-back with a few LSB of noise still counts).
std::vector<char> hold_mask(const io::Dataset& data, const io::AxisSeries& ax) {
  const std::size_t N = ax.voltage_v.size();
  std::vector<char> m(N, 0);
  if (data.phase.size() == N) {
    for (std::size_t t = 0; t < N; ++t) m[t] = data.phase[t] == kHoldPhase;
    return m;
  }
  const auto [mn, mx] = std::minmax_element(ax.voltage_v.begin(), ax.voltage_v.end());
  const double tol = 1e-4 * std::max(1e-12, *mx - *mn);
  const std::size_t min_len = std::max<std::size_t>(20, static_cast<std::size_t>(2.0 * data.sample_rate_hz()));
  std::size_t start = 0;
  for (std::size_t t = 1; t <= N; ++t)
    if (t == N || std::abs(ax.voltage_v[t] - ax.voltage_v[start]) > tol) {
      if (t - start >= min_len) std::fill(m.begin() + start + 1, m.begin() + t, 1);  // first sample is the move
      start = t;
    }
  return m;
}

struct Score {
  double all = INFINITY, hold = NAN, walk = NAN;
};

// Free-run MAE against the measurement on the validation part, the model having run over the training part
// first (the validation part continues it in time), split into hold and walk samples.
// abs_err (optional): the per-sample absolute errors.
Score validation_score(const PiCreepModel& fitted, const io::AxisSeries& train, const io::AxisSeries& val,
                       const std::vector<char>& val_hold, std::vector<double>* abs_err = nullptr) {
  PiCreepModel m = fitted;
  m.reset(train.voltage_v[0], train.position_nm[0]);
  ModelInput in;
  for (double v : train.voltage_v) {
    in.voltage_v = v;
    m.commit(in, 0.0);
  }
  double s[2] = {0, 0};
  std::size_t n[2] = {0, 0};
  for (std::size_t t = 0; t < val.voltage_v.size(); ++t) {
    in.voltage_v = val.voltage_v[t];
    const double e = std::abs(m.predict(in) - val.position_nm[t]);
    if (abs_err) abs_err->push_back(e);
    m.commit(in, 0.0);
    const int k = val_hold[t] ? 1 : 0;
    s[k] += e, ++n[k];
  }
  Score sc;
  sc.all = (n[0] + n[1]) ? (s[0] + s[1]) / double(n[0] + n[1]) : INFINITY;
  if (!std::isfinite(sc.all)) sc.all = INFINITY;
  if (n[1]) sc.hold = s[1] / n[1];
  if (n[0]) sc.walk = s[0] / n[0];
  return sc;
}

std::vector<double> thresholds_for(const std::vector<double>& v, int n) {
  const auto [mn, mx] = std::minmax_element(v.begin(), v.end());
  const double half_range = std::max(1e-6, 0.5 * (*mx - *mn));
  std::vector<double> r;
  for (int i = 0; i < n; ++i) r.push_back(half_range * i / n);
  return r;
}

// The preisach kinds' knots: play i moves within [v_min + r_i, v_max − r_i] once the data has swept the span, cut
// there into about K·(its width / the span) equal intervals (at least one), so the ramp hysterons tile the Preisach
// triangle evenly; knots at the inner interval ends only, so the outer pieces stay identified and extrapolate.
// A PI kind's input map (input_map): the first play (r_0 = 0, the voltage itself) cut the same way, the others not.
Basis basis_for(const std::vector<double>& v, std::vector<double> r, bool preisach, int knots_per_span,
                bool input_map = false) {
  Basis hb;
  hb.r = std::move(r);
  if (!preisach && !input_map) return hb;
  const auto [mn, mx] = std::minmax_element(v.begin(), v.end());
  const double span = std::max(1e-6, *mx - *mn);
  if (input_map) {
    if (knots_per_span < 2) return hb;  // one piece: plain PI
    hb.knots.assign(hb.r.size(), {});
    for (int j = 1; j < knots_per_span; ++j) hb.knots[0].push_back(*mn + span * j / knots_per_span);
    hb.input_map = true;
    return hb;
  }
  for (double ri : hb.r) {
    const double lo = *mn + ri, hi = *mx - ri;
    const int m = std::max(1, static_cast<int>(std::lround(knots_per_span * (hi - lo) / span)));
    std::vector<double> k;
    for (int j = 1; j < m; ++j) k.push_back(lo + (hi - lo) * j / m);
    hb.knots.push_back(k);
  }
  return hb;
}

// Options of fit_pi_creep, read and checked once (the range checks name the option).
struct PiFitOptions {
  bool initial_state_terms = true;
  double min_slope_fraction = 0.01;  // smallest initial slope, as a fraction of the overall V→position slope
  bool joint_on_h = false;           // creep_on_h_fit: joint (else alternate)
  int joint_iterations = 12;
  int alternations = 6, final_alternations = 6;
  std::string creep_input;           // voltage, hysteresis or auto
  int knots_per_span = 0;            // 0: the number of play operators, at most 12
  std::string input_map = "off";     // PI kinds: off, on, or auto (by validation)
  double piece_smoothing = 0.1;
  bool thresholds_given = false, n_play_given = false;
  std::vector<double> thresholds_v;
  int n_play = 12;
  std::string hold_weight;           // auto, off or a factor
  double hold_weight_factor = 1.0;
  bool refit_with_validation = false;
  // The creep law: grid, starting values and what is searched.
  int decades = 5, modes_per_decade = 2;
  double tau_min_s = 1.0, tau_max_s = 1.0, t1_s = 1.0, alpha = 0.5;
  bool t1_given = false, alpha_given = false, taus_given = false, fix_taus = false;
  bool warm_start = false;  // the given law (taus_s, t1_s or alpha) is a start, refined near it (refit_options)
  std::vector<double> taus_s;
  int n_pairs = 2, search_rounds = 3;
};

bool given(const YAML::Node& o, const char* key) { return o && o[key]; }

// The creep law's options (those of other kinds are not read).
void parse_creep_law_options(const YAML::Node& o, CreepKind kind, double tau_lo, double tau_hi, PiFitOptions& p) {
  p.decades = option_int(o, "decades", 5);
  p.modes_per_decade = option_int(o, "modes_per_decade", kind == CreepKind::kLog ? 3 : 2);
  p.tau_min_s = option_num(o, "tau_min_s", kind == CreepKind::kProny ? tau_lo : 1.0);
  p.tau_max_s = option_num(o, "tau_max_s", tau_hi);
  if (kind == CreepKind::kLog) {
    p.t1_given = given(o, "t1_s");
    p.t1_s = option_num(o, "t1_s", 1.0);
  }
  if (kind == CreepKind::kFractional && given(o, "alpha")) {
    p.alpha_given = true;
    p.alpha = option_num(o, "alpha", 0.5);
  }
  if (kind == CreepKind::kLti) {
    p.taus_given = given(o, "taus_s");
    if (p.taus_given) p.taus_s = yaml_numbers(o, "taus_s");
    p.fix_taus = option_bool(o, "fix_taus", false);
    if (p.fix_taus && !p.taus_given) throw std::runtime_error("option 'fix_taus': needs taus_s");
    p.n_pairs = option_int(o, "n_pairs", 2);
    if (!p.taus_given && (p.n_pairs < 1 || p.n_pairs > 6)) throw std::runtime_error("option 'n_pairs': expected 1..6");
    p.search_rounds = option_int(o, "search_rounds", 3);
  }
  p.warm_start = option_bool(o, "warm_start", false);
  if (p.warm_start && !(kind == CreepKind::kNone || kind == CreepKind::kProny || p.t1_given || p.alpha_given || p.taus_given))
    throw std::runtime_error("option 'warm_start': needs the law's start (taus_s, t1_s or alpha)");
}

PiFitOptions parse_pi_options(const YAML::Node& o, CreepKind kind, bool preisach, bool has_validation, double tau_lo,
                              double tau_hi) {
  PiFitOptions p;
  p.initial_state_terms = option_str(o, "initial_state_terms", "true") != "false";
  p.min_slope_fraction = option_num(o, "min_slope_fraction", 0.01);
  const std::string on_h_fit = option_str(o, "creep_on_h_fit", "alternate");
  if (on_h_fit != "alternate" && on_h_fit != "joint")
    throw std::runtime_error("option 'creep_on_h_fit': expected alternate or joint, got '" + on_h_fit + "'");
  p.joint_on_h = on_h_fit == "joint";
  p.joint_iterations = option_int(o, "joint_iterations", 12);
  if (p.joint_on_h && (p.joint_iterations < 1 || p.joint_iterations > 100))
    throw std::runtime_error("option 'joint_iterations': expected 1..100");
  // Creep-on-H alternations while choosing (plays, input, hold weight), and for the final model. On Preisach
  // physics 3 alternations are far from the bilinear least-squares point: the slow modes' gains still move (seed 12,
  // docs/models.md issue 12: worst end of hold 6.68 nm after 3, 1.57 after 10; 10 and 20 agree within 0.1 nm).
  // The choices keep the cheaper fit they were measured with.
  p.alternations = option_int(o, "alternations", preisach ? 3 : 6);
  p.final_alternations = option_int(o, "final_alternations", preisach ? 10 : p.alternations);
  if (p.alternations < 0 || p.alternations > 100 || p.final_alternations < 0 || p.final_alternations > 100)
    throw std::runtime_error("option 'alternations' / 'final_alternations': expected 0..100");
  p.creep_input = option_str(o, "creep_input", has_validation && kind != CreepKind::kNone ? "auto" : "hysteresis");
  if (p.creep_input != "voltage" && p.creep_input != "hysteresis" && p.creep_input != "auto")
    throw std::runtime_error("option 'creep_input': expected voltage, hysteresis or auto, got '" + p.creep_input + "'");
  p.knots_per_span = option_int(o, "knots_per_span", 0);
  if (p.knots_per_span < 0 || p.knots_per_span > kMaxKnotsPerPlay + 1)
    throw std::runtime_error("option 'knots_per_span': expected 1.." + std::to_string(kMaxKnotsPerPlay + 1));
  // Off by default: it lowers the PI kinds' errors on asymmetric and Preisach stages but, chosen by validation on
  // a 40-s recording, raises them on another recording of the same stage (docs/models.md, "Model kinds").
  p.input_map = option_str(o, "input_map", "off");
  if (p.input_map != "auto" && p.input_map != "on" && p.input_map != "off")
    throw std::runtime_error("option 'input_map': expected auto, on or off, got '" + p.input_map + "'");
  if (preisach && given(o, "input_map"))
    throw std::runtime_error("option 'input_map': only for the PI kinds (the preisach kinds cut every play)");
  // Measured on the PI-hysteresis and Preisach creep-protocol stages (docs/models.md): 0.1 beats 0 on both.
  p.piece_smoothing = option_num(o, "piece_smoothing", 0.1);
  if (!(p.piece_smoothing >= 0 && p.piece_smoothing <= 1e6))
    throw std::runtime_error("option 'piece_smoothing': expected 0..1e6");
  p.thresholds_given = given(o, "thresholds_v");
  if (p.thresholds_given) p.thresholds_v = yaml_numbers(o, "thresholds_v");
  p.n_play_given = given(o, "n_play");
  p.n_play = option_int(o, "n_play", 12);
  if (!p.thresholds_given && (p.n_play_given || !has_validation) && (p.n_play < 1 || p.n_play > kMaxPlayOperators))
    throw std::runtime_error("option 'n_play': expected 1..200");
  p.hold_weight = option_str(o, "hold_weight", "auto");
  if (p.hold_weight != "auto" && p.hold_weight != "off") {
    p.hold_weight_factor = option_num(o, "hold_weight", 1.0);
    if (!(p.hold_weight_factor >= 1.0 && p.hold_weight_factor <= 1000.0))
      throw std::runtime_error("option 'hold_weight': expected auto, off or a number in [1, 1000]");
  }
  const bool refit = option_bool(o, "refit_with_validation", false);
  // Only for the kinds linear in their parameters (no creep-law search that the validation part no longer checks).
  if (refit && !(kind == CreepKind::kNone || kind == CreepKind::kProny))
    throw std::runtime_error("option 'refit_with_validation': only for pi, pi_creep_prony and the preisach kinds");
  p.refit_with_validation = refit;
  parse_creep_law_options(o, kind, tau_lo, tau_hi, p);
  return p;
}

const io::AxisSeries& training_axis(const FitRequest& req) {
  if (!req.train) throw std::runtime_error("PI fit: no training data");
  const io::AxisSeries& ax = req.train->axis(req.axis);
  if (ax.voltage_v.size() < 10) throw std::runtime_error("PI fit: need at least 10 samples");
  return ax;
}

const io::AxisSeries* validation_axis(const FitRequest& req) {
  if (req.validation && req.validation->has_axis(req.axis) && req.validation->axis(req.axis).voltage_v.size() >= 10)
    return &req.validation->axis(req.axis);
  return nullptr;
}

// Smallest allowed initial slope: a fraction of the overall voltage→position slope (0 when that is not positive).
double min_slope(const io::AxisSeries& ax, double fraction) {
  double mv = 0, my = 0;
  const std::size_t N = ax.voltage_v.size();
  for (std::size_t t = 0; t < N; ++t) mv += ax.voltage_v[t], my += ax.position_nm[t];
  mv /= N, my /= N;
  double cvy = 0, cvv = 0;
  for (std::size_t t = 0; t < N; ++t) {
    cvy += (ax.voltage_v[t] - mv) * (ax.position_nm[t] - my);
    cvv += (ax.voltage_v[t] - mv) * (ax.voltage_v[t] - mv);
  }
  return cvv > 0 && cvy > 0 ? fraction * cvy / cvv : 0.0;
}

using SseFn = std::function<double(const CreepParams&)>;

// Where a creep-on-H alternation stopped (after `done` rounds, on the training data with sample weights `weight`): a
// later fit of the same data and weights with more rounds continues from here, with the same result as starting
// over (each round depends only on the creep law and the play weights the last one left).
struct Alternation {
  CreepParams cp;
  EvalResult best;
  int done = 0;
  const std::vector<double>* weight = nullptr;
};

// One fit_pi_creep call: the data, the options and the choices made on them, each choice a member.
class PiCreepFit {
 public:
  PiCreepFit(const FitRequest& req, CreepKind kind, bool preisach);
  models::ModelPtr run();

 private:
  double clamp_tau(double t) const { return std::min(tau_hi_, std::max(tau_lo_, t)); }
  // Keeps the log law's slowest mode inside the data for a given t1.
  int log_decades(double t1) const {
    return std::max(1, std::min(cp0_.decades, static_cast<int>(std::floor(std::log10(tau_hi_ / t1) + 1e-9))));
  }
  void report(const char* what) {
    ++evals_;
    if (req_.progress) req_.progress(std::min<double>(evals_, total_), total_, what);
  }
  CreepParams initial_creep() const;
  Basis basis_n(std::vector<double> thresholds, bool input_map = false) const;
  // One fit for given thresholds, creep input, sample weights and alternations. `alt` (training data only): where
  // its alternation stopped, and where it continues from when it stopped earlier with the same weights.
  std::unique_ptr<PiCreepModel> fit_with(const FitData& d, const Basis& r, bool on_h, int alternations,
                                         const std::vector<double>* weight,
                                         std::unique_ptr<PiCreepModel>* v_model = nullptr,
                                         Alternation* alt = nullptr);
  EvalResult iterate_joint_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best);
  EvalResult alternate_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters);
  EvalResult continue_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters);
  void search_creep_law(CreepParams& cp, const SseFn& sse_fn, bool refine_only);
  void search_log_t1(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  void search_alpha(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  void search_lti_taus(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  // The choices, in the order run() makes them.
  Basis choose_play_count();
  std::unique_ptr<PiCreepModel> choose_creep_input(const Basis& r, Score& score);
  double choose_hold_weight(const Basis& r, const Score& score, const std::vector<char>& train_hold,
                            std::unique_ptr<PiCreepModel>& m, std::vector<double>& weight);
  void final_fit(const Basis& r, double used_factor, const std::vector<double>& weight,
                 const std::vector<char>& train_hold, std::unique_ptr<PiCreepModel>& m);

  const FitRequest& req_;
  const CreepKind kind_;
  const bool preisach_;
  const io::AxisSeries& ax_;
  const io::AxisSeries* val_;
  const double rate_;
  // What the data can identify: no mode faster than two samples, none slower than the recording.
  const double tau_lo_, tau_hi_;
  const PiFitOptions opt_;
  const CreepParams cp0_;
  FitData d_;
  std::vector<char> val_hold_;
  double min_w0_ = 0;
  int evals_ = 0;
  double total_ = 1;
  // The alternations of the unweighted and the hold-weighted fit, continued by final_fit.
  Alternation alt_plain_, alt_weighted_;
};

PiCreepFit::PiCreepFit(const FitRequest& req, CreepKind kind, bool preisach)
    : req_(req),
      kind_(kind),
      preisach_(preisach),
      ax_(training_axis(req)),
      val_(validation_axis(req)),
      rate_(req.train->sample_rate_hz()),
      tau_lo_(2.0 / rate_),
      tau_hi_(std::max(2.0 * tau_lo_, ax_.voltage_v.size() / rate_)),
      opt_(parse_pi_options(req.options, kind, preisach, val_ != nullptr, tau_lo_, tau_hi_)),
      cp0_(initial_creep()),
      d_{&ax_.voltage_v, &ax_.position_nm, rate_} {
  d_.initial_state_terms = opt_.initial_state_terms;
  if (val_) val_hold_ = hold_mask(*req.validation, *val_);
  min_w0_ = min_slope(ax_, opt_.min_slope_fraction);
  const double per_search = kind == CreepKind::kNone || kind == CreepKind::kProny ? 1
                            : kind == CreepKind::kLti                           ? 21.0 * opt_.n_pairs
                                                                                : 17;
  total_ = (per_search * 3 + 6 * (per_search + 2)) * (val_ ? 2 : 1) + (preisach ? 8 : 15);
}

CreepParams PiCreepFit::initial_creep() const {
  CreepParams cp0;
  cp0.kind = kind_;
  cp0.decades = opt_.decades;
  cp0.modes_per_decade = opt_.modes_per_decade;
  cp0.tau_min_s = clamp_tau(opt_.tau_min_s);
  cp0.tau_max_s = clamp_tau(opt_.tau_max_s);
  if (kind_ == CreepKind::kFractional && !(cp0.tau_max_s > cp0.tau_min_s)) cp0.tau_min_s = tau_lo_;
  if (kind_ == CreepKind::kProny && cp0.modes_per_decade >= 1 && cp0.tau_max_s > cp0.tau_min_s) {
    // The grid's last mode on or below tau_max_s (log_tau_grid rounds the decade count: 3 per decade on 8 h of
    // data put a mode at 39 000 s).
    const double steps = std::floor(std::log10(cp0.tau_max_s / cp0.tau_min_s) * cp0.modes_per_decade + 1e-9);
    cp0.tau_max_s = cp0.tau_min_s * std::pow(10.0, steps / cp0.modes_per_decade);
  }
  if (kind_ == CreepKind::kLog) {
    cp0.t1_s = clamp_tau(opt_.t1_s);
    cp0.decades = std::max(1, std::min(cp0.decades, static_cast<int>(std::floor(std::log10(tau_hi_ / tau_lo_)))));
  }
  if (kind_ == CreepKind::kFractional && opt_.alpha_given) cp0.alpha = opt_.alpha;
  if (kind_ == CreepKind::kLti) {
    // Given time constants, else spread evenly in log over the identifiable range.
    const double lo = std::log10(tau_lo_), hi = std::log10(tau_hi_);
    if (opt_.taus_given)
      for (double t : opt_.taus_s) cp0.taus_s.push_back(clamp_tau(t));
    else
      for (int j = 0; j < opt_.n_pairs; ++j) cp0.taus_s.push_back(std::pow(10.0, lo + (hi - lo) * (j + 0.5) / opt_.n_pairs));
    cp0.gains_nm_per_v.assign(cp0.taus_s.size(), 0.0);
  }
  cp0.check_sizes();
  return cp0;
}

Basis PiCreepFit::basis_n(std::vector<double> thresholds, bool input_map) const {
  const int n = static_cast<int>(thresholds.size());
  Basis b = basis_for(ax_.voltage_v, std::move(thresholds), preisach_,
                      opt_.knots_per_span > 0 ? opt_.knots_per_span : std::min(n, 12), input_map && !preisach_);
  b.smoothing = opt_.piece_smoothing;
  return b;
}

// With on_h, the voltage-input model it starts from is handed out through v_model (auto input costs nothing extra).
std::unique_ptr<PiCreepModel> PiCreepFit::fit_with(const FitData& d, const Basis& r, bool on_h, int alternations,
                                                   const std::vector<double>* weight,
                                                   std::unique_ptr<PiCreepModel>* v_model, Alternation* alt) {
  FitData dd = d;
  dd.weight = weight;
  const int iters = kind_ == CreepKind::kNone || !on_h ? 0 : alternations;
  const bool joint = kind_ == CreepKind::kProny && opt_.joint_on_h;
  if (alt && !v_model && !joint && alt->done > 0 && alt->done <= iters && alt->weight == weight) {
    CreepParams cp = alt->cp;
    EvalResult best = continue_on_h(dd, r, cp, alt->best, iters - alt->done);
    *alt = Alternation{cp, best, iters, weight};
    return r.model(best.w, best.b, cp, rate_);
  }
  CreepParams cp = cp0_;
  // Creep on the voltage: weights and creep coefficients are jointly linear.
  StaticGram pieces{r.pieces(), {}};
  ModeSearchRows kept;
  search_creep_law(cp, [&](const CreepParams& c) { return evaluate(dd, r, c, min_w0_, &pieces, &kept).sse; }, false);
  EvalResult best = evaluate(dd, r, cp, min_w0_, &pieces);
  cp.set_coefficients(best.theta);
  if (v_model) *v_model = r.model(best.w, best.b, cp, rate_);
  // The joint fixed point is exact where the hysteresis is representable, but with a misfit it is not the
  // least-squares solution the alternation converges to: on Preisach physics it was better on one seed and worse on
  // another (docs/models.md, "Creep on physics no kind was written from"), so the alternation is the default (creep_on_h_fit: joint, prony only).
  if (iters > 0 && joint) {
    best = iterate_joint_on_h(dd, r, cp, best);
  } else if (iters > 0) {
    best = alternate_on_h(dd, r, cp, best, iters);
    if (alt) *alt = Alternation{cp, best, iters, weight};
  }
  return r.model(best.w, best.b, cp, rate_);
}

// Prony creep on H (linear in its gains): iterates the joint solve to its fixed point, from the voltage-input play
// weights; stops once the weights' shape moves by < 0.1 % (their scale does not change the solve).
EvalResult PiCreepFit::iterate_joint_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best) {
  const CreepParams on_v = cp;
  cp.on_hysteresis = true;
  std::vector<double> w = best.w;
  bool moved = false;
  for (int it = 0; it < opt_.joint_iterations; ++it) {
    EvalResult cr = evaluate_joint_on_h(d, r, w, cp, min_w0_);
    report("PI + creep fit");
    double sw = 0, sn = 0, diff = 0, lag_gain = 0;
    for (std::size_t i = 0; i < w.size(); ++i) sw += w[i], sn += cr.w[i];
    if (!(sw > 0 && sn > 0)) break;
    for (std::size_t i = 0; i < w.size(); ++i) diff += std::abs(cr.w[i] / sn - w[i] / sw);
    // With A = Σ w'·F and H_prev = c·A (c = sw/sn once the shapes agree): y = (1 − c·G)·A + c·Σ θ_j·LP_j(A),
    // G = Σθ; so the model's weights are (1 − c·G)·w' and its gains c·θ/(1 − c·G).
    const double c = sw / sn;
    for (double x : cr.theta) lag_gain += x;
    const double direct = 1.0 - c * lag_gain;
    if (!(direct > 0.05)) break;  // creep as large as H itself: not a creep the iteration can represent
    for (double& x : cr.w) x *= direct;
    for (double& x : cr.theta) x *= c / direct;
    cp.set_coefficients(cr.theta);
    w = cr.w;
    best = cr;
    moved = true;
    if (diff < 1e-3) break;
  }
  if (!moved) cp = on_v;  // the voltage-input solution stands
  return best;
}

// Creep on H is bilinear (w and g): alternates the two linear problems, refining the law's nonlinear parameters
// once per round, starting from the voltage-input solution.
EvalResult PiCreepFit::alternate_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters) {
  cp.on_hysteresis = true;
  // Voltage-input gains are in nm/V; as gains on H they are about (nm/V)/(Σw) nm/nm.
  double sum_w = 0;
  for (double x : best.w) sum_w += x;
  std::vector<double> theta = best.theta;
  for (double& t : theta) t /= std::max(1e-12, sum_w);
  cp.set_coefficients(theta);
  return continue_on_h(d, r, cp, best, iters);
}

// `iters` more rounds of the alternation from the play weights best.w and the law cp.
EvalResult PiCreepFit::continue_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters) {
  std::vector<double> w = best.w;
  for (int it = 0; it < iters; ++it) {
    const std::vector<double> H = hysteresis_series(d, r, w);
    ModeSearchRows kept;
    search_creep_law(cp, [&](const CreepParams& c) { return evaluate_creep_on_h(d, H, w, c, &kept).sse; }, true);
    EvalResult cr = evaluate_creep_on_h(d, H, w, cp);
    report("PI + creep fit");
    cp.set_coefficients(cr.theta);
    w = cr.w;
    best = evaluate_w_given_creep_on_h(d, r, cp, min_w0_);
    report("PI + creep fit");
    w = best.w;
  }
  return best;
}

// Searches the law's nonlinear parameters (t1, α or the τ_j) for the least SSE of `sse_fn`; refine_only: near the
// current values. Prony and no creep are linear in their weights: nothing to search.
void PiCreepFit::search_creep_law(CreepParams& cp, const SseFn& sse_fn, bool refine_only) {
  const SseFn sse_of = [&](const CreepParams& c) {
    report("PI + creep fit");
    return sse_fn(c);
  };
  // A warm start (the law given as a start, refit_options) searches as the alternation's refinements do: near the
  // given values (a backfitting refit, whose data moved little; the alternation on H that follows refines them
  // again), not over the whole range.
  refine_only = refine_only || opt_.warm_start;
  switch (kind_) {
    case CreepKind::kNone:
    case CreepKind::kProny: break;
    case CreepKind::kLog: search_log_t1(cp, sse_of, refine_only); break;
    case CreepKind::kFractional: search_alpha(cp, sse_of, refine_only); break;
    case CreepKind::kLti: search_lti_taus(cp, sse_of, refine_only); break;
  }
}

void PiCreepFit::search_log_t1(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  if (opt_.t1_given && !opt_.warm_start) return;  // fixed
  const double cur = std::log10(cp.t1_s), lo = std::log10(tau_lo_), hi = std::log10(tau_hi_) - 1.0;
  if (!(hi > lo)) return;
  const auto sse_at = [&](double lg) {
    CreepParams c = cp;
    c.t1_s = std::pow(10.0, lg);
    c.decades = log_decades(c.t1_s);
    return sse_of(c);
  };
  cp.t1_s = std::pow(10.0, search_1d(sse_at, refine_only ? std::max(lo, cur - 0.3) : lo,
                                     refine_only ? std::min(hi, cur + 0.3) : hi, refine_only ? 5 : 15, 12));
  cp.decades = log_decades(cp.t1_s);
}

void PiCreepFit::search_alpha(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  if (opt_.alpha_given && !opt_.warm_start) return;  // fixed (initial_creep set it)
  const double cur = cp.alpha;
  cp.alpha = search_1d([&](double al) { CreepParams c = cp; c.alpha = al; return sse_of(c); },
                       refine_only ? std::max(0.02, cur - 0.1) : 0.03, refine_only ? std::min(0.98, cur + 0.1) : 0.97,
                       refine_only ? 5 : 19, 12);
}

void PiCreepFit::search_lti_taus(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  const double lo = std::log10(tau_lo_), hi = std::log10(tau_hi_);  // the start: initial_creep
  const int rounds = refine_only ? 1 : opt_.search_rounds;
  for (int round = refine_only ? 1 : 0; round < (refine_only ? 2 : rounds) && !opt_.fix_taus; ++round)
    for (std::size_t j = 0; j < cp.taus_s.size(); ++j) {
      auto f = [&](double lg) { CreepParams c = cp; c.taus_s[j] = std::pow(10.0, lg); return sse_of(c); };
      const double cur = std::log10(cp.taus_s[j]);
      // First round scans the whole range; later rounds refine around the current value.
      const double a = round == 0 ? lo : std::max(lo, cur - 0.5), b = round == 0 ? hi : std::min(hi, cur + 0.5);
      cp.taus_s[j] = std::pow(10.0, search_1d(f, a, b, 11, 10));
    }
  std::sort(cp.taus_s.begin(), cp.taus_s.end());
}

// Thresholds: given, or n_play given, or chosen by the validation error of PI + a prony spectrum on the voltage
// (one linear solve per candidate; the choice is not blurred by creep a plain PI cannot follow); for the PI kinds,
// with and without the input map (option input_map: auto). The fewest pieces within 0.2 % of the best.
Basis PiCreepFit::choose_play_count() {
  // The input map's candidates: the PI kinds with a validation part try both (auto); given on or off, that one.
  std::vector<bool> maps{opt_.input_map == "on"};
  if (opt_.input_map == "auto" && !preisach_ && val_) maps = {false, true};
  std::vector<std::vector<double>> counts;
  if (opt_.thresholds_given) counts.push_back(opt_.thresholds_v);
  else if (opt_.n_play_given || !val_) counts.push_back(thresholds_for(ax_.voltage_v, opt_.n_play));
  else
    // The preisach kinds have ~n·K/2 pieces: up to 20 play operators (K ≤ 12: 138 pieces).
    for (int n : {4, 6, 8, 12, 16, 20, 24, 32}) {
      if (static_cast<std::size_t>(n) * 20 > ax_.voltage_v.size() || (preisach_ && n > 20)) break;
      if (!preisach_ && n == 20) continue;
      counts.push_back(thresholds_for(ax_.voltage_v, n));
    }
  if (counts.empty()) counts.push_back(thresholds_for(ax_.voltage_v, 4));
  std::vector<Basis> bases;
  for (const auto& c : counts)
    for (bool map : maps) bases.push_back(basis_n(c, map));
  if (bases.size() == 1) return bases.front();
  CreepParams proxy;
  if (kind_ != CreepKind::kNone) {
    proxy.kind = CreepKind::kProny;
    proxy.tau_min_s = tau_lo_;
    proxy.tau_max_s = tau_hi_;
    proxy.modes_per_decade = 1;
  }
  std::vector<double> score;
  for (const Basis& b : bases) {
    const EvalResult e = evaluate(d_, b, proxy, min_w0_);
    report("PI thresholds");
    CreepParams c = proxy;
    c.set_coefficients(e.theta);
    score.push_back(validation_score(*b.model(e.w, e.b, c, rate_), ax_, *val_, val_hold_).all);
  }
  // The fewest pieces within 0.2 % of the best (without the map first on a tie).
  const double best = *std::min_element(score.begin(), score.end());
  std::size_t chosen = 0;
  for (std::size_t k = 0; k < bases.size(); ++k)
    if (score[k] <= 1.002 * best &&
        (score[chosen] > 1.002 * best || bases[k].pieces() < bases[chosen].pieces()))
      chosen = k;
  return bases[chosen];
}

// Creep input by validation (auto), else as given; `score` is the chosen model's validation score.
std::unique_ptr<PiCreepModel> PiCreepFit::choose_creep_input(const Basis& r, Score& score) {
  if (opt_.creep_input != "auto") {
    auto m = fit_with(d_, r, opt_.creep_input == "hysteresis", opt_.alternations, nullptr, nullptr, &alt_plain_);
    if (val_) score = validation_score(*m, ax_, *val_, val_hold_);
    return m;
  }
  std::unique_ptr<PiCreepModel> mv;
  auto mh = fit_with(d_, r, true, opt_.alternations, nullptr, &mv, &alt_plain_);
  std::vector<double> ev, eh;
  const Score sv = validation_score(*mv, ax_, *val_, val_hold_, &ev), sh = validation_score(*mh, ax_, *val_, val_hold_, &eh);
  // Creep on V only when validation shows it clearly better: against the noise floor (16.6 nm on the Preisach
  // creep-protocol stage) a 0.26-nm lead of V over 2 h of validation picked it on seed 4242, where against the
  // truth it left 11.9 nm at the end of a hold and H 3.0 nm (docs/models.md, "Creep on physics no kind was written from"). Blocks of 5 min; with
  // under 20 min of validation the lower MAE decides, as before (forcing H there cost the stage matrix's short
  // stages up to 88 %: stack150_pi_creep preisach_creep_prony 16.2 → 30.4 nm).
  const bool use_h = !validation_prefers(ev, eh, static_cast<std::size_t>(300.0 * rate_));
  score = use_h ? sh : sv;
  return use_h ? std::move(mh) : std::move(mv);
}

// Hold weighting: holds get the weight of the walk samples in total (capped at 10×), kept only when validation
// shows the holds improve and the walk error does not grow by more than 5 %. Returns the factor kept (1: none);
// `weight` holds the per-sample weights it was fitted with.
double PiCreepFit::choose_hold_weight(const Basis& r, const Score& score, const std::vector<char>& train_hold,
                                      std::unique_ptr<PiCreepModel>& m, std::vector<double>& weight) {
  const double n_hold = double(std::count(train_hold.begin(), train_hold.end(), 1));
  const double n_walk = double(train_hold.size()) - n_hold;
  double factor = 1.0;
  if (opt_.hold_weight == "auto") {
    if (val_ && n_hold > 0 && n_walk > 0) factor = std::min(10.0, std::max(1.0, n_walk / n_hold));
  } else if (opt_.hold_weight != "off") {
    factor = opt_.hold_weight_factor;
  }
  if (!(factor > 1.0 && kind_ != CreepKind::kNone && n_hold > 0)) return 1.0;
  weight.resize(train_hold.size());
  for (std::size_t t = 0; t < weight.size(); ++t) weight[t] = train_hold[t] ? factor : 1.0;
  auto mw = fit_with(d_, r, m->creep().on_hysteresis, opt_.alternations, &weight, nullptr, &alt_weighted_);
  bool keep = opt_.hold_weight != "auto";
  if (!keep) {
    const Score sw = validation_score(*mw, ax_, *val_, val_hold_);
    keep = std::isfinite(sw.hold) && std::isfinite(score.hold) && sw.hold < score.hold && !(sw.walk > 1.05 * score.walk);
  }
  if (!keep) return 1.0;
  m = std::move(mw);
  return factor;
}

// With everything chosen: the final alternations, or (refit_with_validation: true) the final weights from the
// training and validation parts together (one recording in time: slow creep modes get hours more data). The refit
// is off by default: the validation metrics stored with the model and compared by --model auto would then be
// in-sample.
void PiCreepFit::final_fit(const Basis& r, double used_factor, const std::vector<double>& weight,
                           const std::vector<char>& train_hold, std::unique_ptr<PiCreepModel>& m) {
  const bool refit = val_ && opt_.refit_with_validation;
  const bool realternate = opt_.final_alternations != opt_.alternations && m->creep().on_hysteresis &&
                           !(kind_ == CreepKind::kProny && opt_.joint_on_h);
  // The chosen fit's alternation continues (the same result as starting over, without its first rounds again).
  if (realternate && !refit)
    m = fit_with(d_, r, true, opt_.final_alternations, used_factor > 1.0 ? &weight : nullptr, nullptr,
                 used_factor > 1.0 ? &alt_weighted_ : &alt_plain_);
  if (!refit) return;
  std::vector<double> all_v = ax_.voltage_v, all_y = ax_.position_nm, all_w;
  all_v.insert(all_v.end(), val_->voltage_v.begin(), val_->voltage_v.end());
  all_y.insert(all_y.end(), val_->position_nm.begin(), val_->position_nm.end());
  for (std::size_t t = 0; t < all_v.size(); ++t) {
    const bool hold = t < train_hold.size() ? train_hold[t] : val_hold_[t - train_hold.size()];
    all_w.push_back(hold ? used_factor : 1.0);
  }
  FitData all = d_;
  all.v = &all_v, all.y = &all_y;
  m = fit_with(all, r, m->creep().on_hysteresis, opt_.final_alternations, used_factor > 1.0 ? &all_w : nullptr);
}

models::ModelPtr PiCreepFit::run() {
  const Basis r = choose_play_count();
  Score score;
  std::unique_ptr<PiCreepModel> m = choose_creep_input(r, score);
  const std::vector<char> train_hold = hold_mask(*req_.train, ax_);
  std::vector<double> weight;
  const double used_factor = choose_hold_weight(r, score, train_hold, m, weight);
  final_fit(r, used_factor, weight, train_hold, m);
  m->meta = make_meta(req_);
  m->meta.validation["fit_hold_weight"] = used_factor;
  m->meta.validation["fit_play_operators"] = static_cast<double>(r.r.size());
  if (preisach_) m->meta.validation["fit_preisach_pieces"] = static_cast<double>(r.pieces());
  else m->meta.validation["fit_input_map_pieces"] = r.input_map ? static_cast<double>(r.knots[0].size() + 1) : 0.0;
  if (kind_ != CreepKind::kNone) m->meta.validation["fit_creep_on_hysteresis"] = m->creep().on_hysteresis ? 1 : 0;
  return m;
}

}  // namespace

// Scale-free by construction: thresholds from the data's own voltage span, normal equations solved on unit
// diagonal, creep time constants only where the data can identify them (≥ 2 samples, ≤ the training duration).
// With a validation part, the number of play operators, the creep input (V or H) and hold weighting are chosen by
// free-run validation error, unless given as options.
// The preisach kinds cut each play output at knots (basis_for); K, the knot intervals over the span, is the number of
// play operators unless given (knots_per_span), so the plane is tiled by an n × n triangle of ramp hysterons.
models::ModelPtr fit_pi_creep(const FitRequest& req, models::CreepKind kind, bool preisach) {
  const std::string map = output_map_option(req.options);
  const FitFn fit = [kind, preisach](const FitRequest& r) -> models::ModelPtr { return PiCreepFit(r, kind, preisach).run(); };
  if (map == "off") return fit(req);
  return fit_with_output_map(req, map == "on", fit);
}

YAML::Node refit_options(const models::Model& previous, const YAML::Node& options, bool same_structure) {
  YAML::Node o = options && options.IsMap() ? YAML::Clone(options) : YAML::Node(YAML::NodeType::Map);
  const auto* pc = dynamic_cast<const models::PiCreepModel*>(&previous);
  if (!pc) return o;
  const CreepParams& cp = pc->creep();
  // Same structure: the previous play thresholds, creep input and maps, so that refits compared with each other
  // (a lag profile) differ only by the data, not by a structure chosen again on it.
  if (same_structure) {
    if (!o["thresholds_v"]) o["thresholds_v"] = pc->thresholds_v();
    if (!o["creep_input"] && cp.kind != CreepKind::kNone) o["creep_input"] = cp.on_hysteresis ? "hysteresis" : "voltage";
    if (!o["input_map"] && !pc->preisach()) o["input_map"] = pc->has_input_map() ? "on" : "off";
    if (!o["output_map"]) o["output_map"] = pc->output_map().empty() ? "off" : "on";
  }
  // Otherwise only the law: the play count, creep input and hold weight are chosen again, as the base that absorbed
  // an effect is not the structure to keep (docs/closing-the-loop.md, backfitting).
  if (o["taus_s"] || o["t1_s"] || o["alpha"]) return o;
  switch (cp.kind) {
    case CreepKind::kLti: o["taus_s"] = cp.taus_s; break;
    case CreepKind::kLog: o["t1_s"] = cp.t1_s; break;
    case CreepKind::kFractional: o["alpha"] = cp.alpha; break;
    case CreepKind::kNone:
    case CreepKind::kProny: return o;  // nothing to search
  }
  o["warm_start"] = true;
  return o;
}

}  // namespace piezo::training
