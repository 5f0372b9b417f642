// KAN: the B-spline basis and the network (forward, gradient, grid update).
#include "piezo_compensation/models/kan_model.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/activations.h"

namespace piezo::models {

namespace {
constexpr int kMaxOrder = 5;
constexpr int kMaxGrid = 64;
}  // namespace

namespace {
// Cox–de Boor on the k+1 basis functions that can be non-zero at x. inv (optional) holds 1/(t[i+j]−t[i]) at
// inv[(j−1)·m + i] (0 for empty spans); without it the spans are divided directly.
inline bool basis_impl(const double* t, const double* inv, int m, int k, double x, int* first, double* values,
                       double* derivatives) {
  if (!(x >= t[0] && x < t[m - 1])) return false;
  int lo = 0, hi = m - 1;
  while (hi - lo > 1) {
    const int mid = (lo + hi) / 2;
    (x >= t[mid] ? lo : hi) = mid;
  }
  const int s = lo;
  auto rspan = [&](int i, int j) {
    if (inv) return inv[(j - 1) * m + i];
    const double d = t[i + j] - t[i];
    return d > 0.0 ? 1.0 / d : 0.0;
  };
  // N[r] = B_{s-j+r}^{j}(x); indices outside 0 … m-2-j are zero.
  double N[kMaxOrder + 1] = {1.0}, prev[kMaxOrder + 1] = {0.0};
  for (int j = 1; j <= k; ++j) {
    std::copy(N, N + j, prev);
    for (int r = 0; r <= j; ++r) {
      const int i = s - j + r;
      double v = 0.0;
      if (i >= 0 && i <= m - 2 - j) {
        if (r >= 1) v += (x - t[i]) * rspan(i, j) * prev[r - 1];
        if (r <= j - 1) v += (t[i + j + 1] - x) * rspan(i + 1, j) * prev[r];
      }
      N[r] = v;
    }
  }
  if (derivatives) {
    // B_i^k' = k/(t_{i+k}-t_i) B_i^{k-1} − k/(t_{i+k+1}-t_{i+1}) B_{i+1}^{k-1}; prev holds order k-1.
    for (int r = 0; r <= k; ++r) {
      const int i = s - k + r;
      double d = 0.0;
      if (k > 0 && i >= 0 && i <= m - 2 - k) {
        if (r >= 1) d += k * rspan(i, k) * prev[r - 1];
        if (r <= k - 1) d -= k * rspan(i + 1, k) * prev[r];
      }
      derivatives[r] = d;
    }
  }
  std::copy(N, N + k + 1, values);
  *first = s - k;
  return true;
}
}  // namespace

bool bspline_basis(const double* t, int m, int k, double x, int* first, double* values, double* derivatives) {
  return basis_impl(t, nullptr, m, k, x, first, values, derivatives);
}

namespace {
// Knots: `grid`+1 points on [lo, hi] extended by `order` equal steps each side.
std::vector<double> make_knots(const std::vector<double>& points, int order) {
  const int G = static_cast<int>(points.size()) - 1;
  const double h = (points.back() - points.front()) / G;
  std::vector<double> t;
  for (int r = order; r >= 1; --r) t.push_back(points.front() - r * h);
  t.insert(t.end(), points.begin(), points.end());
  for (int r = 1; r <= order; ++r) t.push_back(points.back() + r * h);
  return t;
}
}  // namespace

KanNet::KanNet(const KanShape& shape) : shape_(shape) {
  if (shape.widths.size() < 2) throw std::runtime_error("kan: widths needs at least inputs and outputs");
  if (shape.widths.back() != 1) throw std::runtime_error("kan: the last width must be 1 (one position)");
  for (int w : shape.widths)
    if (w < 1 || w > kMaxWidth) throw std::runtime_error("kan: every width must be in 1..64");
  if (shape.grid < 1 || shape.grid > kMaxGrid) throw std::runtime_error("kan: grid must be in 1..64");
  if (shape.order < 0 || shape.order > kMaxOrder) throw std::runtime_error("kan: order must be in 0..5");
  Eigen::Index o = 0;
  std::vector<double> uniform;
  for (int q = 0; q <= shape.grid; ++q) uniform.push_back(-2.0 + 4.0 * q / shape.grid);
  const std::vector<double> t = make_knots(uniform, shape.order);
  for (int l = 0; l < num_layers(); ++l) {
    const int in = shape.widths[static_cast<std::size_t>(l)], out = shape.widths[static_cast<std::size_t>(l + 1)];
    layer_offset_.push_back(o);
    o += static_cast<Eigen::Index>(in) * out * (1 + num_basis());
    bias_offset_.push_back(o);
    o += out;
    std::vector<double> g;
    for (int i = 0; i < in; ++i) g.insert(g.end(), t.begin(), t.end());
    grids_.push_back(std::move(g));
  }
  num_params_ = static_cast<std::size_t>(o);
  inv_spans_.resize(grids_.size());
  for (int l = 0; l < num_layers(); ++l) update_inv_spans(l);
}

void KanNet::update_inv_spans(int layer) {
  const int m = num_knots(), k = shape_.order, in = shape_.widths[static_cast<std::size_t>(layer)];
  const std::vector<double>& g = grids_[static_cast<std::size_t>(layer)];
  std::vector<double>& inv = inv_spans_[static_cast<std::size_t>(layer)];
  inv.assign(static_cast<std::size_t>(in * std::max(k, 1) * m), 0.0);
  for (int node = 0; node < in; ++node)
    for (int j = 1; j <= k; ++j)
      for (int i = 0; i + j < m; ++i) {
        const double d = g[static_cast<std::size_t>(node * m + i + j)] - g[static_cast<std::size_t>(node * m + i)];
        inv[static_cast<std::size_t>(node * k * m + (j - 1) * m + i)] = d > 0.0 ? 1.0 / d : 0.0;
      }
}

void KanNet::set_grid(int layer, std::vector<double> knots) {
  if (layer < 0 || layer >= num_layers()) throw std::runtime_error("kan: no layer " + std::to_string(layer));
  const int m = num_knots();
  if (knots.size() != grids_[static_cast<std::size_t>(layer)].size())
    throw std::runtime_error("kan: grid of layer " + std::to_string(layer) + " has the wrong size");
  for (std::size_t i = 0; i < knots.size(); ++i)
    if (i % static_cast<std::size_t>(m) != 0 && !(knots[i] > knots[i - 1]))
      throw std::runtime_error("kan: grids[" + std::to_string(layer) + "] knots must increase");
  grids_[static_cast<std::size_t>(layer)] = std::move(knots);
  update_inv_spans(layer);
}

bool KanNet::basis(int layer, int input, double x, int* first, double* values, double* derivatives) const {
  const int m = num_knots(), k = shape_.order;
  return basis_impl(knots(layer, input), inv_spans_[static_cast<std::size_t>(layer)].data() + input * k * m, m, k, x,
                    first, values, derivatives);
}

Eigen::Index KanNet::edge_offset(int layer, int input, int output) const {
  const int out = shape_.widths[static_cast<std::size_t>(layer + 1)];
  return layer_offset_[static_cast<std::size_t>(layer)] +
         static_cast<Eigen::Index>(input * out + output) * (1 + num_basis());
}

const double* KanNet::knots(int layer, int input) const {
  return grids_[static_cast<std::size_t>(layer)].data() + static_cast<std::size_t>(input * num_knots());
}

Eigen::VectorXd KanNet::initial_params(std::uint64_t seed) const {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n01;
  Eigen::VectorXd p = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(num_params_));
  for (int l = 0; l < num_layers(); ++l) {
    const int in = shape_.widths[static_cast<std::size_t>(l)], out = shape_.widths[static_cast<std::size_t>(l + 1)];
    const double s = 1.0 / std::sqrt(static_cast<double>(in));
    for (int i = 0; i < in; ++i)
      for (int j = 0; j < out; ++j) {
        const Eigen::Index e = edge_offset(l, i, j);
        p[e] = s * n01(rng);
        for (int b = 0; b < num_basis(); ++b) p[e + 1 + b] = 0.1 * s * n01(rng);
      }
  }
  return p;
}

