// Live residual watch: warns only after the rolling MAE stayed above k × floor for hold_s, clears when back under.
#include <gtest/gtest.h>

#include <random>

#include "piezo_compensation/compensation/residual_watch.h"

using piezo::compensation::ResidualWatch;
using piezo::compensation::ResidualWatchOptions;

TEST(ResidualWatch, WarnsAfterHoldAndClears) {
  ResidualWatchOptions o;
  o.window_s = 10.0, o.noise_floor_nm = 16.0, o.k = 1.5, o.hold_s = 5.0;
  ResidualWatch w(o);
  std::mt19937 rng(7);
  std::normal_distribution<double> noise(0.0, 20.0);  // MAE of N(0, 20) ≈ 16 nm: at the floor
  double t = 0.0;
  const double dt = 1.0 / 11.0;
  for (; t < 30.0; t += dt) w.add(t, noise(rng));
  EXPECT_NEAR(w.rolling_mae_nm(), 16.0, 3.0);
  EXPECT_FALSE(w.warning());
  // a 40 nm drift appears: MAE ≈ 40 > 24 nm; the warning waits until the window mean crosses, then hold_s
  double first_warn = -1.0;
  for (; t < 60.0; t += dt) {
    w.add(t, 40.0 + noise(rng));
    if (w.warning() && first_warn < 0.0) first_warn = t;
  }
  ASSERT_GT(first_warn, 30.0 + o.hold_s);
  EXPECT_LT(first_warn, 30.0 + o.window_s + o.hold_s);
  EXPECT_NE(w.message("c").find("~snapshot"), std::string::npos);
  EXPECT_NE(w.message("c").find("axis c"), std::string::npos);
  for (; t < 80.0; t += dt) w.add(t, noise(rng));
  EXPECT_FALSE(w.warning());
}

TEST(ResidualWatch, ShortExcursionDoesNotWarn) {
  ResidualWatchOptions o;
  o.window_s = 4.0, o.noise_floor_nm = 10.0, o.k = 2.0, o.hold_s = 10.0;
  ResidualWatch w(o);
  double t = 0.0;
  for (; t < 10.0; t += 0.1) w.add(t, 5.0);
  for (; t < 15.0; t += 0.1) w.add(t, 100.0);  // 5 s above, hold is 10 s
  EXPECT_FALSE(w.warning());
  EXPECT_GT(w.above_for_s(), 0.0);
  for (; t < 30.0; t += 0.1) w.add(t, 5.0);
  EXPECT_FALSE(w.warning());
  EXPECT_DOUBLE_EQ(w.above_for_s(), 0.0);
}

TEST(ResidualWatch, RefusesBadOptions) {
  ResidualWatchOptions o;
  EXPECT_THROW(ResidualWatch{o}, std::invalid_argument);  // no noise floor
  o.noise_floor_nm = 10.0;
  o.k = 0.5;
  EXPECT_THROW(ResidualWatch{o}, std::invalid_argument);
}
