#include "basis.h"

#include <cmath>

namespace piezo::training::pi {

std::vector<double> poles_of(const std::vector<double>& taus, double rate) {
  std::vector<double> a;
  for (double t : taus) a.push_back(std::exp(-1.0 / (rate * t)));
  return a;
}

std::vector<double> init_poles(const std::vector<double>& taus, const FitData& d) {
  std::vector<double> out;
  for (double t : taus)
    if (slow_mode(t, d)) out.push_back(std::exp(-1.0 / (d.rate * t)));
  return out;
}

CreepBasis::CreepBasis(const models::CreepParams& cp, double rate) {
  cp.basis(taus, B);
  poles = poles_of(taus, rate);
  identity = B.size() == taus.size();
  for (std::size_t k = 0; k < B.size() && identity; ++k)
    for (std::size_t j = 0; j < B[k].size(); ++j) identity = identity && B[k][j] == (j == k ? 1.0 : 0.0);
}

std::vector<double> thresholds_for(const std::vector<double>& v, int n) {
  const auto [mn, mx] = std::minmax_element(v.begin(), v.end());
  const double half_range = std::max(1e-6, 0.5 * (*mx - *mn));
  std::vector<double> r;
  for (int i = 0; i < n; ++i) r.push_back(half_range * i / n);
  return r;
}

Basis basis_for(const std::vector<double>& v, std::vector<double> r, bool preisach, int knots_per_span,
                bool input_map) {
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

}  // namespace piezo::training::pi
