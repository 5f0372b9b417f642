#include "piezo_compensation/io/holds.h"

#include <algorithm>
#include <cmath>

namespace piezo::io {

namespace {

std::vector<HoldRun> marked_holds(const Dataset& d, const HoldRule& rule, std::size_t from, double dt) {
  std::vector<HoldRun> out;
  std::size_t i = from;
  while (i < d.size()) {
    if (d.phase[i] != kHoldPhase) {
      ++i;
      continue;
    }
    HoldRun h;
    h.begin = i;
    h.segment = d.segment.empty() ? -1 : d.segment[i];
    ++i;
    while (i < d.size() && d.phase[i] == kHoldPhase && (d.segment.empty() || d.segment[i] == h.segment) &&
           !d.starts_recording(i))
      ++i;
    h.end = i;
    if (double(h.end - h.begin) * dt >= rule.min_marked_s) out.push_back(h);
  }
  return out;
}

std::vector<HoldRun> voltage_runs(const Dataset& d, const std::vector<double>& v, const HoldRule& rule,
                                  std::size_t from, double dt) {
  std::vector<HoldRun> out;
  double tol = rule.tolerance_v;
  if (rule.tolerance_of_span > 0 && !v.empty()) {
    const auto [mn, mx] = std::minmax_element(v.begin(), v.end());
    tol = std::max(tol, rule.tolerance_of_span * (*mx - *mn));
  }
  const std::size_t skip = rule.skip_first_row ? 1 : 0;
  std::size_t i = from;
  while (i < v.size()) {
    std::size_t j = i + 1;
    while (j < v.size() && std::fabs(v[j] - v[i]) <= tol && !d.starts_recording(j)) ++j;
    if (double(j - i) * dt >= rule.min_duration_s && j - i >= rule.min_rows && j > i + skip)
      out.push_back({i + skip, j, -1});
    i = j;
  }
  return out;
}

}  // namespace

std::vector<HoldRun> find_holds(const Dataset& data, const std::string& axis, const HoldRule& rule, std::size_t from) {
  const std::vector<double>& v = data.axis(axis).voltage_v;
  if (data.size() < 2) return {};
  const double dt = data.sample_period_s();
  if (rule.use_phase && data.phase.size() == data.size()) return marked_holds(data, rule, from, dt);
  return voltage_runs(data, v, rule, from, dt);
}

std::vector<char> hold_rows(std::size_t rows, const std::vector<HoldRun>& holds) {
  std::vector<char> m(rows, 0);
  for (const HoldRun& h : holds)
    std::fill(m.begin() + static_cast<std::ptrdiff_t>(std::min(h.begin, rows)),
              m.begin() + static_cast<std::ptrdiff_t>(std::min(h.end, rows)), 1);
  return m;
}

}  // namespace piezo::io
