// The PI and Preisach fits' bases (private to training/pi): the hysteresis basis (play thresholds and, for the
// preisach kinds or a PI kind's input map, the knots of the play outputs) and the creep basis on the data's clock.
#pragma once

#include <algorithm>
#include <cstddef>
#include <memory>
#include <utility>
#include <vector>

#include "gram.h"
#include "piezo_compensation/features/play_operator.h"
#include "piezo_compensation/models/pi_model.h"

namespace piezo::training::pi {

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
      p[i] = features::play(v, r[i], p[i]);
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
  std::unique_ptr<models::PiCreepModel> model(const std::vector<double>& w, double b, const models::CreepParams& cp,
                                              double rate) const {
    return std::make_unique<models::PiCreepModel>(r, w, b, cp, rate, knots, input_map);
  }
};

// The discrete poles exp(−1/(rate·τ)) of time constants `taus` at `rate` samples per second.
std::vector<double> poles_of(const std::vector<double>& taus, double rate);

// Poles of the modes whose initial state is worth estimating (slow_mode).
std::vector<double> init_poles(const std::vector<double>& taus, const FitData& d);

// Creep coefficients with a physical sign: the prony spectrum's weights and the LTI pairs' compliances g_j = 1/k_j
// (creep follows its input). Signed LTI gains let two poles the record cannot separate cancel at huge values
// (−1.9e5 nm/V pairs on the 40-s creep-free lowvolt_pi recording).
inline bool signed_creep(const models::CreepParams& cp) {
  return cp.kind == models::CreepKind::kProny || cp.kind == models::CreepKind::kLti;
}

// The creep basis of `cp` on the data's sample clock: mode time constants, basis matrix and discrete poles
// (shared by the creep-on-V and creep-on-H evaluations). The Prony and LTI bases are the identity (one column per
// mode), which creep_columns copies instead of multiplying.
struct CreepBasis {
  std::vector<double> taus, poles;
  std::vector<std::vector<double>> B;
  bool identity = false;
  CreepBasis(const models::CreepParams& cp, double rate);
};

// Advances the first-order creep modes l by input u and writes the basis projections Σ_j B[k][j]·l[j] (with the
// identity basis l itself: the same values, as the other terms of each sum are exact zeros).
inline void creep_columns(const CreepBasis& cb, std::vector<double>& l, double u, double* out) {
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

// n play thresholds evenly over [0, half the voltage span).
std::vector<double> thresholds_for(const std::vector<double>& v, int n);

// The preisach kinds' knots: play i moves within [v_min + r_i, v_max − r_i] once the data has swept the span, cut
// there into about K·(its width / the span) equal intervals (at least one), so the ramp hysterons tile the Preisach
// triangle evenly; knots at the inner interval ends only, so the outer pieces stay identified and extrapolate.
// A PI kind's input map (input_map): the first play (r_0 = 0, the voltage itself) cut the same way, the others not.
Basis basis_for(const std::vector<double>& v, std::vector<double> r, bool preisach, int knots_per_span,
                bool input_map = false);

}  // namespace piezo::training::pi
