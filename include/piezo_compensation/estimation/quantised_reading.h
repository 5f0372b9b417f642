// The encoder's reading model (docs/estimation.md): Gaussian noise of σ before a uniform quantiser of step q. A
// reading y (a level centre) says that the truth x plus the noise fell in its cell [y − q/2, y + q/2]:
//   P(y | x) = Φ((y + q/2 − x)/σ) − Φ((y − q/2 − x)/σ).
// One model for every axis: q ≫ σ (axes a/b: 250 nm against 21 nm) is the quantised end, q ≲ σ (axis c: 20 nm
// against 20 nm) the dithered one, q = 0 the limit of a point reading with Gaussian noise. ROS-free.
//
// The measurement update is assumed-density (moment matching): a Gaussian prior N(m, P) on x times this likelihood
// is projected back onto a Gaussian with the exact posterior mean and variance. With y* = x + v ~ N(m, s²),
// s² = P + σ², the reading restricts y* to the cell, and x | y* is Gaussian, so
//   E[x | y] = m + (P/s²)(E[y* | cell] − m),  Var[x | y] = P − P²/s² + (P/s²)² Var[y* | cell],
// with the moments of a truncated normal. Everything is computed from log-probabilities (erfc, its asymptotic
// expansion far in the tails), so a reading 10σ or 40σ from the prior gives finite numbers, never NaN or −inf.
#pragma once

namespace piezo::estimation {

// log Φ(x) and log(1 − Φ(x)), finite for every finite x.
double log_normal_cdf(double x);
double log_normal_sf(double x);

// Moments of a standard normal restricted to [alpha, beta] (alpha < beta; ±infinity allowed): log of its
// probability Z, its mean and its variance. A zero-width cell is the limit (mean alpha, variance 0; log_z is then
// the log density, so likelihoods of point readings stay comparable).
struct TruncatedMoments {
  double log_z = 0.0;
  double mean = 0.0;
  double var = 1.0;
};
TruncatedMoments truncated_standard_normal(double alpha, double beta);

// log P(reading y | truth x): the probability of the reading's cell (q > 0), or the Gaussian log density (q = 0).
double reading_log_likelihood(double y_nm, double x_nm, double sigma_nm, double step_nm);

// One moment-matched update of a Gaussian prior N(mean_nm, var_nm2) on the truth by a reading.
struct ReadingUpdate {
  double mean_nm = 0.0, var_nm2 = 0.0;  // the posterior's moments
  double log_p = 0.0;        // log P(y | readings before): the prediction-error term of the likelihood
  double innovation_nm = 0.0;  // E[y* | y] − mean_nm: the reading's pull; = y − mean_nm for q = 0
  double explained_nm2 = 0.0;  // s² − Var[y* | y]: the innovation's share of s² the reading resolved
  double cell_distance = 0.0;  // distance of the prior mean from the cell in units of s (0 inside)
};
ReadingUpdate quantised_update(double mean_nm, double var_nm2, double y_nm, double sigma_nm, double step_nm);

}  // namespace piezo::estimation
