#include "piezo_compensation/util/fingerprint.h"

#include <cstdio>

namespace piezo::util {

std::uint64_t fnv1a64(const void* data, std::size_t bytes, std::uint64_t h) {
  const auto* p = static_cast<const unsigned char*>(data);
  for (std::size_t i = 0; i < bytes; ++i) {
    h ^= p[i];
    h *= 1099511628211ULL;
  }
  return h;
}

std::string fingerprint(const io::Dataset& d) {
  auto col = [](const std::vector<double>& v, std::uint64_t h) { return fnv1a64(v.data(), v.size() * sizeof(double), h); };
  std::uint64_t h = col(d.time_s, 1469598103934665603ULL);
  for (const auto& a : d.axes) {
    h = fnv1a64(a.name.data(), a.name.size(), h);
    h = col(a.voltage_v, h);
    h = col(a.position_nm, h);
  }
  for (const auto& x : d.aux) {
    h = fnv1a64(x.name.data(), x.name.size(), h);
    h = col(x.values, h);
  }
  char buf[64];
  std::snprintf(buf, sizeof buf, "fnv1a64:%016llx:%zu", static_cast<unsigned long long>(h), d.size());
  return buf;
}

}  // namespace piezo::util
