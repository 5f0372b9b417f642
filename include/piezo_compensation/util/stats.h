// Small statistics of a sample, one definition each: mean, mean absolute value, median and percentile.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace piezo::util {

// Mean of v[a, b) (0 for an empty range).
inline double mean(const std::vector<double>& v, std::size_t a, std::size_t b) {
  double s = 0;
  for (std::size_t i = a; i < b; ++i) s += v[i];
  return b > a ? s / static_cast<double>(b - a) : 0.0;
}
inline double mean(const std::vector<double>& v) { return mean(v, 0, v.size()); }

// Mean of |v[i]| over [a, b) (0 for an empty range): the MAE of a residual.
inline double mean_abs(const std::vector<double>& v, std::size_t a, std::size_t b) {
  double s = 0;
  for (std::size_t i = a; i < b; ++i) s += std::fabs(v[i]);
  return b > a ? s / static_cast<double>(b - a) : 0.0;
}

// The element at n/2 of the sorted sample (the upper of the two middle ones for an even count); `empty` for none.
inline double median(std::vector<double> v, double empty = 0.0) {
  if (v.empty()) return empty;
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return v[v.size() / 2];
}

}  // namespace piezo::util
