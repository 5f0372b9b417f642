#include "piezo_compensation/estimation/quantised_reading.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace piezo::estimation {
namespace {

constexpr double kLogSqrtTwoPi = 0.91893853320467274;  // log √(2π)
constexpr double kSqrtHalf = 0.70710678118654752;
constexpr double kNarrowCell = 1e-7;  // a cell this narrow (in units of s) is a point reading

double log_pdf(double x) { return -0.5 * x * x - kLogSqrtTwoPi; }

// φ(x)/Z and x·φ(x)/Z, 0 at an infinite end
double ratio(double x, double log_z) { return std::isfinite(x) ? std::exp(log_pdf(x) - log_z) : 0.0; }
double x_ratio(double x, double log_z) { return std::isfinite(x) ? x * ratio(x, log_z) : 0.0; }

// [alpha, beta] with alpha + beta ≥ 0 (the caller reflects): Z without cancellation.
double log_probability_upper(double alpha, double beta) {
  if (alpha > 0.0) {  // both ends in the upper tail: Q(α) − Q(β) in log space
    const double la = log_normal_sf(alpha), lb = log_normal_sf(beta);
    return la + std::log1p(-std::exp(lb - la));
  }
  // the cell holds 0: Φ(β) − Φ(α) as a sum of two positive erf terms
  return std::log(0.5 * (std::erf(beta * kSqrtHalf) - std::erf(alpha * kSqrtHalf)));
}

}  // namespace

double log_normal_sf(double x) {
  if (x == std::numeric_limits<double>::infinity()) return -std::numeric_limits<double>::infinity();
  if (x < 30.0) return std::log(0.5 * std::erfc(x * kSqrtHalf));
  // Q(x) = φ(x)/x · (1 − 1/x² + 3/x⁴ − 15/x⁶ + …): erfc underflows near x = 37
  const double r = 1.0 / (x * x);
  return log_pdf(x) - std::log(x) + std::log1p(-r * (1.0 - 3.0 * r * (1.0 - 5.0 * r)));
}

double log_normal_cdf(double x) { return log_normal_sf(-x); }

TruncatedMoments truncated_standard_normal(double alpha, double beta) {
  TruncatedMoments t;
  const double w = beta - alpha;
  if (std::isfinite(w) && w < kNarrowCell) {  // the point limit: the density at the centre, no spread
    const double c = 0.5 * (alpha + beta);
    t.log_z = log_pdf(c) + (w > 0.0 ? std::log(w) : 0.0);
    t.mean = c;
    t.var = w > 0.0 ? w * w / 12.0 : 0.0;
    return t;
  }
  if (alpha + beta < 0.0) {  // the lower tail is the upper one reflected
    const TruncatedMoments r = truncated_standard_normal(-beta, -alpha);
    return {r.log_z, -r.mean, r.var};
  }
  t.log_z = log_probability_upper(alpha, beta);
  const double ra = ratio(alpha, t.log_z), rb = ratio(beta, t.log_z);
  t.mean = ra - rb;
  t.var = 1.0 + x_ratio(alpha, t.log_z) - x_ratio(beta, t.log_z) - t.mean * t.mean;
  // far in a tail the last three terms cancel to ~1/α²; rounding must not make the variance negative or exceed
  // the prior's
  t.var = std::clamp(t.var, 0.0, 1.0);
  if (t.var == 0.0 && alpha > 0.0) t.var = std::min(w * w / 12.0, 1.0 / (alpha * alpha));
  return t;
}

double reading_log_likelihood(double y_nm, double x_nm, double sigma_nm, double step_nm) {
  const double h = 0.5 * std::max(step_nm, 0.0);
  const TruncatedMoments t = truncated_standard_normal((y_nm - h - x_nm) / sigma_nm, (y_nm + h - x_nm) / sigma_nm);
  return step_nm > 0.0 ? t.log_z : t.log_z - std::log(sigma_nm);
}

ReadingUpdate quantised_update(double mean_nm, double var_nm2, double y_nm, double sigma_nm, double step_nm) {
  ReadingUpdate u;
  const double s2 = std::max(var_nm2, 0.0) + sigma_nm * sigma_nm, s = std::sqrt(s2);
  const double h = 0.5 * std::max(step_nm, 0.0);
  const double alpha = (y_nm - h - mean_nm) / s, beta = (y_nm + h - mean_nm) / s;
  const TruncatedMoments t = truncated_standard_normal(alpha, beta);
  u.log_p = step_nm > 0.0 ? t.log_z : t.log_z - std::log(s);
  u.innovation_nm = s * t.mean;
  u.explained_nm2 = s2 * (1.0 - t.var);
  u.cell_distance = alpha > 0.0 ? alpha : (beta < 0.0 ? -beta : 0.0);
  const double k = std::max(var_nm2, 0.0) / s2;  // x | y* is Gaussian with gain P/s²
  u.mean_nm = mean_nm + k * u.innovation_nm;
  u.var_nm2 = std::max(var_nm2 - k * var_nm2 + k * k * s2 * t.var, 0.0);
  return u;
}

}  // namespace piezo::estimation
