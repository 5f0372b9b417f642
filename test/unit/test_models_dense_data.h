// Small synthetic data for the neural model tests (hysteretic_walk.h with its defaults and a little noise),
// one-step MAE and the C99 export check.
#pragma once

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "hysteretic_walk.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/model.h"

namespace test_data {

inline piezo::io::Dataset hysteretic_dataset(std::size_t n, std::uint64_t seed, double noise_nm = 2.0) {
  HystereticWalk w;  // the defaults: walk 30 of every 40 samples, steps of 3 V, play ±5 V, creep 0.01/sample
  w.noise_nm = noise_nm;
  return hysteretic_walk(n, seed, w);
}

// One-step MAE of a model on the data (measured positions committed).
inline double one_step_mae(const piezo::models::Model& model, const piezo::io::Dataset& d, const std::string& axis) {
  auto m = model.clone();
  const auto& ax = d.axis(axis);
  m->reset(ax.voltage_v[0], ax.position_nm[0]);
  double sum = 0.0;
  for (std::size_t t = 0; t < d.size(); ++t) {
    const piezo::models::ModelInput in{ax.voltage_v[t], nullptr};
    sum += std::abs(m->predict(in) - ax.position_nm[t]);
    m->commit(in, ax.position_nm[t]);
  }
  return sum / static_cast<double>(d.size());
}

inline double mean_abs_deviation(const std::vector<double>& x) {
  double mean = 0.0;
  for (double v : x) mean += v;
  mean /= static_cast<double>(x.size());
  double s = 0.0;
  for (double v : x) s += std::abs(v - mean);
  return s / static_cast<double>(x.size());
}

}  // namespace test_data

#include <array>
#include <cstdio>
#include <fstream>
#include <sstream>

#include <gtest/gtest.h>

namespace test_data {

inline std::string run_command(const std::string& cmd) {
  std::string out;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return "FAILED to start: " + cmd;
  char buf[4096];
  while (std::size_t n = fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  const int rc = pclose(p);
  if (rc != 0) out = "FAILED(" + std::to_string(rc) + "): " + out;
  return out;
}

// Compiles the exported header with a driver (-Werror -pedantic) and checks one-step and free-run outputs
// against the C++ model sample by sample; returns the largest relative difference.
inline double c_export_max_diff(const piezo::models::Model& m, const std::string& header, const piezo::io::Dataset& d,
                                const std::string& axis) {
  const std::string dir = ::testing::TempDir(), tag = "nn_" + m.kind();
  const std::string hdr = dir + tag + ".h", src = dir + tag + ".c", exe = dir + tag, input = dir + tag + "_in.txt";
  std::ofstream(hdr) << header;
  std::ofstream(src) << "#include <stdio.h>\n#include \"" << hdr << "\"\n"
                     << "int main(void) { pz_state one, fr; double v, x; int first = 1;\n"
                     << "  while (scanf(\"%lf %lf\", &v, &x) == 2) {\n"
                     << "    double a, b;\n"
                     << "    if (first) { pz_init(&one, v, x); pz_init(&fr, v, x); first = 0; }\n"
                     << "    a = pz_step(&one, v, x); b = pz_step(&fr, v, NAN);\n"
                     << "    printf(\"%.17g %.17g\\n\", a, b); }\n  return 0; }\n";
  const std::string build =
      run_command(std::string(PIEZO_C_COMPILER) + " -std=c99 -Wall -Wextra -Werror -pedantic -O2 -o " + exe + " " + src + " -lm 2>&1");
  EXPECT_EQ(build, "") << "C compile failed";
  const auto& ax = d.axis(axis);
  {
    std::ofstream in(input);
    in.precision(17);
    for (std::size_t i = 0; i < d.size(); ++i) in << ax.voltage_v[i] << " " << ax.position_nm[i] << "\n";
  }
  std::istringstream out(run_command(exe + " < " + input));
  auto one = m.clone(), fr = m.clone();
  one->reset(ax.voltage_v[0], ax.position_nm[0]);
  fr->reset(ax.voltage_v[0], ax.position_nm[0]);
  double max_diff = 0.0;
  std::size_t rows = 0;
  double a = 0, b = 0;
  while (out >> a >> b) {
    const piezo::models::ModelInput in{ax.voltage_v[rows], nullptr};
    const double pa = one->predict(in), pb = fr->predict(in);
    max_diff = std::max({max_diff, std::abs(a - pa) / (1 + std::abs(pa)), std::abs(b - pb) / (1 + std::abs(pb))});
    one->commit(in, ax.position_nm[rows]);
    fr->commit(in, pb);
    ++rows;
  }
  EXPECT_EQ(rows, d.size());
  return rows == d.size() ? max_diff : 1e300;
}

}  // namespace test_data
