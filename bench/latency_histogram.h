// What the command-latency tools (can_command_latency, can_ros_command_latency) share: their options, the wall
// clock the commands are stamped with (CLOCK_REALTIME, comparable with the kernel's SO_TIMESTAMP), percentiles,
// and the printed latency histogram and percentile line.
#pragma once

#include <time.h>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

namespace piezo::bench {

// Reads --seconds S and --rate-hz R into the given defaults; prints the usage and returns false on any other option.
inline bool parse_latency_options(int argc, char** argv, double& seconds, double& rate_hz) {
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--seconds") seconds = std::atof(argv[i + 1]);
    else if (a == "--rate-hz") rate_hz = std::atof(argv[i + 1]);
    else {
      std::fprintf(stderr, "usage: %s [--seconds S] [--rate-hz R]\n", argv[0]);
      return false;
    }
  }
  return true;
}

inline double wall_s() {
  timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return ts.tv_sec + ts.tv_nsec * 1e-9;
}

// Nearest-rank percentile, p in [0, 100]; NaN for no samples.
inline double percentile(std::vector<double> v, double p) {
  if (v.empty()) return std::nan("");
  std::sort(v.begin(), v.end());
  const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(std::ceil(p / 100.0 * v.size())) - 1);
  return v[k];
}

// One row per bin of `edges_us` (ascending; below the first and from the last edge on are bins too): label,
// count, share and a bar of 60 '#' at 100 %.
inline void print_latency_histogram(const std::vector<double>& latency_us, const std::vector<double>& edges_us) {
  std::vector<std::size_t> counts(edges_us.size() + 1, 0);
  for (double x : latency_us) counts[std::upper_bound(edges_us.begin(), edges_us.end(), x) - edges_us.begin()]++;
  const std::size_t n = std::max<std::size_t>(1, latency_us.size());
  for (std::size_t b = 0; b < counts.size(); ++b) {
    char label[48];
    if (b == 0)
      std::snprintf(label, sizeof label, "      < %5.0f us", edges_us[0]);
    else if (b == edges_us.size())
      std::snprintf(label, sizeof label, "     >= %5.0f us", edges_us.back());
    else
      std::snprintf(label, sizeof label, "%5.0f - %5.0f us", edges_us[b - 1], edges_us[b]);
    const int bar = static_cast<int>(std::round(60.0 * counts[b] / n));
    std::printf("  %s %7zu %6.2f%% %s\n", label, counts[b], 100.0 * counts[b] / n, std::string(bar, '#').c_str());
  }
}

// Prints the p50/p90/p99/p99.9/max line and returns p99 (the target's figure).
inline double print_latency_percentiles(const std::vector<double>& latency_us) {
  const double p99 = percentile(latency_us, 99);
  std::printf("latency [us]: p50 %.1f  p90 %.1f  p99 %.1f  p99.9 %.1f  max %.1f\n", percentile(latency_us, 50),
              percentile(latency_us, 90), p99, percentile(latency_us, 99.9), percentile(latency_us, 100));
  return p99;
}

}  // namespace piezo::bench
