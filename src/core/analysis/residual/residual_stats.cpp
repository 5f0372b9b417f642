// Statistics of the residual tool: blocked cross-validation with circular-shift null draws, periodograms.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <complex>
#include <numeric>
#include <stdexcept>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/util/stats.h"

namespace piezo::analysis {

namespace {
constexpr double kTwoPi = 6.283185307179586;
// Circular-shift draws of the position scan's null (its family-wise p-value; each costs two dot products per
// frequency, the sinusoids being computed once).
constexpr std::size_t kPositionNullDraws = 39;

struct FoldSums {
  Eigen::MatrixXd G;  // X_f^T X_f, X = [1, Z]
  Eigen::VectorXd b;  // X_f^T r_f
  double rr = 0, s = 0;
  double n = 0;
};

double cv_ev(const std::vector<FoldSums>& f, std::size_t k1) {
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(k1, k1);
  Eigen::VectorXd b = Eigen::VectorXd::Zero(k1);
  double S = 0, N = 0;
  for (const auto& x : f) {
    G += x.G;
    b += x.b;
    S += x.s;
    N += x.n;
  }
  double sse = 0, sse0 = 0;
  for (const auto& x : f) {
    Eigen::MatrixXd Gt = G - x.G;
    const Eigen::VectorXd bt = b - x.b;
    // A tiny ridge on the standardised regressors keeps collinear variants solvable; the intercept is free.
    for (std::size_t j = 1; j < k1; ++j) Gt(j, j) += 1e-6 * Gt(0, 0) + 1e-9;
    const Eigen::VectorXd beta = Gt.ldlt().solve(bt);
    sse += x.rr - 2.0 * beta.dot(x.b) + beta.dot(x.G * beta);
    const double m = (S - x.s) / std::max(1.0, N - x.n);
    sse0 += x.rr - 2.0 * m * x.s + x.n * m * m;
  }
  if (!(sse0 > 0)) return 0.0;
  return 1.0 - sse / sse0;
}

// Xᵀr, rᵀr and Σr over rows [a, e) of X (k1 columns, row-major) against r shifted circularly by `shift`. Each sum
// runs over the rows in order; with K columns known at compile time the sums stay in registers.
template <std::size_t K>
void fold_sums_k(const double* X, const std::vector<double>& r, std::size_t a, std::size_t e, std::size_t shift,
                 FoldSums& out) {
  double b[K] = {};
  double rr = 0, s = 0;
  const std::size_t n = r.size();
  for (std::size_t i = a; i < e; ++i) {
    std::size_t src = i + shift;
    if (src >= n) src -= n;
    const double y = r[src];
    const double* x = X + i * K;
    for (std::size_t j = 0; j < K; ++j) b[j] += x[j] * y;
    rr += y * y;
    s += y;
  }
  for (std::size_t j = 0; j < K; ++j) out.b[static_cast<Eigen::Index>(j)] = b[j];
  out.rr = rr;
  out.s = s;
}

void fold_sums(const double* X, std::size_t k1, const std::vector<double>& r, std::size_t a, std::size_t e,
               std::size_t shift, FoldSums& out) {
  switch (k1) {
    case 2: return fold_sums_k<2>(X, r, a, e, shift, out);
    case 3: return fold_sums_k<3>(X, r, a, e, shift, out);
    case 4: return fold_sums_k<4>(X, r, a, e, shift, out);
    case 5: return fold_sums_k<5>(X, r, a, e, shift, out);
    case 6: return fold_sums_k<6>(X, r, a, e, shift, out);
    default: break;
  }
  const std::size_t n = r.size();
  double rr = 0, s = 0;
  for (std::size_t i = a; i < e; ++i) {
    std::size_t src = i + shift;
    if (src >= n) src -= n;
    const double y = r[src];
    const double* x = X + i * k1;
    for (std::size_t j = 0; j < k1; ++j) out.b[static_cast<Eigen::Index>(j)] += x[j] * y;
    rr += y * y;
    s += y;
  }
  out.rr = rr;
  out.s = s;
}

void fft(std::vector<std::complex<double>>& a) {
  const std::size_t n = a.size();
  for (std::size_t i = 1, j = 0; i < n; ++i) {
    std::size_t bit = n >> 1;
    for (; j & bit; bit >>= 1) j ^= bit;
    j ^= bit;
    if (i < j) std::swap(a[i], a[j]);
  }
  for (std::size_t len = 2; len <= n; len <<= 1) {
    const double ang = -kTwoPi / static_cast<double>(len);
    const std::complex<double> wl(std::cos(ang), std::sin(ang));
    for (std::size_t i = 0; i < n; i += len) {
      std::complex<double> w(1.0, 0.0);
      for (std::size_t j = 0; j < len / 2; ++j) {
        const auto u = a[i + j], v = a[i + j + len / 2] * w;
        a[i + j] = u + v;
        a[i + j + len / 2] = u - v;
        w *= wl;
      }
    }
  }
}

// |Σ r e^{-2πi f u}|² / n for demeaned r.
double power_at(const std::vector<double>& u, const std::vector<double>& r, double f) {
  double c = 0, s = 0;
  for (std::size_t i = 0; i < u.size(); ++i) {
    const double ph = kTwoPi * f * u[i];
    c += r[i] * std::cos(ph);
    s += r[i] * std::sin(ph);
  }
  return (c * c + s * s) / static_cast<double>(u.size());
}

bool is_uniform(const std::vector<double>& u) {
  if (u.size() < 3) return false;
  const double d = (u.back() - u.front()) / static_cast<double>(u.size() - 1);
  if (!(d > 0)) return false;
  for (std::size_t i = 1; i < u.size(); ++i)
    if (std::fabs(u[i] - u[i - 1] - d) > 0.01 * d) return false;
  return true;
}
}  // namespace

CvScore cv_explained_variance(const std::vector<double>& r, const std::vector<double>& Z, std::size_t k, int folds,
                              const std::vector<std::size_t>& shifts) {
  const std::size_t n = r.size();
  if (k == 0 || Z.size() != n * k) throw std::invalid_argument("cv_explained_variance: Z must be n × k");
  if (folds < 2 || n < static_cast<std::size_t>(folds) * 4) throw std::invalid_argument("cv_explained_variance: too few samples for the folds");
  // Standardise the regressors once (a constant column becomes zero: it explains nothing beyond the intercept).
  const std::size_t k1 = k + 1;
  std::vector<double> X(n * k1);
  for (std::size_t j = 0; j < k; ++j) {
    double m = 0, ss = 0;
    for (std::size_t i = 0; i < n; ++i) m += Z[i * k + j];
    m /= static_cast<double>(n);
    for (std::size_t i = 0; i < n; ++i) ss += (Z[i * k + j] - m) * (Z[i * k + j] - m);
    const double sd = std::sqrt(ss / static_cast<double>(n));
    for (std::size_t i = 0; i < n; ++i) X[i * k1 + j + 1] = sd > 0 ? (Z[i * k + j] - m) / sd : 0.0;
  }
  for (std::size_t i = 0; i < n; ++i) X[i * k1] = 1.0;

  std::vector<std::size_t> edge(folds + 1);
  for (int f = 0; f <= folds; ++f) edge[f] = n * f / folds;
  std::vector<FoldSums> base(folds);
  for (int f = 0; f < folds; ++f) {
    Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> Xf(
        X.data() + edge[f] * k1, edge[f + 1] - edge[f], k1);
    base[f].G = Xf.transpose() * Xf;
    base[f].n = static_cast<double>(edge[f + 1] - edge[f]);
  }
  auto score = [&](std::size_t shift) {
    std::vector<FoldSums> fs = base;
    for (int f = 0; f < folds; ++f) {
      fs[f].b = Eigen::VectorXd::Zero(k1);
      fold_sums(X.data(), k1, r, edge[f], edge[f + 1], shift, fs[f]);
    }
    return cv_ev(fs, k1);
  };
  CvScore out;
  out.explained_variance = score(0);
  for (std::size_t s : shifts) out.null_explained_variance.push_back(score(s % n));
  return out;
}

namespace {

// A periodogram: power per frequency and the background shape it is divided by.
struct Spectrum {
  std::vector<double> freq, pow, shape;
};

// On a uniform grid: FFT, zero-padded `oversample` times, and the AR(1) spectrum shape fitted to r (lag-1
// autocorrelation): the background of a slow residual is red, not flat.
Spectrum uniform_spectrum(const std::vector<double>& u, const std::vector<double>& r, double f_min, double f_max,
                          double oversample) {
  Spectrum s;
  const std::size_t n = r.size();
  const double du = (u.back() - u.front()) / static_cast<double>(n - 1);
  double c0 = 0, c1 = 0;
  for (std::size_t i = 0; i < n; ++i) c0 += r[i] * r[i];
  for (std::size_t i = 1; i < n; ++i) c1 += r[i] * r[i - 1];
  const double phi = c0 > 0 ? std::clamp(c1 / c0, 0.0, 0.999) : 0.0;
  std::size_t N = 1;
  while (N < static_cast<std::size_t>(oversample * static_cast<double>(n))) N <<= 1;
  std::vector<std::complex<double>> a(N);
  for (std::size_t i = 0; i < n; ++i) a[i] = r[i];
  fft(a);
  for (std::size_t j = 1; j < N / 2; ++j) {
    const double f = static_cast<double>(j) / (static_cast<double>(N) * du);
    if (f < f_min / 2 || f > std::min(2 * f_max, 0.5 / du)) continue;
    s.freq.push_back(f);
    s.pow.push_back(std::norm(a[j]) / static_cast<double>(n));
    s.shape.push_back(1.0 / (1.0 + phi * phi - 2.0 * phi * std::cos(kTwoPi * f * du)));
  }
  return s;
}

// On a non-uniform variable (position) the residual is in time order and strongly autocorrelated (slow misfit,
// holds at one position for minutes), so a plain periodogram against position sees a background of slow
// structure that swamps a periodic error of the size of the reading noise. The scan therefore prewhitens the
// residual and each frequency's sinusoids alike with the residual's AR(1) filter (1 − φB), regresses the
// whitened residual on the whitened pair, and scores the explained sum of squares over the whitened residual's
// variance: under white whitened noise half of it is Exp(1), the same scale as a periodogram over its
// background. Its family-wise significance comes from the same scan with the whitened residual shifted
// circularly against the positions (the alignment destroyed, the sampling of positions and the residual's
// remaining structure kept): the draws' maxima over the grid, their rank and a Gumbel tail beyond them.
struct PositionScan {
  double frequency = 0, ratio = 0, amplitude = 0;
  std::vector<double> null_max;  // per shift: the largest ratio over the grid
  std::size_t grid = 0;
};

struct Whitened {
  std::vector<double> w;  // (1 − φB) r, demeaned, rows 1 … n − 1
  double phi = 0, var = 0;
};

Whitened whiten(const std::vector<double>& r) {
  Whitened out;
  const std::size_t n = r.size();
  double c0 = 0, c1 = 0;
  for (std::size_t i = 0; i < n; ++i) c0 += r[i] * r[i];
  for (std::size_t i = 1; i < n; ++i) c1 += r[i] * r[i - 1];
  out.phi = c0 > 0 ? std::clamp(c1 / c0, 0.0, 0.999) : 0.0;
  out.w.resize(n - 1);
  double m = 0;
  for (std::size_t i = 1; i < n; ++i) m += (out.w[i - 1] = r[i] - out.phi * r[i - 1]);
  m /= static_cast<double>(n - 1);
  for (double& x : out.w) x -= m, out.var += x * x;
  out.var /= static_cast<double>(n - 1);
  return out;
}

// The whitened sinusoid pair at f, and the 2 × 2 normal matrix's inverse (false when singular).
bool whitened_pair(const std::vector<double>& u, double f, double phi, std::vector<double>& cw, std::vector<double>& sw,
                   double inv[3]) {
  const std::size_t n = u.size();
  double pc = std::cos(kTwoPi * f * u[0]), ps = std::sin(kTwoPi * f * u[0]);
  double g11 = 0, g12 = 0, g22 = 0;
  for (std::size_t i = 1; i < n; ++i) {
    const double c = std::cos(kTwoPi * f * u[i]), s = std::sin(kTwoPi * f * u[i]);
    cw[i - 1] = c - phi * pc, sw[i - 1] = s - phi * ps;
    pc = c, ps = s;
    g11 += cw[i - 1] * cw[i - 1], g12 += cw[i - 1] * sw[i - 1], g22 += sw[i - 1] * sw[i - 1];
  }
  const double det = g11 * g22 - g12 * g12;
  if (!(det > 1e-12 * (g11 * g22 + 1e-300))) return false;
  inv[0] = g22 / det, inv[1] = -g12 / det, inv[2] = g11 / det;
  return true;
}

// Explained sum of squares of w (shifted by `shift`) by the pair, and the coefficients.
double pair_ess(const std::vector<double>& w, std::size_t shift, const std::vector<double>& cw, const std::vector<double>& sw,
                const double inv[3], double* beta = nullptr) {
  const std::size_t m = w.size();
  double bc = 0, bs = 0;
  for (std::size_t i = 0, j = shift; i < m; ++i, ++j) {
    if (j == m) j = 0;
    bc += cw[i] * w[j], bs += sw[i] * w[j];
  }
  const double x = inv[0] * bc + inv[1] * bs, y = inv[1] * bc + inv[2] * bs;
  if (beta) beta[0] = x, beta[1] = y;
  return x * bc + y * bs;
}

// A direct scan costs one pass over the data per frequency: beyond this many frequencies it is not run.
constexpr std::size_t kMaxPositionGrid = 200000;

PositionScan position_scan(const std::vector<double>& u, const std::vector<double>& r, double f_min, double f_max,
                           double oversample, double range, std::size_t draws) {
  PositionScan out;
  const Whitened wh = whiten(r);
  if (!(wh.var > 0)) return out;
  const std::size_t m = wh.w.size();
  const double df = 1.0 / (oversample * range);
  const std::size_t grid = static_cast<std::size_t>((f_max - f_min) / df) + 1;
  out.grid = grid;
  if (grid > kMaxPositionGrid) return out;  // the caller says why
  std::vector<std::size_t> shifts(draws);
  for (std::size_t q = 0; q < draws; ++q) shifts[q] = m / 10 + (m * 8 / 10) * q / std::max<std::size_t>(1, draws - 1);
  out.null_max.assign(draws, 0.0);
  std::vector<double> cw(m), sw(m);
  double inv[3];
  auto ratio_at = [&](double f, std::size_t shift, double* beta) {
    if (!whitened_pair(u, f, wh.phi, cw, sw, inv)) return 0.0;
    return pair_ess(wh.w, shift, cw, sw, inv, beta) / (2.0 * wh.var);
  };
  for (std::size_t j = 0; j < grid; ++j) {
    const double f = f_min + df * static_cast<double>(j);
    if (!whitened_pair(u, f, wh.phi, cw, sw, inv)) continue;
    const double obs = pair_ess(wh.w, 0, cw, sw, inv) / (2.0 * wh.var);
    if (obs > out.ratio) out.ratio = obs, out.frequency = f;
    for (std::size_t q = 0; q < draws; ++q)
      out.null_max[q] = std::max(out.null_max[q], pair_ess(wh.w, shifts[q], cw, sw, inv) / (2.0 * wh.var));
  }
  if (!(out.frequency > 0)) return out;
  // The peak refined inside its bin (two passes of 21 points, the second a tenth as wide).
  for (int it = 0; it < 2; ++it) {
    const double width = (it == 0 ? 1.0 : 0.1) * df, centre = out.frequency;
    for (int q = -10; q <= 10; ++q) {
      const double f = centre + width * q / 10.0;
      if (f <= 0 || q == 0) continue;
      const double x = ratio_at(f, 0, nullptr);
      if (x > out.ratio) out.ratio = x, out.frequency = f;
    }
  }
  double beta[2] = {0, 0};
  ratio_at(out.frequency, 0, beta);
  out.amplitude = std::hypot(beta[0], beta[1]);
  return out;
}

// Refines the frequency inside the peak's bin by a fine local search; returns (frequency, power).
std::pair<double, double> refine_peak(const std::vector<double>& u, const std::vector<double>& r, double f0, double p0,
                                      double step) {
  double best_f = f0, best_p = p0;
  for (int it = 0; it < 2; ++it) {
    const double width = (it == 0 ? 1.0 : 0.1) * step;
    const double centre = best_f;
    for (int q = -10; q <= 10; ++q) {
      const double f = centre + width * q / 10.0;
      if (f <= 0) continue;
      const double p = power_at(u, r, f);
      if (p > best_p) best_p = p, best_f = f;
    }
  }
  return {best_f, best_p};
}

}  // namespace

// The observed maximum against the draws' maxima: the empirical rank, and beyond every draw a Gumbel tail fitted
// to them by moments (the law of a maximum over many frequencies).
double null_max_p_value(double observed, const std::vector<double>& null_max) {
  const double k = static_cast<double>(null_max.size());
  if (k < 2) return 1.0;
  double mean = 0, var = 0, above = 0;
  for (double x : null_max) mean += x / k, above += x >= observed;
  for (double x : null_max) var += (x - mean) * (x - mean) / (k - 1);
  const double p_emp = (1.0 + above) / (1.0 + k);
  if (above > 0 || !(var > 0)) return p_emp;
  const double beta = std::sqrt(6.0 * var) / 3.141592653589793, mu = mean - 0.5772156649015329 * beta;
  return std::min(p_emp, -std::expm1(-std::exp(-(observed - mu) / beta)));
}

PeriodicPeak find_periodic_peak(const std::vector<double>& u, const std::vector<double>& r_in, double f_min, double f_max,
                                double oversample) {
  PeriodicPeak out;
  const std::size_t n = r_in.size();
  if (u.size() != n || n < 16 || !(f_max > f_min) || !(f_min >= 0) || !(oversample >= 1)) return out;
  const double mean = std::accumulate(r_in.begin(), r_in.end(), 0.0) / static_cast<double>(n);
  std::vector<double> r(n);
  for (std::size_t i = 0; i < n; ++i) r[i] = r_in[i] - mean;
  const auto [umin, umax] = std::minmax_element(u.begin(), u.end());
  const double range = *umax - *umin;
  if (!(range > 0)) return out;
  if (!is_uniform(u)) {
    const PositionScan ps = position_scan(u, r, f_min, f_max, oversample, range, kPositionNullDraws);
    if (ps.grid > kMaxPositionGrid) {
      out.skipped = std::to_string(ps.grid) + " frequencies over a non-uniform axis (a host clock's time over several "
                    "recordings): not searched";
      return out;
    }
    if (ps.grid / static_cast<std::size_t>(oversample) < 2 || !(ps.frequency > 0)) return out;
    out.frequency = ps.frequency;
    out.amplitude = ps.amplitude;
    out.power_ratio = ps.ratio;
    out.searched = std::max<std::size_t>(1, static_cast<std::size_t>(static_cast<double>(ps.grid) / oversample));
    out.p_value = null_max_p_value(ps.ratio, ps.null_max);
    return out;
  }
  // On a uniform grid (time) the periodogram divided by its AR(1) background shape is compared with its own
  // median over a log-frequency window [f/2, 2f] around the peak (outside the peak's lobe), which follows
  // whatever slope is left.
  const Spectrum sp = uniform_spectrum(u, r, f_min, f_max, oversample);
  const std::vector<double>& freq = sp.freq;
  std::vector<double> white(sp.pow.size());
  for (std::size_t j = 0; j < sp.pow.size(); ++j) white[j] = sp.pow[j] / sp.shape[j];
  std::size_t ipk = SIZE_MAX, in_band = 0;
  for (std::size_t j = 0; j < freq.size(); ++j) {
    if (freq[j] < f_min || freq[j] > f_max) continue;
    ++in_band;
    if (ipk == SIZE_MAX || white[j] > white[ipk]) ipk = j;
  }
  if (in_band < 8 || ipk == SIZE_MAX) return out;
  const std::size_t lobe = static_cast<std::size_t>(std::ceil(2 * oversample));
  std::vector<double> bg;
  for (std::size_t j = 0; j < freq.size(); ++j)
    if ((j > ipk ? j - ipk : ipk - j) > lobe && freq[j] >= freq[ipk] / 2 && freq[j] <= 2 * freq[ipk]) bg.push_back(white[j]);
  if (bg.size() < 8) return out;
  const double bg_mean = util::median(std::move(bg)) / std::log(2.0);  // median of Exp(1) is ln 2
  const auto [best_f, best_p] = refine_peak(u, r, freq[ipk], sp.pow[ipk], freq.size() > 1 ? (freq[1] - freq[0]) : 0.0);
  out.frequency = best_f;
  out.amplitude = 2.0 * std::sqrt(best_p / static_cast<double>(n));
  out.power_ratio = white[ipk] / bg_mean;
  out.searched = static_cast<std::size_t>(std::max(1.0, static_cast<double>(in_band) / oversample));
  const double p1 = std::exp(-out.power_ratio);
  // 1 − (1 − p1)^M without cancellation.
  out.p_value = -std::expm1(static_cast<double>(out.searched) * std::log1p(-std::min(p1, 1.0 - 1e-16)));
  return out;
}

}  // namespace piezo::analysis