double KanNet::edge(const double* params, int layer, int input, int output, double x) const {
  const double* e = params + edge_offset(layer, input, output);
  double y = e[0] * x * sigmoid(x);
  int first = 0;
  double v[kMaxOrder + 1];
  if (basis(layer, input, x, &first, v, nullptr))
    for (int r = 0; r <= shape_.order; ++r) {
      const int b = first + r;
      if (b >= 0 && b < num_basis()) y += e[1 + b] * v[r];
    }
  return y;
}

double KanNet::forward(const double* params, const double* x) const {
  double a[kMaxWidth], b[kMaxWidth], v[kMaxOrder + 1];
  const double* in = x;
  double* out = a;
  const int nb = num_basis(), k = shape_.order, stride = 1 + nb;
  for (int l = 0; l < num_layers(); ++l) {
    const int n_in = shape_.widths[static_cast<std::size_t>(l)], n_out = shape_.widths[static_cast<std::size_t>(l + 1)];
    const double* bias = params + bias_offset_[static_cast<std::size_t>(l)];
    for (int j = 0; j < n_out; ++j) out[j] = bias[j];
    for (int i = 0; i < n_in; ++i) {
      const double xi = in[i], silu = xi * sigmoid(xi);
      int first = 0;
      const bool any = basis(l, i, xi, &first, v, nullptr);
      const double* e = params + edge_offset(l, i, 0);
      for (int j = 0; j < n_out; ++j, e += stride) {
        double y = e[0] * silu;
        if (any)
          for (int r = 0; r <= k; ++r) {
            const int bi = first + r;
            if (bi >= 0 && bi < nb) y += e[1 + bi] * v[r];
          }
        out[j] += y;
      }
    }
    in = out;
    out = (out == a) ? b : a;
  }
  return in[0];
}

