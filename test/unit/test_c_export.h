// The exported C99 header of a model (models/c_export.h) compiled with the C compiler (PIEZO_C_COMPILER) into a
// small program that reads "v d" lines and prints one-step, free-run and inverse results per line (a model
// with aux inputs is given none).
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "piezo_compensation/models/c_export.h"

namespace piezo {

namespace {

std::string run(const std::string& cmd) {
  std::string out;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return out;
  char buf[4096];
  while (std::size_t n = fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  const int rc = pclose(p);
  if (rc != 0) out = "FAILED(" + std::to_string(rc) + "): " + out;
  return out;
}

// Compiles header + driver; the driver reads "v d" lines and prints one-step, free-run and inverse results.
std::vector<std::array<double, 3>> run_c(const models::Model& m, const std::vector<double>& v, const std::vector<double>& d) {
  const std::string dir = ::testing::TempDir(),
                    tag = m.kind() + std::to_string(::getpid()) + "_" + std::to_string(reinterpret_cast<std::uintptr_t>(&m));
  const std::string hdr = dir + "pz_" + tag + ".h", src = dir + "pz_" + tag + ".c", exe = dir + "pz_" + tag;
  std::ofstream(hdr) << models::export_c99(m, "pz");
  std::ofstream(src) << "#include <stdio.h>\n#include \"" << hdr << "\"\n"
                     // a kind with aux inputs (augmented) takes them as a fourth argument: none here
                     << "#ifdef pz_NAUX\n#define PZ_STEP(s, v, d) pz_step(s, v, d, NULL)\n#else\n"
                     << "#define PZ_STEP(s, v, d) pz_step(s, v, d)\n#endif\n"
                     << "int main(void) { pz_state one, free; double v, d; int first = 1;\n"
                     << "  while (scanf(\"%lf %lf\", &v, &d) == 2) {\n"
                     << "    if (first) { pz_init(&one, v, d); pz_init(&free, v, d); first = 0; }\n"
                     << "    double inv = 0.0;\n#ifdef pz_HAS_INVERSE\n    inv = pz_inverse(&one, 100.0);\n#endif\n"
                     << "    double a = PZ_STEP(&one, v, d); double b = PZ_STEP(&free, v, NAN);\n"
                     << "    printf(\"%.17g %.17g %.17g\\n\", a, b, inv); }\n  return 0; }\n";
  const std::string cc = PIEZO_C_COMPILER;
  const std::string build = run(cc + " -std=c99 -Wall -Wextra -Werror -pedantic -O2 -o " + exe + " " + src + " -lm 2>&1");
  EXPECT_EQ(build, "") << "C compile failed";
  std::ostringstream in;
  in.precision(17);
  for (std::size_t i = 0; i < v.size(); ++i) in << v[i] << " " << d[i] << "\n";
  const std::string input = dir + "pz_" + tag + "_in.txt";
  std::ofstream(input) << in.str();
  std::istringstream out(run(exe + " < " + input));
  std::vector<std::array<double, 3>> rows;
  std::array<double, 3> r{};
  while (out >> r[0] >> r[1] >> r[2]) rows.push_back(r);
  return rows;
}

}  // namespace

}  // namespace piezo
