#include "piezo_compensation/models/kan_model.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <random>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/models/dense_model.h"

namespace piezo::models {

namespace {
constexpr int kMaxOrder = 5;
constexpr int kMaxGrid = 64;
double sigmoid(double z) { return 1.0 / (1.0 + std::exp(-z)); }
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

// ---- symbolic formulas --------------------------------------------------------------------------------------

namespace {

struct LinearFit {
  double a = 0, d = 0, r2 = -std::numeric_limits<double>::infinity();
};

// y ≈ a·u + d by least squares, with R².
LinearFit fit_affine(const std::vector<double>& u, const std::vector<double>& y, double sst) {
  const double n = static_cast<double>(u.size());
  double mu = 0, my = 0;
  for (std::size_t i = 0; i < u.size(); ++i) {
    if (!std::isfinite(u[i])) return {};
    mu += u[i];
    my += y[i];
  }
  mu /= n;
  my /= n;
  double suu = 0, suy = 0;
  for (std::size_t i = 0; i < u.size(); ++i) {
    suu += (u[i] - mu) * (u[i] - mu);
    suy += (u[i] - mu) * (y[i] - my);
  }
  if (suu < 1e-14 * n) return {};
  LinearFit f;
  f.a = suy / suu;
  f.d = my - f.a * mu;
  double sse = 0;
  for (std::size_t i = 0; i < u.size(); ++i) sse += std::pow(y[i] - f.a * u[i] - f.d, 2);
  f.r2 = 1.0 - sse / sst;
  return f;
}

double apply_family(const std::string& fam, double z) {
  if (fam == "sin") return std::sin(z);
  if (fam == "tanh") return std::tanh(z);
  if (fam == "exp") return std::exp(z);
  return z > 0.0 ? std::log(z) : std::numeric_limits<double>::quiet_NaN();  // log
}

int complexity(const std::string& fam) {
  static const std::vector<std::string> order{"x", "x^2", "x^3", "tanh", "sin", "exp", "log"};
  return static_cast<int>(std::find(order.begin(), order.end(), fam) - order.begin());
}

std::string num(double v) {
  std::ostringstream os;
  os << std::setprecision(4) << v;
  return os.str();
}

}  // namespace

std::string SymbolicFit::formula(const std::string& var) const {
  if (family == "x" || family == "x^2" || family == "x^3") {
    std::string s = num(coef[0]);
    const char* pw[] = {"", "", "^2", "^3"};
    for (std::size_t p = 1; p < coef.size(); ++p) {
      s += coef[p] < 0 ? " - " : " + ";
      s += num(std::abs(coef[p])) + "·" + var + pw[p];
    }
    return s;
  }
  std::string inner = num(coef[1]) + "·" + var + (coef[2] < 0 ? " - " : " + ") + num(std::abs(coef[2]));
  return num(coef[0]) + "·" + family + "(" + inner + ")" + (coef[3] < 0 ? " - " : " + ") + num(std::abs(coef[3]));
}

SymbolicFit fit_symbolic(const std::vector<double>& x, const std::vector<double>& y) {
  if (x.size() != y.size() || x.size() < 5) throw std::runtime_error("fit_symbolic: need at least 5 samples");
  const std::size_t n = x.size();
  double my = 0;
  for (double v : y) my += v;
  my /= static_cast<double>(n);
  double sst = 0;
  for (double v : y) sst += (v - my) * (v - my);
  if (sst < 1e-18 * static_cast<double>(n)) return {"x", {my, 0.0}, 1.0};

  std::vector<SymbolicFit> fits;
  for (int deg = 1; deg <= 3; ++deg) {
    Eigen::MatrixXd V(static_cast<Eigen::Index>(n), deg + 1);
    Eigen::VectorXd Y = Eigen::Map<const Eigen::VectorXd>(y.data(), static_cast<Eigen::Index>(n));
    for (std::size_t i = 0; i < n; ++i)
      for (int p = 0; p <= deg; ++p) V(static_cast<Eigen::Index>(i), p) = std::pow(x[i], p);
    const Eigen::VectorXd c = V.colPivHouseholderQr().solve(Y);
    const double sse = (V * c - Y).squaredNorm();
    fits.push_back({deg == 1 ? "x" : deg == 2 ? "x^2" : "x^3", std::vector<double>(c.data(), c.data() + c.size()),
                    1.0 - sse / sst});
  }
  double xlo = *std::min_element(x.begin(), x.end()), xhi = *std::max_element(x.begin(), x.end());
  const double xspan = std::max(xhi - xlo, 1e-12);
  std::vector<double> u(n);
  for (const std::string fam : {"tanh", "sin", "exp", "log"}) {
    // Coarse grid over the inner scale b (per unit of the input span) and shift c, then local refinement.
    double best_b = 0, best_c = 0;
    LinearFit best;
    auto score = [&](double b, double c) {
      for (std::size_t i = 0; i < n; ++i) {
        const double z = b * x[i] + c;
        u[i] = (fam == "exp" && std::abs(z) > 30.0) ? std::numeric_limits<double>::quiet_NaN() : apply_family(fam, z);
      }
      const LinearFit f = fit_affine(u, y, sst);
      if (f.r2 > best.r2) {
        best = f;
        best_b = b;
        best_c = c;
      }
    };
    const double b_max = 8.0 * 2.0 / xspan;
    const double c_max = fam == "sin" ? 3.14159 : 4.0;
    for (int ib = -32; ib <= 32; ++ib) {
      if (ib == 0) continue;
      for (int ic = -12; ic <= 12; ++ic) score(b_max * ib / 32.0, c_max * ic / 12.0);
    }
    double db = b_max / 32.0, dc = c_max / 12.0;
    for (int round = 0; round < 12; ++round) {
      db *= 0.5;
      dc *= 0.5;
      const double b0 = best_b, c0 = best_c;
      for (int ib = -2; ib <= 2; ++ib)
        for (int ic = -2; ic <= 2; ++ic) score(b0 + db * ib, c0 + dc * ic);
    }
    if (std::isfinite(best.r2)) fits.push_back({fam, {best.a, best_b, best_c, best.d}, best.r2});
  }
  double best_r2 = -std::numeric_limits<double>::infinity();
  for (const auto& f : fits) best_r2 = std::max(best_r2, f.r2);
  const SymbolicFit* pick = nullptr;
  for (const auto& f : fits)
    if (f.r2 >= best_r2 - 1e-4 && (!pick || complexity(f.family) < complexity(pick->family))) pick = &f;
  return *pick;
}

// ---- model --------------------------------------------------------------------------------------------------

KanModel::KanModel(const features::FeatureSpec& spec, double sample_rate_hz, KanNet net, Eigen::VectorXd params,
                   TargetScale target)
    : stream_(spec, sample_rate_hz), sample_rate_hz_(sample_rate_hz), net_(std::move(net)), params_(std::move(params)),
      target_(target) {
  if (static_cast<int>(spec.size()) != net_.shape().widths.front())
    throw std::runtime_error("kan: the feature spec has " + std::to_string(spec.size()) +
                             " features but the network expects " + std::to_string(net_.shape().widths.front()));
  if (static_cast<std::size_t>(params_.size()) != net_.num_params())
    throw std::runtime_error("kan: weight count does not match the architecture");
  meta.sample_rate_hz = sample_rate_hz;
}

double KanModel::predict(const ModelInput& in) const {
  double x[KanNet::kMaxWidth];
  stream_.compute(in, x);
  return target_.to_nm(net_.forward(params_.data(), x));
}

YAML::Node KanModel::to_yaml() const {
  YAML::Node n;
  n["sample_rate_hz"] = sample_rate_hz_;
  n["features"] = stream_.spec().to_yaml();
  n["target"] = target_.to_yaml();
  YAML::Node widths(YAML::NodeType::Sequence);
  for (int w : net_.shape().widths) widths.push_back(w);
  widths.SetStyle(YAML::EmitterStyle::Flow);
  n["hyperparameters"]["widths"] = widths;
  n["hyperparameters"]["grid"] = net_.shape().grid;
  n["hyperparameters"]["order"] = net_.shape().order;
  if (training_info) n["training"] = training_info;
  YAML::Node grids(YAML::NodeType::Sequence);
  for (const auto& g : net_.grids())
    grids.push_back(flow_sequence(Eigen::Map<const Eigen::VectorXd>(g.data(), static_cast<Eigen::Index>(g.size()))));
  n["grids"] = grids;
  n["weights"] = flow_sequence(params_);
  return n;
}

std::unique_ptr<KanModel> KanModel::from_yaml(const YAML::Node& node) {
  const std::string what = "kan model";
  const NeuralFileHeader header = read_neural_file_header(node, "kan", {"widths", "grid", "order"}, {"grids"});
  const double rate = header.sample_rate_hz;
  const features::FeatureSpec& spec = header.spec;
  const TargetScale& target = header.target;
  const YAML::Node h = header.hyperparameters;
  KanShape shape;
  if (!h["widths"] || !h["widths"].IsSequence()) throw std::runtime_error(what + ": 'widths' must be a list");
  shape.widths.clear();
  for (const auto& w : h["widths"]) {
    try {
      shape.widths.push_back(w.as<int>());
    } catch (const YAML::Exception&) {
      throw std::runtime_error(what + ": 'widths' entries must be integers");
    }
  }
  shape.grid = yaml_int(h, "grid", what, 1, 64);
  shape.order = yaml_int(h, "order", what, 0, 5);
  if (shape.widths.empty() || shape.widths.front() != static_cast<int>(spec.size()))
    throw std::runtime_error(what + ": 'widths' must start with the number of features (" +
                             std::to_string(spec.size()) + ")");
  KanNet net(shape);
  const YAML::Node grids = node["grids"];
  if (!grids || !grids.IsSequence() || static_cast<int>(grids.size()) != net.num_layers())
    throw std::runtime_error(what + ": 'grids' must be a list with one entry per layer (" +
                             std::to_string(net.num_layers()) + ")");
  for (int l = 0; l < net.num_layers(); ++l) {
    YAML::Node wrap;
    wrap["g"] = grids[static_cast<std::size_t>(l)];
    std::vector<double> g = yaml_doubles(wrap, "g", what + " grids[" + std::to_string(l) + "]",
                                                   net.grids()[static_cast<std::size_t>(l)].size());
    try {
      net.set_grid(l, std::move(g));
    } catch (const std::runtime_error& e) {
      throw std::runtime_error(what + ": " + e.what());
    }
  }
  const std::vector<double> w = yaml_doubles(node, "weights", what, net.num_params());
  auto m = std::make_unique<KanModel>(spec, rate, std::move(net),
                                      Eigen::Map<const Eigen::VectorXd>(w.data(), static_cast<Eigen::Index>(w.size())),
                                      target);
  if (node["training"]) m->training_info = node["training"];
  return m;
}

std::string KanModel::formulas() const {
  std::ostringstream os;
  const auto& spec = stream_.spec();
  os << "KAN " << net_.shape().widths.size() - 1 << " layer(s), grid " << net_.shape().grid << ", order "
     << net_.shape().order << "; position_nm = " << num(target_.mean_nm) << " + " << num(target_.scale_nm)
     << " · output\n";
  for (std::size_t i = 0; i < spec.size(); ++i) {
    const double mean = spec.mean.empty() ? 0.0 : spec.mean[i];
    os << "  z" << i << " = (" << spec.features[i].name() << (mean < 0 ? " + " : " - ") << num(std::abs(mean))
       << ") / " << num(spec.scale.empty() ? 1.0 : spec.scale[i]) << "\n";
  }
  for (int l = 0; l < net_.num_layers(); ++l) {
    const int n_in = net_.shape().widths[static_cast<std::size_t>(l)], n_out = net_.shape().widths[static_cast<std::size_t>(l + 1)];
    const bool last = l + 1 == net_.num_layers();
    for (int i = 0; i < n_in; ++i) {
      const double* t = net_.knots(l, i);
      const double lo = t[net_.shape().order], hi = t[net_.num_knots() - 1 - net_.shape().order];
      const std::string var = l == 0 ? "z" + std::to_string(i) : "h" + std::to_string(l) + "_" + std::to_string(i);
      for (int j = 0; j < n_out; ++j) {
        std::vector<double> xs, ys;
        for (int s = 0; s <= 100; ++s) {
          xs.push_back(lo + (hi - lo) * s / 100.0);
          ys.push_back(net_.edge(params_.data(), l, i, j, xs.back()));
        }
        const SymbolicFit f = fit_symbolic(xs, ys);
        os << "  layer " << l << ", " << var << " -> " << (last ? "output" : "h" + std::to_string(l + 1) + "_" + std::to_string(j))
           << ": " << f.formula(var) << "   (R² " << std::fixed << std::setprecision(5) << f.r2 << ")\n";
        os.unsetf(std::ios::fixed);
      }
    }
  }
  return os.str();
}

std::string KanModel::export_c99(const std::string& prefix) const {
  return neural_c99_header(stream_.spec(), sample_rate_hz_, prefix, export_c99_network(prefix));
}

std::string KanModel::export_c99_network(const std::string& prefix) const {
  std::ostringstream os;
  os << std::setprecision(17);
  const KanShape& s = net_.shape();
  const int L = net_.num_layers();
  os << "/* KAN (widths";
  for (int w : s.widths) os << " " << w;
  os << ", grid " << s.grid << ", order " << s.order
     << "): position [nm] from the standardised feature vector. Generated by piezo_compensation. */\n"
     << "#include <math.h>\n"
     << "#define " << prefix << "_NUM_FEATURES " << s.widths.front() << "\n"
     << "static const int " << prefix << "_widths[" << s.widths.size() << "] = {";
  for (std::size_t i = 0; i < s.widths.size(); ++i) os << (i ? ", " : "") << s.widths[i];
  os << "};\n";
  std::size_t total_knots = 0;
  for (const auto& g : net_.grids()) total_knots += g.size();
  os << "static const double " << prefix << "_knots[" << total_knots << "] = {";
  std::size_t c = 0;
  for (const auto& g : net_.grids())
    for (double v : g) os << (c ? "," : "") << (c % 4 == 0 ? "\n  " : " ") << v, ++c;
  os << "\n};\nstatic const double " << prefix << "_params[" << params_.size() << "] = {";
  for (Eigen::Index i = 0; i < params_.size(); ++i) os << (i ? "," : "") << (i % 4 == 0 ? "\n  " : " ") << params_[i];
  const int K = s.order, M = net_.num_knots(), NB = net_.num_basis();
  os << "\n};\n"
     << "/* B-spline values N[0..K] of basis first..first+K at x; returns 0 outside the knots. */\n"
     << "static int " << prefix << "_basis(const double* t, double x, int* first, double* N) {\n"
     << "  const int m = " << M << ", k = " << K << ";\n"
     << "  double prev[" << K + 1 << "];\n"
     << "  int lo = 0, hi = m - 1, s, j, r;\n"
     << "  if (!(x >= t[0] && x < t[m - 1])) return 0;\n"
     << "  while (hi - lo > 1) { int mid = (lo + hi) / 2; if (x >= t[mid]) lo = mid; else hi = mid; }\n"
     << "  s = lo; N[0] = 1.0;\n"
     << "  for (j = 1; j <= k; ++j) {\n"
     << "    for (r = 0; r < j; ++r) prev[r] = N[r];\n"
     << "    for (r = 0; r <= j; ++r) {\n"
     << "      int i = s - j + r; double v = 0.0, d;\n"
     << "      if (i >= 0 && i <= m - 2 - j) {\n"
     << "        if (r >= 1) { d = t[i + j] - t[i]; if (d > 0.0) v += (x - t[i]) / d * prev[r - 1]; }\n"
     << "        if (r <= j - 1) { d = t[i + j + 1] - t[i + 1]; if (d > 0.0) v += (t[i + j + 1] - x) / d * prev[r]; }\n"
     << "      }\n"
     << "      N[r] = v;\n"
     << "    }\n"
     << "  }\n"
     << "  *first = s - k; return 1;\n"
     << "}\n"
     << "static double " << prefix << "_network(const double* x) {\n"
     << "  double a[" << KanNet::kMaxWidth << "], b[" << KanNet::kMaxWidth << "], N[" << K + 1 << "];\n"
     << "  const double* in = x; double* out = a; const double* p = " << prefix << "_params;\n"
     << "  const double* t = " << prefix << "_knots;\n"
     << "  int l, i, j, r, first;\n"
     << "  for (l = 0; l < " << L << "; ++l) {\n"
     << "    const int n_in = " << prefix << "_widths[l], n_out = " << prefix << "_widths[l + 1];\n"
     << "    const double* bias = p + n_in * n_out * " << 1 + NB << ";\n"
     << "    for (j = 0; j < n_out; ++j) out[j] = bias[j];\n"
     << "    for (i = 0; i < n_in; ++i) {\n"
     << "      const double xi = in[i], silu = xi / (1.0 + exp(-xi));\n"
     << "      const int any = " << prefix << "_basis(t + i * " << M << ", xi, &first, N);\n"
     << "      for (j = 0; j < n_out; ++j) {\n"
     << "        const double* e = p + (i * n_out + j) * " << 1 + NB << ";\n"
     << "        double y = e[0] * silu;\n"
     << "        if (any) for (r = 0; r <= " << K << "; ++r) if (first + r >= 0 && first + r < " << NB
     << ") y += e[1 + first + r] * N[r];\n"
     << "        out[j] += y;\n"
     << "      }\n"
     << "    }\n"
     << "    t += n_in * " << M << "; p = bias + n_out; in = out; out = (out == a) ? b : a;\n"
     << "  }\n"
     << "  return " << target_.c99_expression("in[0]") << ";\n"
     << "}\n";
  return os.str();
}

}  // namespace piezo::models