double KanNet::loss_grad(const Eigen::VectorXd& params, const Eigen::MatrixXd& x, const Eigen::VectorXd& y,
                         Eigen::VectorXd* grad) const {
  const int L = num_layers(), nb = num_basis(), k = shape_.order, stride = 1 + nb;
  // Per layer, per input node: value, SiLU, SiLU', basis window, basis values and derivatives.
  struct Node {
    double x, silu, dsilu;
    int first;
    bool any;
    double v[kMaxOrder + 1], dv[kMaxOrder + 1];
  };
  std::vector<std::vector<Node>> nodes(static_cast<std::size_t>(L));
  for (int l = 0; l < L; ++l) nodes[static_cast<std::size_t>(l)].resize(static_cast<std::size_t>(shape_.widths[static_cast<std::size_t>(l)]));
  const double* p = params.data();
  double* g = grad ? grad->data() : nullptr;
  double loss = 0.0;
  double buf_a[kMaxWidth], buf_b[kMaxWidth];
  for (Eigen::Index c = 0; c < x.cols(); ++c) {
    const double* in = x.col(c).data();
    double* out = buf_a;
    for (int l = 0; l < L; ++l) {
      const int n_in = shape_.widths[static_cast<std::size_t>(l)], n_out = shape_.widths[static_cast<std::size_t>(l + 1)];
      const double* bias = p + bias_offset_[static_cast<std::size_t>(l)];
      for (int j = 0; j < n_out; ++j) out[j] = bias[j];
      for (int i = 0; i < n_in; ++i) {
        Node& nd = nodes[static_cast<std::size_t>(l)][static_cast<std::size_t>(i)];
        nd.x = in[i];
        const double s = sigmoid(nd.x);
        nd.silu = nd.x * s;
        nd.dsilu = s * (1.0 + nd.x * (1.0 - s));
        nd.any = basis(l, i, nd.x, &nd.first, nd.v, grad ? nd.dv : nullptr);
        const double* e = p + edge_offset(l, i, 0);
        for (int j = 0; j < n_out; ++j, e += stride) {
          double yv = e[0] * nd.silu;
          if (nd.any)
            for (int r = 0; r <= k; ++r) {
              const int bi = nd.first + r;
              if (bi >= 0 && bi < nb) yv += e[1 + bi] * nd.v[r];
            }
          out[j] += yv;
        }
      }
      in = out;
      out = (out == buf_a) ? buf_b : buf_a;
    }
    const double err = in[0] - y[c];
    loss += err * err;
    if (!g) continue;
    double d_out[kMaxWidth], d_in[kMaxWidth];
    d_out[0] = 2.0 * err;
    for (int l = L - 1; l >= 0; --l) {
      const int n_in = shape_.widths[static_cast<std::size_t>(l)], n_out = shape_.widths[static_cast<std::size_t>(l + 1)];
      double* gbias = g + bias_offset_[static_cast<std::size_t>(l)];
      for (int j = 0; j < n_out; ++j) gbias[j] += d_out[j];
      for (int i = 0; i < n_in; ++i) {
        const Node& nd = nodes[static_cast<std::size_t>(l)][static_cast<std::size_t>(i)];
        const double* e = p + edge_offset(l, i, 0);
        double* ge = g + edge_offset(l, i, 0);
        double dx = 0.0;
        for (int j = 0; j < n_out; ++j, e += stride, ge += stride) {
          const double dj = d_out[j];
          ge[0] += dj * nd.silu;
          double slope = e[0] * nd.dsilu;
          if (nd.any)
            for (int r = 0; r <= k; ++r) {
              const int bi = nd.first + r;
              if (bi >= 0 && bi < nb) {
                ge[1 + bi] += dj * nd.v[r];
                slope += e[1 + bi] * nd.dv[r];
              }
            }
          dx += dj * slope;
        }
        d_in[i] = dx;
      }
      std::copy(d_in, d_in + n_in, d_out);
    }
  }
  return loss;
}

