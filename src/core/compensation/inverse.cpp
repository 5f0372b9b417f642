#include "piezo_compensation/compensation/inverse.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <utility>

namespace piezo::compensation {
namespace {

std::string unreachable(double target_nm, double p_lo, double p_hi, const InverseOptions& o) {
  std::ostringstream s;
  s << "no inverse inside the voltage limits [" << o.voltage_min_v << ", " << o.voltage_max_v << "] V: target "
    << target_nm << " nm, reachable " << std::min(p_lo, p_hi) << " .. " << std::max(p_lo, p_hi) << " nm";
  return s.str();
}

// Bracketed Illinois (modified regula falsi) on f over [a, b], f(a) = fa and f(b) = fb of opposite signs: needs
// only a sign change, converges superlinearly on the piecewise-smooth responses of hysteresis models, never leaves
// the bracket. Returns the last point and f there (not finite: f was not finite there, the search stopped).
template <class F>
std::pair<double, double> illinois(F&& f, double a, double fa, double b, double fb, const InverseOptions& o,
                                   double span) {
  int side = 0;
  double c = a, fc = fa;
  for (int it = 0; it < o.max_iterations; ++it) {
    c = (a * fb - b * fa) / (fb - fa);
    if (!(c > std::min(a, b) && c < std::max(a, b))) c = 0.5 * (a + b);
    fc = f(c);
    if (!std::isfinite(fc)) break;
    if (std::abs(fc) <= o.tolerance_nm || std::abs(b - a) < 1e-12 * span) break;
    if (fc * fb > 0) {
      b = c, fb = fc;
      if (side == -1) fa *= 0.5;
      side = -1;
    } else {
      a = c, fa = fc;
      if (side == +1) fb *= 0.5;
      side = +1;
    }
  }
  return {c, fc};
}

}  // namespace

InverseResult invert(const models::Model& model, double target_nm, const InverseOptions& o, const double* aux) {
  InverseResult r;
  if (!std::isfinite(target_nm)) {
    r.error = "target position is not finite";
    r.voltage_v = std::numeric_limits<double>::quiet_NaN();
    return r;
  }
  if (!(o.voltage_max_v > o.voltage_min_v)) {
    r.error = "voltage limits are empty";
    r.voltage_v = std::numeric_limits<double>::quiet_NaN();
    return r;
  }
  auto eval = [&](double v) {
    ++r.evaluations;
    return model.predict(models::ModelInput{v, aux});
  };
  const double lo = o.voltage_min_v, hi = o.voltage_max_v;
  const double p_lo = eval(lo), p_hi = eval(hi);
  if (!std::isfinite(p_lo) || !std::isfinite(p_hi)) {
    r.error = "model prediction is not finite at the voltage limits";
    r.voltage_v = std::numeric_limits<double>::quiet_NaN();
    r.predicted_nm = std::numeric_limits<double>::quiet_NaN();
    return r;
  }
  // Outside the reachable span: report the limit nearest to the target so a caller may still show it.
  auto nearest_limit = [&] {
    r.voltage_v = std::abs(p_lo - target_nm) < std::abs(p_hi - target_nm) ? lo : hi;
    r.predicted_nm = r.voltage_v == lo ? p_lo : p_hi;
    r.error = unreachable(target_nm, p_lo, p_hi, o);
    return r;
  };

  if (model.is_affine_in_voltage()) {
    r.closed_form = true;
    const double slope = (p_hi - p_lo) / (hi - lo);
    if (!(std::abs(slope) > 1e-12)) {
      r.error = "model has no voltage gain (slope 0), cannot invert";
      r.voltage_v = std::numeric_limits<double>::quiet_NaN();
      return r;
    }
    const double v = lo + (target_nm - p_lo) / slope;
    const double eps = 1e-9 * (hi - lo);
    if (!(v >= lo - eps && v <= hi + eps)) return nearest_limit();
    r.voltage_v = std::clamp(v, lo, hi);
    r.predicted_nm = eval(r.voltage_v);
    if (!std::isfinite(r.predicted_nm)) {
      r.error = "model prediction is not finite at the inverse voltage";
      return r;
    }
    r.ok = true;
    return r;
  }

  // Bracketed search between the limits (illinois above).
  double a = lo, fa = p_lo - target_nm, b = hi, fb = p_hi - target_nm;
  if (std::abs(fa) <= o.tolerance_nm) {
    r.ok = true, r.voltage_v = a, r.predicted_nm = p_lo;
    return r;
  }
  if (std::abs(fb) <= o.tolerance_nm) {
    r.ok = true, r.voltage_v = b, r.predicted_nm = p_hi;
    return r;
  }
  if (fa * fb > 0) return nearest_limit();
  const auto [c, fc] = illinois([&](double v) { return eval(v) - target_nm; }, a, fa, b, fb, o, hi - lo);
  if (!std::isfinite(fc)) {
    r.error = "model prediction is not finite inside the voltage limits";
    r.voltage_v = std::numeric_limits<double>::quiet_NaN();
    r.predicted_nm = std::numeric_limits<double>::quiet_NaN();
    return r;
  }
  r.voltage_v = c;
  r.predicted_nm = fc + target_nm;
  // A discontinuous model may leave a residual above the tolerance at the bracket's collapse: accept within
  // ten times the tolerance, report anything else.
  if (std::abs(fc) > 10.0 * o.tolerance_nm) {
    std::ostringstream s;
    s << "inverse did not converge: residual " << fc << " nm after " << r.evaluations << " evaluations";
    r.error = s.str();
    return r;
  }
  r.ok = true;
  return r;
}

}  // namespace piezo::compensation
