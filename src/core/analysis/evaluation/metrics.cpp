#include "piezo_compensation/analysis/evaluation/metrics.h"

#include <stdexcept>
#include <string>

namespace piezo::analysis {

ErrorStats error_stats(const std::vector<double>& p, const std::vector<double>& r, const std::vector<char>& mask) {
  if (p.size() != r.size() || (!mask.empty() && mask.size() != p.size()))
    throw std::invalid_argument("error_stats: sizes differ (" + std::to_string(p.size()) + " predicted, " +
                                std::to_string(r.size()) + " reference, " + std::to_string(mask.size()) + " mask)");
  ErrorStats s;
  double sa = 0, s2 = 0, sm = 0, mx = 0;
  std::size_t n = 0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (!mask.empty() && !mask[i]) continue;
    const double e = p[i] - r[i];
    sa += std::abs(e);
    s2 += e * e;
    sm += e;
    mx = std::max(mx, std::abs(e));
    ++n;
  }
  if (n == 0) return s;
  s.n = n;
  s.mae_nm = sa / n;
  s.rms_nm = std::sqrt(s2 / n);
  s.max_nm = mx;
  s.mean_nm = sm / n;
  return s;
}

double noise_sigma_nm(const std::vector<double>& m, const std::vector<double>& t, const std::vector<char>& mask) {
  const ErrorStats s = error_stats(m, t, mask);
  if (!s.valid()) return NAN;
  return std::sqrt(std::max(0.0, s.rms_nm * s.rms_nm - s.mean_nm * s.mean_nm));
}

}  // namespace piezo::analysis
