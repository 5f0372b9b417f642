// The play (backlash) operator, the one definition used by the play features, the PI models and their fits.
#pragma once

#include <algorithm>
#include <cstddef>

namespace piezo::features {

// Output of a play operator of half-width r for input v, given its previous output.
inline double play(double v, double r, double prev) { return std::max(v - r, std::min(v + r, prev)); }

// Monotone pieces of a play output p cut at knots c_0 < … < c_{n−1} (the "preisach" kinds): out[0] = min(p − c_0, 0),
// out[k] = clamp(p − c_{k−1}, 0, c_k − c_{k−1}) for 0 < k < n, out[n] = max(p − c_{n−1}, 0); with no knot, out[0] = p.
// The pieces sum to p − c_0, so equal weights give the play operator back (PI is the special case); non-negative
// unequal weights give any monotone piecewise-linear map of p. A piece is a ramp hysteron of the Preisach plane
// (centre c, half-width r): relays smoothed over one knot spacing, which is what lets the sum be asymmetric.
inline std::size_t play_piece_count(std::size_t n_knots) { return n_knots + 1; }
inline void play_pieces(double p, const double* knots, std::size_t n_knots, double* out) {
  if (n_knots == 0) {
    out[0] = p;
    return;
  }
  out[0] = std::min(p - knots[0], 0.0);
  for (std::size_t k = 1; k < n_knots; ++k) out[k] = std::min(std::max(p - knots[k - 1], 0.0), knots[k] - knots[k - 1]);
  out[n_knots] = std::max(p - knots[n_knots - 1], 0.0);
}
// Σ_k w[k]·piece_k(p), without a buffer (the models' per-sample path).
inline double play_pieces_dot(double p, const double* knots, std::size_t n_knots, const double* w) {
  if (n_knots == 0) return w[0] * p;
  double s = w[0] * std::min(p - knots[0], 0.0) + w[n_knots] * std::max(p - knots[n_knots - 1], 0.0);
  for (std::size_t k = 1; k < n_knots; ++k) s += w[k] * std::min(std::max(p - knots[k - 1], 0.0), knots[k] - knots[k - 1]);
  return s;
}

}  // namespace piezo::features