std::vector<Eigen::MatrixXd> KanNet::activations(const Eigen::VectorXd& params, const Eigen::MatrixXd& x) const {
  std::vector<Eigen::MatrixXd> acts{x};
  for (int l = 0; l < num_layers(); ++l) {
    const int n_in = shape_.widths[static_cast<std::size_t>(l)], n_out = shape_.widths[static_cast<std::size_t>(l + 1)];
    Eigen::MatrixXd next(n_out, x.cols());
    const Eigen::MatrixXd& a = acts.back();
    for (Eigen::Index c = 0; c < x.cols(); ++c)
      for (int j = 0; j < n_out; ++j) {
        double s = params[bias_offset_[static_cast<std::size_t>(l)] + j];
        for (int i = 0; i < n_in; ++i) s += edge(params.data(), l, i, j, a(i, c));
        next(j, c) = s;
      }
    acts.push_back(std::move(next));
  }
  return acts;
}

void KanNet::update_grids(Eigen::VectorXd& params, const Eigen::MatrixXd& x_all, double grid_eps) {
  // An evenly spaced subsample keeps this cheap on a million samples.
  const Eigen::Index n_all = x_all.cols();
  if (n_all < 2) return;
  const Eigen::Index n = std::min<Eigen::Index>(n_all, 2000);
  Eigen::MatrixXd x(x_all.rows(), n);
  for (Eigen::Index c = 0; c < n; ++c) x.col(c) = x_all.col(c * n_all / n);
  const std::vector<Eigen::MatrixXd> acts = activations(params, x);
  const int G = shape_.grid, k = shape_.order, nb = num_basis(), m = num_knots();
  for (int l = 0; l < num_layers(); ++l) {
    const int n_in = shape_.widths[static_cast<std::size_t>(l)], n_out = shape_.widths[static_cast<std::size_t>(l + 1)];
    for (int i = 0; i < n_in; ++i) {
      std::vector<double> xs(static_cast<std::size_t>(n));
      for (Eigen::Index c = 0; c < n; ++c) xs[static_cast<std::size_t>(c)] = acts[static_cast<std::size_t>(l)](i, c);
      std::sort(xs.begin(), xs.end());
      double lo = xs.front(), hi = xs.back();
      if (hi - lo < 1e-9) {
        lo -= 1.0;
        hi += 1.0;
      }
      std::vector<double> pts(static_cast<std::size_t>(G + 1));
      for (int q = 0; q <= G; ++q) {
        const double quant = xs[static_cast<std::size_t>(static_cast<double>(q) * static_cast<double>(n - 1) / G)];
        const double uni = lo + (hi - lo) * q / G;
        pts[static_cast<std::size_t>(q)] = grid_eps * uni + (1.0 - grid_eps) * quant;
      }
      pts.front() = lo;
      pts.back() = hi;
      for (int q = 1; q <= G; ++q)  // strictly increasing even with repeated values
        pts[static_cast<std::size_t>(q)] = std::max(pts[static_cast<std::size_t>(q)], pts[static_cast<std::size_t>(q - 1)] + 1e-6 * (hi - lo));
      const std::vector<double> t_new = make_knots(pts, k);
      // Refit every outgoing edge's spline part on the new knots by least squares.
      Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n, nb);
      double v[kMaxOrder + 1];
      for (Eigen::Index c = 0; c < n; ++c) {
        int first = 0;
        if (bspline_basis(t_new.data(), m, k, acts[static_cast<std::size_t>(l)](i, c), &first, v, nullptr))
          for (int r = 0; r <= k; ++r)
            if (first + r >= 0 && first + r < nb) A(c, first + r) = v[r];
      }
      Eigen::MatrixXd AtA = A.transpose() * A;
      AtA.diagonal().array() += 1e-8 * std::max(1.0, AtA.diagonal().maxCoeff());
      const Eigen::LDLT<Eigen::MatrixXd> ldlt(AtA);
      for (int j = 0; j < n_out; ++j) {
        const Eigen::Index e = edge_offset(l, i, j);
        Eigen::VectorXd s_old(n);
        for (Eigen::Index c = 0; c < n; ++c) {
          const double xv = acts[static_cast<std::size_t>(l)](i, c);
          s_old[c] = edge(params.data(), l, i, j, xv) - params[e] * xv * sigmoid(xv);
        }
        params.segment(e + 1, nb) = ldlt.solve(A.transpose() * s_old);
      }
      std::copy(t_new.begin(), t_new.end(), grids_[static_cast<std::size_t>(l)].begin() + static_cast<std::ptrdiff_t>(i * m));
    }
    update_inv_spans(l);
  }
}

}  // namespace piezo::models
