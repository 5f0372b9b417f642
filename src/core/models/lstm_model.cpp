#include "piezo_compensation/models/lstm_model.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <stdexcept>

namespace piezo::models {

LstmNet::LstmNet(const LstmShape& shape) : shape_(shape) {
  if (shape.inputs < 1 || shape.inputs > 256) throw std::runtime_error("lstm: inputs must be in 1..256");
  if (shape.layers < 1 || shape.layers > kMaxLayers) throw std::runtime_error("lstm: layers must be in 1..8");
  if (shape.hidden < 1 || shape.hidden > kMaxHidden) throw std::runtime_error("lstm: hidden must be in 1..256");
  Eigen::Index o = 0;
  const Eigen::Index H = shape.hidden;
  for (int l = 0; l < shape.layers; ++l) {
    layer_offset_.push_back(o);
    o += 4 * H * layer_inputs(l) + 4 * H * H + 4 * H;
  }
  head_offset_ = o;
  num_params_ = static_cast<std::size_t>(o + H + 1);
  // Per gate row: −k, a, b of a / (1 + e^{−k z}) + b: the sigmoid for i, f, o;
  // tanh(z) = 2 / (1 + e^{−2z}) − 1 for g.
  gate_coef_.assign(static_cast<std::size_t>(12 * H), 0.0);
  for (Eigen::Index r = 0; r < 4 * H; ++r) {
    const bool g = r >= 2 * H && r < 3 * H;
    gate_coef_[static_cast<std::size_t>(r)] = g ? -2.0 : -1.0;
    gate_coef_[static_cast<std::size_t>(4 * H + r)] = g ? 2.0 : 1.0;
    gate_coef_[static_cast<std::size_t>(8 * H + r)] = g ? -1.0 : 0.0;
  }
}

Eigen::VectorXd LstmNet::initial_params(std::uint64_t seed) const {
  std::mt19937_64 rng(seed);
  const double r = 1.0 / std::sqrt(static_cast<double>(shape_.hidden));
  std::uniform_real_distribution<double> u(-r, r);
  Eigen::VectorXd p(static_cast<Eigen::Index>(num_params_));
  for (Eigen::Index i = 0; i < p.size(); ++i) p[i] = u(rng);
  const Eigen::Index H = shape_.hidden;
  for (int l = 0; l < shape_.layers; ++l) {
    const Eigen::Index b = layer_offset_[l] + 4 * H * layer_inputs(l) + 4 * H * H;
    p.segment(b, 4 * H).setZero();
    p.segment(b + H, H).setConstant(1.0);  // remember by default: forget gate open
  }
  p[head_offset_ + H] = 0.0;
  return p;
}

namespace {
// A named namespace inside: the core is a unity build, so short names here could meet another file's.
namespace lstm_kernels {

// The kernels below are plain loops over vectors of doubles (GCC vector extensions), written once as
// templates and compiled twice: four-wide for AVX2 and two-wide for the SSE2 baseline (what Eigen and the
// rest of the code are built for); the CPU picks one at load time (function multiversioning). Every element
// goes through the same IEEE operations in the same order in both (AVX2 has no FMA, so nothing is fused; no
// sum runs across lanes), so every CPU gives the same bits.
using Index = Eigen::Index;
using Lanes4 = double __attribute__((vector_size(32)));
using Lanes2 = double __attribute__((vector_size(16)));

// Per vector type: its width, an alias at the alignment of a double (loads and stores at any address, by
// reference, since passing 32-byte vectors by value would mean two calling conventions), its integer bits.
template <class V>
struct Vec {
  static constexpr Index width = 1;
  using unaligned = double;
  using bits = std::uint64_t;
};
template <>
struct Vec<Lanes4> {
  static constexpr Index width = 4;
  using unaligned = double __attribute__((vector_size(32), aligned(8), may_alias));
  using bits = std::uint64_t __attribute__((vector_size(32)));
};
template <>
struct Vec<Lanes2> {
  static constexpr Index width = 2;
  using unaligned = double __attribute__((vector_size(16), aligned(8), may_alias));
  using bits = std::uint64_t __attribute__((vector_size(16)));
};
template <class V>
__attribute__((always_inline)) inline const typename Vec<V>::unaligned& at(const double* p) {
  return *reinterpret_cast<const typename Vec<V>::unaligned*>(p);
}
template <class V>
__attribute__((always_inline)) inline typename Vec<V>::unaligned& at(double* p) {
  return *reinterpret_cast<typename Vec<V>::unaligned*>(p);
}

// e^x, element by element: x clamped to ±708 (the result stays a normal number; NaN passes through),
// x = n ln 2 + r with |r| ≤ ln 2 / 2 (n rounded by adding and subtracting 1.5·2^52, ln 2 in two parts so that
// n ln 2 is exact), e^r by its Taylor polynomial to r^13 (truncation < 1e-17 relative), times 2^n written
// into the exponent bits. No library call, so it vectorises; within 1 ulp of std::exp.
template <class V>
__attribute__((always_inline)) inline void exp_in_place(V& x) {
  using Bits = typename Vec<V>::bits;
  const V lo = V{} - 708.0, hi = V{} + 708.0;
  x = x < lo ? lo : x;
  x = x > hi ? hi : x;
  const double shifter = 0x1.8p52;
  const V t = x * 0x1.71547652b82fep0 + shifter;  // 1 / ln 2
  const V n = t - shifter;
  const V r = (x - n * 0x1.62e42feep-1) - n * 0x1.a39ef35793c76p-33;  // ln 2 = hi + lo, hi with 32 zero bits
  // 1 + r + r² Σ_{i=2}^{13} r^{i−2} / i!, the sum by Estrin's scheme (pairs, then powers r², r⁴, r⁸: a short
  // dependency chain); the leading 1 + r added last keeps the result within 1 ulp.
  const V r2 = r * r, r4 = r2 * r2, r8 = r4 * r4;
  const V a0 = 1.0 / 2 + r * (1.0 / 6), a1 = 1.0 / 24 + r * (1.0 / 120), a2 = 1.0 / 720 + r * (1.0 / 5040);
  const V a3 = 1.0 / 40320 + r * (1.0 / 362880), a4 = 1.0 / 3628800 + r * (1.0 / 39916800);
  const V a5 = 1.0 / 479001600 + r * (1.0 / 6227020800);
  const V p = 1.0 + (r + r2 * ((a0 + a1 * r2) + (a2 + a3 * r2) * r4 + (a4 + a5 * r2) * r8));
  // t's low mantissa bits hold 2^51 + n; shifted by 52 only n + 1023 (in 1 … 2045) stays: the bits of 2^n.
  Bits b;
  std::memcpy(&b, &t, sizeof b);
  b = (b + 1023) << 52;
  V scale;
  std::memcpy(&scale, &b, sizeof scale);
  x = p * scale;
}

// C (m × n, column-major, ldc) += A · B: A m × k column-major (lda), B(p, j) = b[p·bk + j·bn]; m a multiple
// of 4. Each element is a sum from zero over p in order, then added to C. Columns in groups of 4 with 2
// vectors of rows (8 sums in registers), the remaining columns (a matrix–vector product) with 4 vectors of
// rows: enough independent sums that the adds' latency does not set the pace.
template <class V>
__attribute__((always_inline)) inline void gemm_nn_impl(Index m, Index n, Index k, const double* __restrict a,
                                                        Index lda, const double* __restrict b, Index bk,
                                                        Index bn, double* __restrict c, Index ldc) {
  constexpr Index w = Vec<V>::width;
  Index j = 0;
  for (; j + 4 <= n; j += 4) {
    Index i = 0;
    for (; i + 2 * w <= m; i += 2 * w) {
      // s<q><r>: column j + q, first (r = 0) and second (r = 1) vector of rows
      V s00{}, s01{}, s10{}, s11{}, s20{}, s21{}, s30{}, s31{};
      const double* ap = a + i;
      const double* bp = b + j * bn;
      for (Index p = 0; p < k; ++p, ap += lda, bp += bk) {
        const V x0 = at<V>(ap), x1 = at<V>(ap + w);
        const double b0 = bp[0], b1 = bp[bn], b2 = bp[2 * bn], b3 = bp[3 * bn];
        s00 += x0 * b0, s01 += x1 * b0, s10 += x0 * b1, s11 += x1 * b1;
        s20 += x0 * b2, s21 += x1 * b2, s30 += x0 * b3, s31 += x1 * b3;
      }
      double* cp = c + i + j * ldc;
      at<V>(cp) += s00, at<V>(cp + w) += s01, cp += ldc;
      at<V>(cp) += s10, at<V>(cp + w) += s11, cp += ldc;
      at<V>(cp) += s20, at<V>(cp + w) += s21, cp += ldc;
      at<V>(cp) += s30, at<V>(cp + w) += s31;
    }
    for (; i < m; i += w) {
      V s0{}, s1{}, s2{}, s3{};
      const double* ap = a + i;
      const double* bp = b + j * bn;
      for (Index p = 0; p < k; ++p, ap += lda, bp += bk) {
        const V x = at<V>(ap);
        s0 += x * bp[0], s1 += x * bp[bn], s2 += x * bp[2 * bn], s3 += x * bp[3 * bn];
      }
      double* cp = c + i + j * ldc;
      at<V>(cp) += s0, at<V>(cp + ldc) += s1, at<V>(cp + 2 * ldc) += s2, at<V>(cp + 3 * ldc) += s3;
    }
  }
  for (; j < n; ++j) {
    Index i = 0;
    for (; i + 4 * w <= m; i += 4 * w) {
      V s0{}, s1{}, s2{}, s3{};
      const double* ap = a + i;
      const double* bp = b + j * bn;
      for (Index p = 0; p < k; ++p, ap += lda, bp += bk) {
        const double bv = bp[0];
        s0 += at<V>(ap) * bv, s1 += at<V>(ap + w) * bv, s2 += at<V>(ap + 2 * w) * bv,
            s3 += at<V>(ap + 3 * w) * bv;
      }
      double* cp = c + i + j * ldc;
      at<V>(cp) += s0, at<V>(cp + w) += s1, at<V>(cp + 2 * w) += s2, at<V>(cp + 3 * w) += s3;
    }
    for (; i < m; i += w) {
      V s{};
      const double* ap = a + i;
      const double* bp = b + j * bn;
      for (Index p = 0; p < k; ++p, ap += lda, bp += bk) s += at<V>(ap) * bp[0];
      at<V>(c + i + j * ldc) += s;
    }
  }
}

// Gate pre-activations (rows = 4H × n, contiguous) → activations in place, per row
// y = ca / (1 + e^{nk·z}) + cb with coef = [nk; ca; cb] (3 × rows): the sigmoid (nk = −1, ca = 1, cb = 0) for
// i, f, o and tanh(z) = 2 / (1 + e^{−2z}) − 1 (nk = −2, ca = 2, cb = −1) for g.
template <class V>
__attribute__((always_inline)) inline void activate_impl(double* g, const double* coef, Index rows, Index n) {
  const double *nk = coef, *ca = coef + rows, *cb = coef + 2 * rows;
  for (Index col = 0; col < n; ++col, g += rows)
    for (Index r = 0; r < rows; r += Vec<V>::width) {
      V e = at<V>(nk + r) * at<V>(g + r);
      exp_in_place(e);
      at<V>(g + r) = at<V>(ca + r) / (1.0 + e) + at<V>(cb + r);
    }
}

// The new state from the activated gates (4H × n): c = f c_prev + i g,
// tanh_c = tanh(c) = 2 / (1 + e^{−2c}) − 1, h = o tanh_c; H × n each, contiguous. c may alias c_prev.
template <class V>
__attribute__((always_inline)) inline void cell_at(const double* gi, Index H, const double* cp, double* c,
                                                   double* tc, double* h) {
  const V cn = at<V>(gi + H) * at<V>(cp) + at<V>(gi) * at<V>(gi + 2 * H);
  V e = -2.0 * cn;
  exp_in_place(e);
  const V t = 2.0 / (1.0 + e) - 1.0;
  at<V>(c) = cn, at<V>(tc) = t, at<V>(h) = at<V>(gi + 3 * H) * t;
}
template <class V>
__attribute__((always_inline)) inline void cell_impl(const double* g, const double* c_prev, double* c,
                                                     double* tanh_c, double* h, Index H, Index n) {
  constexpr Index w = Vec<V>::width;
  for (Index col = 0; col < n; ++col) {
    const double* gi = g + col * 4 * H;
    const Index o = col * H;
    Index r = 0;
    for (; r + w <= H; r += w) cell_at<V>(gi + r, H, c_prev + o + r, c + o + r, tanh_c + o + r, h + o + r);
    for (; r < H; ++r) cell_at<double>(gi + r, H, c_prev + o + r, c + o + r, tanh_c + o + r, h + o + r);
  }
}

// One step back through the cell (H × n; a: the activated gates, 4H × n, overwritten with dA, the gradient of
// the pre-activations): dh = from_above + dh_next (both with leading dimension ld),
// dc = dc_next + dh o (1 − tanh_c²); dc_next ← dc f.
template <class V>
__attribute__((always_inline)) inline void cell_back_at(double* a, Index H, const double* tc_p,
                                                        const double* cp_p, const double* fa_p,
                                                        const double* dhn_p, double* dcn_p) {
  const V i = at<V>(a), f = at<V>(a + H), g = at<V>(a + 2 * H), o = at<V>(a + 3 * H), tc = at<V>(tc_p);
  const V dh = at<V>(fa_p) + at<V>(dhn_p);
  const V dc = at<V>(dcn_p) + dh * o * (1.0 - tc * tc);
  at<V>(dcn_p) = dc * f;
  at<V>(a) = dc * g * i * (1.0 - i);
  at<V>(a + H) = dc * at<V>(cp_p) * f * (1.0 - f);
  at<V>(a + 2 * H) = dc * i * (1.0 - g * g);
  at<V>(a + 3 * H) = dh * tc * o * (1.0 - o);
}
template <class V>
__attribute__((always_inline)) inline void cell_backward_impl(double* a, const double* tanh_c,
                                                              const double* c_prev, const double* from_above,
                                                              const double* dh_next, Index ld,
                                                              double* dc_next, Index H, Index n) {
  constexpr Index w = Vec<V>::width;
  for (Index col = 0; col < n; ++col) {
    double* ac = a + col * 4 * H;
    const Index o = col * H, od = col * ld;
    Index r = 0;
    for (; r + w <= H; r += w)
      cell_back_at<V>(ac + r, H, tanh_c + o + r, c_prev + o + r, from_above + od + r, dh_next + od + r,
                      dc_next + o + r);
    for (; r < H; ++r)
      cell_back_at<double>(ac + r, H, tanh_c + o + r, c_prev + o + r, from_above + od + r, dh_next + od + r,
                           dc_next + o + r);
  }
}

// The two versions of each kernel.
#define PIEZO_LSTM_KERNEL(name, params, args)                                    \
  __attribute__((target("avx2"))) void name params { name##_impl<Lanes4> args; } \
  __attribute__((target("default"))) void name params { name##_impl<Lanes2> args; }
PIEZO_LSTM_KERNEL(gemm_nn,
                  (Index m, Index n, Index k, const double* a, Index lda, const double* b, Index bk, Index bn,
                   double* c, Index ldc),
                  (m, n, k, a, lda, b, bk, bn, c, ldc))
PIEZO_LSTM_KERNEL(activate, (double* g, const double* coef, Index rows, Index n), (g, coef, rows, n))
PIEZO_LSTM_KERNEL(cell,
                  (const double* g, const double* c_prev, double* c, double* tanh_c, double* h, Index H,
                   Index n),
                  (g, c_prev, c, tanh_c, h, H, n))
PIEZO_LSTM_KERNEL(cell_backward,
                  (double* a, const double* tanh_c, const double* c_prev, const double* from_above,
                   const double* dh_next, Index ld, double* dc_next, Index H, Index n),
                  (a, tanh_c, c_prev, from_above, dh_next, ld, dc_next, H, n))
#undef PIEZO_LSTM_KERNEL

// The head, w·h + b, summed in order (the streaming step and the training loss use it alike).
inline double head(const double* w, const double* h, Index H) {
  double y = w[H];
  for (Index j = 0; j < H; ++j) y += w[j] * h[j];
  return y;
}

// Buffers of sequence_loss_grad, kept per thread: the trainer calls it thousands of times with the same
// shapes.
struct Workspace {
  Eigen::MatrixXd h, c, gates, tanh_c, gates_tmp, tanh_c_tmp, proj, err, from_above, dh_next, dc_next,
      transposed;
  Eigen::RowVectorXd dy;
};

// Columns (time steps × batch) of layer 0's input projection computed in one product when the steps are not
// kept for the gradient: large enough for an efficient product, small enough to stay in cache for large
// batches.
constexpr Index kProjectionColumns = 512;

// One call of sequence_loss_grad: the shapes, the parameter blocks and the views into the workspace that its
// forward and backward passes share. Storage, all H- or 4H-row matrices of B-column blocks: with the gradient
// (keep) every scored step is kept, per layer the states h, c of slots 0 (after the warm-up) … T and the
// gates and tanh(c) of steps 0 … T − 1; the warm-up (and without the gradient every step) updates slot 0 in
// place.
struct SequencePass {
  SequencePass(const double* params, const std::vector<Index>& layer_offset, Index head_offset,
               const double* gate_coef, const LstmShape& shape, Index T, Index B, int warmup, bool keep,
               const Eigen::MatrixXd& x, Workspace& ws)
      : P(params),
        layer_offset(layer_offset),
        head_offset(head_offset),
        gate_coef(gate_coef),
        inputs(shape.inputs),
        H(shape.hidden),
        H4(4 * H),
        T(T),
        B(B),
        S(warmup + T),
        TB(T * B),
        L(shape.layers),
        warmup(warmup),
        keep(keep),
        slots(keep ? T + 1 : 1),
        x(x),
        ws(ws) {}

  const double* P;
  const std::vector<Index>& layer_offset;
  Index head_offset;
  const double* gate_coef;
  Index inputs, H, H4, T, B, S, TB;
  int L, warmup;
  bool keep;
  Index slots;
  const Eigen::MatrixXd& x;
  Workspace& ws;

  Index layer_inputs(int l) const { return l == 0 ? inputs : H; }
  // 4H × inputs of layer l, then U (4H × H), then b (4H)
  const double* W(int l) const { return P + layer_offset[l]; }
  const double* U(int l) const { return P + layer_offset[l] + H4 * layer_inputs(l); }
  Eigen::Map<const Eigen::VectorXd> bias(int l) const {
    return Eigen::Map<const Eigen::VectorXd>(U(l) + H4 * H, H4);
  }
  const double* head_weights() const { return P + head_offset; }
  double* hs(int l, Index s) const { return ws.h.data() + (l * slots + s) * B * H; }
  double* cs(int l, Index s) const { return ws.c.data() + (l * slots + s) * B * H; }
  double* gates(int l, Index t) const { return ws.gates.data() + (l * T + t) * B * H4; }
  double* tanh_c(int l, Index t) const { return ws.tanh_c.data() + (l * T + t) * B * H; }

  void allocate();
  // Layer 0's input projections b + W x do not depend on the state: one product over a run of steps.
  void project(Index tau0, Index n, double* dst) const;
  // The gate block of layer 0 at step tau (its projection is computed here when due).
  double* layer0_gates(Index tau, Index& proj_begin, Index& proj_end) const;
  // All layers forward over the warm-up and the scored steps; returns Σ squared errors (ws.err per step).
  double forward(const Eigen::MatrixXd& ys) const;
  // The products with Uᵀ and Wᵀ take them transposed, padded with zero rows to Hp (a multiple of 4).
  const double* transpose_padded(const double* m, Index Hp) const;
  // Backward, layer by layer from the top; adds the gradient to *grad.
  void backward(Eigen::VectorXd* grad) const;
  void backward_layer(int l, Index Hp, Eigen::VectorXd* grad) const;
};

void SequencePass::allocate() {
  ws.h.resize(H, L * slots * B);
  ws.c.resize(H, L * slots * B);
  if (keep) {
    ws.gates.resize(H4, L * TB);
    ws.tanh_c.resize(H, L * TB);
  }
  ws.gates_tmp.resize(H4, B);
  ws.tanh_c_tmp.resize(H, B);
  ws.err.resize(B, T);
  for (int l = 0; l < L; ++l) {
    Eigen::Map<Eigen::MatrixXd>(hs(l, 0), H, B).setZero();
    Eigen::Map<Eigen::MatrixXd>(cs(l, 0), H, B).setZero();
  }
}

void SequencePass::project(Index tau0, Index n, double* dst) const {
  Eigen::Map<Eigen::MatrixXd>(dst, H4, n * B).colwise() = bias(0);
  gemm_nn(H4, n * B, inputs, W(0), H4, x.data() + tau0 * B * inputs, 1, inputs, dst, H4);
}

double* SequencePass::layer0_gates(Index tau, Index& proj_begin, Index& proj_end) const {
  if (keep && tau >= warmup) {
    const Index t = tau - warmup;
    if (tau == warmup) project(warmup, T, gates(0, 0));
    return gates(0, t);
  }
  if (tau >= proj_end) {
    const Index chunk = std::max<Index>(1, kProjectionColumns / B);
    const Index n = std::min(chunk, (keep ? warmup : S) - tau);
    ws.proj.resize(H4, n * B);
    project(tau, n, ws.proj.data());
    proj_begin = tau;
    proj_end = tau + n;
  }
  return ws.proj.data() + (tau - proj_begin) * B * H4;
}

double SequencePass::forward(const Eigen::MatrixXd& ys) const {
  Index proj_begin = 0, proj_end = 0;  // the steps whose projections are in ws.proj
  for (Index tau = 0; tau < S; ++tau) {
    const bool kept = keep && tau >= warmup;
    const Index t = tau - warmup, si = kept ? t : 0, so = kept ? t + 1 : 0;
    for (int l = 0; l < L; ++l) {
      double* g;
      if (l == 0) {
        g = layer0_gates(tau, proj_begin, proj_end);
      } else {
        g = kept ? gates(l, t) : ws.gates_tmp.data();
        Eigen::Map<Eigen::MatrixXd>(g, H4, B).colwise() = bias(l);
        gemm_nn(H4, B, H, W(l), H4, hs(l - 1, so), 1, H, g, H4);
      }
      gemm_nn(H4, B, H, U(l), H4, hs(l, si), 1, H, g, H4);
      activate(g, gate_coef, H4, B);
      cell(g, cs(l, si), cs(l, so), kept ? tanh_c(l, t) : ws.tanh_c_tmp.data(), hs(l, so), H, B);
    }
    if (tau >= warmup)
      for (Index j = 0; j < B; ++j) ws.err(j, t) = head(head_weights(), hs(L - 1, so) + j * H, H) - ys(t, j);
  }
  return ws.err.squaredNorm();
}

const double* SequencePass::transpose_padded(const double* m, Index Hp) const {  // 4H × H → Hp × 4H
  ws.transposed.setZero(Hp, H4);
  ws.transposed.topRows(H) = Eigen::Map<const Eigen::MatrixXd>(m, H4, H).transpose();
  return ws.transposed.data();
}

// Within a layer only dh_next = Uᵀ dA is sequential; the weight gradients and what a layer passes down are
// one product each over all steps. dA overwrites the gates. dh_next and from_above have Hp rows (the last Hp
// − H zero).
void SequencePass::backward(Eigen::VectorXd* grad) const {
  using CMat = Eigen::Map<const Eigen::MatrixXd>;
  const Index Hp = (H + 3) / 4 * 4;
  ws.dy =
      2.0 * Eigen::Map<const Eigen::RowVectorXd>(ws.err.data(), TB);  // column t·B + j: step t, sequence j
  Eigen::Map<Eigen::VectorXd>(grad->data() + head_offset, H).noalias() +=
      CMat(hs(L - 1, 1), H, TB) * ws.dy.transpose();
  (*grad)[head_offset + H] += ws.dy.sum();
  ws.from_above.setZero(Hp, TB);
  ws.from_above.topRows(H).noalias() = Eigen::Map<const Eigen::VectorXd>(head_weights(), H) * ws.dy;
  ws.dh_next.resize(Hp, B);
  ws.dc_next.resize(H, B);
  for (int l = L - 1; l >= 0; --l) backward_layer(l, Hp, grad);
}

void SequencePass::backward_layer(int l, Index Hp, Eigen::VectorXd* grad) const {
  using CMat = Eigen::Map<const Eigen::MatrixXd>;
  ws.dh_next.setZero();
  ws.dc_next.setZero();
  const double* ut = transpose_padded(U(l), Hp);
  for (Index t = T - 1; t >= 0; --t) {
    cell_backward(gates(l, t), tanh_c(l, t), cs(l, t), ws.from_above.data() + t * B * Hp, ws.dh_next.data(),
                  Hp, ws.dc_next.data(), H, B);
    if (t > 0) {
      ws.dh_next.setZero();
      gemm_nn(Hp, B, H4, ut, Hp, gates(l, t), 1, H4, ws.dh_next.data(), Hp);
    }
  }
  const Index in = layer_inputs(l);
  double* gp = grad->data() + layer_offset[l];
  const double* input = l == 0 ? x.data() + warmup * B * in : hs(l - 1, 1);
  gemm_nn(H4, in, TB, gates(l, 0), H4, input, in, 1, gp, H4);
  gemm_nn(H4, H, TB, gates(l, 0), H4, hs(l, 0), H, 1, gp + H4 * in, H4);
  Eigen::Map<Eigen::VectorXd>(gp + H4 * (in + H), H4) += CMat(gates(l, 0), H4, TB).rowwise().sum();
  if (l > 0) {
    ws.from_above.setZero();
    gemm_nn(Hp, TB, H4, transpose_padded(W(l), Hp), Hp, gates(l, 0), 1, H4, ws.from_above.data(), Hp);
  }
}

}  // namespace lstm_kernels
}  // namespace

double LstmNet::step(const double* params, const double* x, const double* h_in, const double* c_in,
                     double* h_out, double* c_out) const {
  using namespace lstm_kernels;
  const Index H = shape_.hidden, H4 = 4 * H;
  double g[4 * kMaxHidden], tc[kMaxHidden];
  const double* input = x;
  for (int l = 0; l < shape_.layers; ++l) {
    const Index in = layer_inputs(l);
    const double* p = params + layer_offset_[l];
    // The sums in the order of sequence_loss_grad: b, + W·input, + U·h.
    std::copy(p + H4 * (in + H), p + H4 * (in + H + 1), g);
    gemm_nn(H4, 1, in, p, H4, input, 1, in, g, H4);
    gemm_nn(H4, 1, H, p + H4 * in, H4, h_in + l * H, 1, H, g, H4);
    activate(g, gate_coef_.data(), H4, 1);
    cell(g, c_in + l * H, c_out + l * H, tc, h_out + l * H, H, 1);
    input = h_out + l * H;
  }
  return head(params + head_offset_, input, H);
}

double LstmNet::sequence_loss_grad(const Eigen::VectorXd& params, const std::vector<Eigen::MatrixXd>& xs,
                                   const Eigen::MatrixXd& ys, int warmup, Eigen::VectorXd* grad) const {
  const Eigen::Index B = ys.cols();
  if (static_cast<Eigen::Index>(xs.size()) != warmup + ys.rows())
    throw std::runtime_error("lstm: sequence length mismatch");
  Eigen::MatrixXd x(shape_.inputs, static_cast<Eigen::Index>(xs.size()) * B);
  for (std::size_t k = 0; k < xs.size(); ++k) {
    if (xs[k].rows() != shape_.inputs || xs[k].cols() != B)
      throw std::runtime_error("lstm: input block shape mismatch");
    x.middleCols(static_cast<Eigen::Index>(k) * B, B) = xs[k];
  }
  return sequence_loss_grad(params, x, ys, warmup, grad);
}

double LstmNet::sequence_loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x,
                                   const Eigen::MatrixXd& ys, int warmup, Eigen::VectorXd* grad) const {
  using namespace lstm_kernels;
  const Index T = ys.rows(), B = ys.cols(), S = warmup + T;
  if (warmup < 0 || x.rows() != shape_.inputs || x.cols() != S * B)
    throw std::runtime_error("lstm: sequence length mismatch");
  if (T == 0 || B == 0) return 0.0;
  thread_local Workspace ws;
  SequencePass pass(params.data(), layer_offset_, head_offset_, gate_coef_.data(), shape_, T, B, warmup,
                    grad != nullptr, x, ws);
  pass.allocate();
  const double loss = pass.forward(ys);
  if (!grad) return loss;
  pass.backward(grad);
  return loss;
}

// ---- model --------------------------------------------------------------------------------------------------

LstmModel::LstmModel(const features::FeatureSpec& spec, double sample_rate_hz, const LstmShape& shape,
                     Eigen::VectorXd params, TargetScale target, int warmup)
    : stream_(spec, sample_rate_hz), sample_rate_hz_(sample_rate_hz), net_(shape), params_(std::move(params)),
      target_(target), warmup_(warmup) {
  if (static_cast<int>(spec.size()) != shape.inputs)
    throw std::runtime_error("lstm: the feature spec has " + std::to_string(spec.size()) +
                             " features but the network expects " + std::to_string(shape.inputs));
  if (static_cast<std::size_t>(params_.size()) != net_.num_params())
    throw std::runtime_error("lstm: weight count does not match the architecture");
  if (warmup_ < 0) throw std::runtime_error("lstm: warmup must be ≥ 0");
  h_.assign(static_cast<std::size_t>(shape.layers * shape.hidden), 0.0);
  c_ = h_;
  meta.sample_rate_hz = sample_rate_hz;
}

void LstmModel::reset(double voltage_v, double position_nm) {
  stream_.reset(voltage_v, position_nm);
  std::fill(h_.begin(), h_.end(), 0.0);
  std::fill(c_.begin(), c_.end(), 0.0);
  if (!stream_.spec().aux_signals().empty()) return;  // aux values unknown at rest: start from the zero state
  // The same gradient-free warm-up from zero that every training window had, here at rest.
  double x[256];
  stream_.compute(ModelInput{voltage_v, nullptr}, x);
  for (int k = 0; k < warmup_; ++k) net_.step(params_.data(), x, h_.data(), c_.data(), h_.data(), c_.data());
}

double LstmModel::predict(const ModelInput& in) const {
  double x[256], h[LstmNet::kMaxLayers * LstmNet::kMaxHidden], c[LstmNet::kMaxLayers * LstmNet::kMaxHidden];
  stream_.compute(in, x);
  return target_.to_nm(net_.step(params_.data(), x, h_.data(), c_.data(), h, c));
}

void LstmModel::commit(const ModelInput& in, double position_nm) {
  double x[256];
  stream_.compute(in, x);
  net_.step(params_.data(), x, h_.data(), c_.data(), h_.data(), c_.data());
  stream_.commit(in, position_nm);
}

YAML::Node LstmModel::to_yaml() const {
  YAML::Node n;
  n["sample_rate_hz"] = sample_rate_hz_;
  n["features"] = stream_.spec().to_yaml();
  n["target"] = target_.to_yaml();
  n["hyperparameters"]["layers"] = net_.shape().layers;
  n["hyperparameters"]["hidden"] = net_.shape().hidden;
  n["hyperparameters"]["warmup"] = warmup_;
  if (training_info) n["training"] = training_info;
  n["weights"] = yaml_list(params_);
  return n;
}

std::unique_ptr<LstmModel> LstmModel::from_yaml(const YAML::Node& node) {
  const NeuralFileHeader header = read_neural_file_header(node, "lstm", {"layers", "hidden", "warmup"});
  const YAML::Node h = header.hyperparameters;
  LstmShape shape;
  shape.inputs = static_cast<int>(header.spec.size());
  shape.layers = yaml_int(h, "layers", 1, 8, "model.hyperparameters");
  shape.hidden = yaml_int(h, "hidden", 1, 256, "model.hyperparameters");
  const int warmup = yaml_int(h, "warmup", 0, 100000, "model.hyperparameters");
  const LstmNet net(shape);
  const std::vector<double> w = yaml_numbers(node, "weights", static_cast<long>(net.num_params()));
  auto m = std::make_unique<LstmModel>(header.spec, header.sample_rate_hz, shape,
                                       Eigen::Map<const Eigen::VectorXd>(w.data(), static_cast<Eigen::Index>(w.size())),
                                       header.target, warmup);
  if (node["training"]) m->training_info = node["training"];
  return m;
}

}  // namespace piezo::models
