// A figure several test binaries compare against (a clean run's TEST MAE). Under ctest a fixture computes it once
// and writes it to the file an environment variable names (cmake/parts/residual.cmake); a binary run by hand,
// without the variable, computes it itself. The file carries a key of the data and settings it was made from, so a
// figure made from other ones (an older setup binary) fails the test instead of being compared against.
#pragma once

#include <gtest/gtest.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iomanip>
#include <iostream>
#include <limits>
#include <string>

namespace piezo::test {

// The setup's side: writes `value` under `key` to $env, after removing the old file so a failed run leaves none.
inline void write_reference_figure(const char* env, const std::string& key, const std::function<double()>& compute) {
  const char* path = std::getenv(env);
  if (!path || !*path) GTEST_SKIP() << env << " is not set: this writes the reference for ctest's fixture";
  std::filesystem::remove(path);
  const double value = compute();
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  const std::string tmp = std::string(path) + ".tmp";
  {
    std::ofstream f(tmp);
    f << "key " << key << "\n" << std::setprecision(std::numeric_limits<double>::max_digits10) << "value " << value << "\n";
    ASSERT_TRUE(f.good()) << "cannot write " << tmp;
  }
  std::filesystem::rename(tmp, path);
  std::cerr << "reference " << value << " written to " << path << "\n";
}

// The consumer's side: the figure from $env's file if the variable is set, else compute(). A missing, unparsable or
// mismatched file is a test failure (and NaN, which no comparison passes).
inline double reference_figure(const char* env, const std::string& key, const std::function<double()>& compute) {
  const char* path = std::getenv(env);
  if (!path || !*path) return compute();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::ifstream f(path);
  if (!f) {
    ADD_FAILURE() << env << "=" << path << ": no reference file (its CTest fixture did not run or failed)";
    return nan;
  }
  std::string line, file_key, value_text;
  while (std::getline(f, line)) {
    if (line.rfind("key ", 0) == 0) file_key = line.substr(4);
    else if (line.rfind("value ", 0) == 0) value_text = line.substr(6);
  }
  char* end = nullptr;
  const double value = std::strtod(value_text.c_str(), &end);
  if (value_text.empty() || *end != '\0') {
    ADD_FAILURE() << env << "=" << path << ": unparsable reference file (no 'value <number>' line)";
    return nan;
  }
  if (file_key != key) {
    ADD_FAILURE() << env << "=" << path << ": reference made from other data or settings\n  file: " << file_key
                  << "\n  this test: " << key;
    return nan;
  }
  std::cerr << "clean reference " << value << " nm (from " << path << ")\n";
  return value;
}

}  // namespace piezo::test
