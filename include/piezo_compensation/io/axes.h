// The one place that names a manipulator's axes. Every other part (CAN codec, nodes, data columns, CLI)
// takes the names and their order from here.
#pragma once

#include <array>
#include <string>

namespace piezo::io {

inline constexpr int kAxisCount = 3;
inline constexpr std::array<const char*, kAxisCount> kAxisNames{"a", "b", "c"};

// Index of `name` in kAxisNames, or -1 when it is not an axis name.
inline int axis_index_or_none(const std::string& name) {
  for (int i = 0; i < kAxisCount; ++i)
    if (name == kAxisNames[i]) return i;
  return -1;
}

// "a, b, c" for error messages.
inline std::string axis_names_list() {
  std::string s;
  for (const char* n : kAxisNames) s += (s.empty() ? "" : ", ") + std::string(n);
  return s;
}

}  // namespace piezo::io
