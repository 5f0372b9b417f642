// util::FlushSubnormals: subnormal results are zero while the guard lives, and the caller's mode is back after it.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "piezo_compensation/util/flush_subnormals.h"

namespace {

// Through volatile so the compiler cannot fold the product at compile time (in the default mode it is subnormal).
double product(double a, double b) {
  volatile double x = a, y = b;
  return x * y;
}

}  // namespace

TEST(FlushSubnormals, SubnormalResultsAreZeroInsideAndTheModeIsRestoredAfter) {
  const double tiny = std::numeric_limits<double>::min();  // smallest normal, 2.2e-308
  ASSERT_EQ(std::fpclassify(product(tiny, 0.5)), FP_SUBNORMAL) << "the default mode keeps subnormals";
  {
    const piezo::util::FlushSubnormals outer;
#if defined(__SSE__) || defined(__x86_64__)
    EXPECT_EQ(product(tiny, 0.5), 0.0);
    {
      const piezo::util::FlushSubnormals inner;  // nesting keeps the flushed mode
      EXPECT_EQ(product(tiny, 0.5), 0.0);
    }
    EXPECT_EQ(product(tiny, 0.5), 0.0) << "the inner guard restored the outer guard's mode";
#endif
    EXPECT_EQ(product(1.5, 2.0), 3.0) << "normal arithmetic is unchanged";
  }
  EXPECT_EQ(std::fpclassify(product(tiny, 0.5)), FP_SUBNORMAL) << "the caller's mode is back";
}
