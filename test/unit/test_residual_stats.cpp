// The statistics of the residual tool on data with known answers.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/analysis/residual/residual.h"

namespace pa = piezo::analysis;

TEST(ResidualStats, CrossValidatedExplainedVarianceOfAPlantedRegressor) {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> g;
  const std::size_t n = 5000;
  std::vector<double> z(n), r(n), noise_only(n);
  for (std::size_t i = 0; i < n; ++i) {
    z[i] = g(rng);
    const double e = g(rng);
    r[i] = 5.0 + 2.0 * z[i] + e;  // EV = 4 / 5
    noise_only[i] = e;
  }
  const std::vector<std::size_t> shifts = {700, 1500, 2600, 3300, 4100};
  const pa::CvScore s = pa::cv_explained_variance(r, z, 1, 5, shifts);
  EXPECT_NEAR(s.explained_variance, 0.8, 0.03);
  ASSERT_EQ(s.null_explained_variance.size(), shifts.size());
  for (double x : s.null_explained_variance) EXPECT_LT(x, 0.01);
  const pa::CvScore none = pa::cv_explained_variance(noise_only, z, 1, 5, {});
  EXPECT_LT(none.explained_variance, 0.005);
  EXPECT_GT(none.explained_variance, -0.01);
}

TEST(ResidualStats, CrossValidationRejectsBadShapes) {
  std::vector<double> r(100, 1.0), z(99, 0.0);
  EXPECT_THROW(pa::cv_explained_variance(r, z, 1, 5, {}), std::invalid_argument);
  EXPECT_THROW(pa::cv_explained_variance(std::vector<double>(6, 1.0), std::vector<double>(6, 1.0), 1, 5, {}),
               std::invalid_argument);
}

TEST(ResidualStats, PeriodicPeakInTimeFoundAndNoiseNotSignificant) {
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g;
  const double fs = 11.0;
  const std::size_t n = 40000;
  std::vector<double> t(n), r(n), noise(n);
  for (std::size_t i = 0; i < n; ++i) {
    t[i] = static_cast<double>(i) / fs;
    noise[i] = 20.0 * g(rng);
    r[i] = noise[i] + 12.0 * std::sin(6.283185307179586 * 0.0371 * t[i] + 1.0);
  }
  const pa::PeriodicPeak p = pa::find_periodic_peak(t, r, 1e-3, 5.0);
  EXPECT_NEAR(p.frequency, 0.0371, 0.0371 * 2e-4);
  EXPECT_NEAR(p.amplitude, 12.0, 2.0);
  EXPECT_LT(p.p_value, 1e-6);
  const pa::PeriodicPeak q = pa::find_periodic_peak(t, noise, 1e-3, 5.0);
  EXPECT_GT(q.p_value, 0.01);
}

TEST(ResidualStats, PeriodicPeakInPositionOnAnIrregularGrid) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> g;
  std::uniform_real_distribution<double> u(0.0, 2000.0);
  const std::size_t n = 20000;
  std::vector<double> x(n), r(n);
  for (std::size_t i = 0; i < n; ++i) {
    x[i] = u(rng);
    r[i] = 20.0 * g(rng) + 10.0 * std::cos(6.283185307179586 * x[i] / 250.0);
  }
  const pa::PeriodicPeak p = pa::find_periodic_peak(x, r, 3.0 / 2000.0, 1.0 / 30.0);
  EXPECT_NEAR(1.0 / p.frequency, 250.0, 1.5);  // 8 periods over the range: ~0.3 % precision at this SNR
  EXPECT_NEAR(p.amplitude, 10.0, 2.0);
  EXPECT_LT(p.p_value, 1e-6);
}

// A scan of a non-uniform axis costs a pass per frequency: one with too many frequencies (a host clock's hour at
// 5 Hz resolution) is not run, and says so, instead of stopping the loop.
TEST(ResidualStats, APeriodicScanTooLargeIsSkippedAndSaysWhy) {
  std::vector<double> t(2000), r(2000);
  for (std::size_t i = 0; i < t.size(); ++i) t[i] = 2.0 * static_cast<double>(i) + (i % 3 == 1 ? 0.3 : 0.0), r[i] = std::sin(0.1 * i);
  const pa::PeriodicPeak p = pa::find_periodic_peak(t, r, 1e-3, 50.0);
  EXPECT_EQ(p.frequency, 0.0);
  EXPECT_NE(p.skipped.find("frequencies over a non-uniform axis"), std::string::npos) << p.skipped;
}

TEST(ResidualStats, ErrorStats) {
  const pa::ErrorStats e = pa::error_stats({0, 0, 0, 0}, {1, -1, 3, -3});
  EXPECT_DOUBLE_EQ(e.mae_nm, 2.0);
  EXPECT_DOUBLE_EQ(e.rms_nm, std::sqrt(5.0));
  EXPECT_DOUBLE_EQ(e.max_nm, 3.0);
  EXPECT_THROW(pa::error_stats({0}, {1, 2}), std::invalid_argument);
  EXPECT_EQ(pa::parse_prediction_mode("one-step"), pa::PredictionMode::kOneStep);
  EXPECT_THROW(pa::parse_prediction_mode("sideways"), std::invalid_argument);
}
