// Shared pieces of the residual-loop tests on synthetic data (test_residual_loop*.cpp): 3 h of the synthetic
// plant of test_residual_common.h with one planted effect, never declared to the tool.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <iostream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "test_residual_common.h"

namespace pa = piezo::analysis;
using piezo::test::Planted;

namespace residual_loop {
struct Outcome {
  pa::ResidualResult res;
  double clean_mae_nm = 0;
};

inline Outcome run(Planted p, std::uint64_t seed) {
  const double hours = 3.0;
  const piezo::io::Dataset d = piezo::test::synthetic(p, hours, seed);
  const std::size_t n_train = d.size() * 2 / 3;
  const piezo::io::Dataset train = d.slice(0, n_train), test = d.slice(n_train, d.size());
  pa::ResidualOptions o;
  o.axis = "c";
  if (std::getenv("PIEZO_RESIDUAL_VERBOSE")) o.log = [](const std::string& s) { std::cerr << s << "\n"; };
  const std::size_t n_fit = static_cast<std::size_t>(static_cast<double>(n_train) * (1.0 - o.validation_fraction));
  auto base = piezo::test::LowpassLinearModel::fit(train, "c", n_fit);
  Outcome out;
  out.res = pa::trace_residual(*base, train, test, o);
  // The same model on the same data without the effect.
  const piezo::io::Dataset clean = piezo::test::synthetic(Planted::kNone, hours, seed);
  const piezo::io::Dataset ctrain = clean.slice(0, n_train), ctest = clean.slice(n_train, clean.size());
  auto cbase = piezo::test::LowpassLinearModel::fit(ctrain, "c", n_fit);
  const auto pred = piezo::models::stream_model(*cbase, ctest, "c").prediction;
  out.clean_mae_nm = pa::error_stats(pred, ctest.axis("c").position_nm).mae_nm;
  return out;
}

inline void expect_found(const Outcome& o, const std::string& family) {
  ASSERT_FALSE(o.res.effects.empty()) << "nothing found, expected " << family;
  EXPECT_EQ(o.res.effects.front().family, family);
  EXPECT_LT(o.res.effects.front().p_value, 0.01);
  EXPECT_LT(o.res.after_test.mae_nm, 1.15 * o.clean_mae_nm)
      << "before " << o.res.before_test.mae_nm << " nm, after " << o.res.after_test.mae_nm << " nm, clean "
      << o.clean_mae_nm << " nm";
  EXPECT_LT(o.res.after_test.mae_nm, o.res.before_test.mae_nm);
}
}  // namespace residual_loop

