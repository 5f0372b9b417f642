// Error statistics of predicted positions and the encoder-noise floor they are judged against.
#pragma once

#include <cmath>
#include <cstddef>
#include <vector>

namespace piezo::analysis {

constexpr double kStudyEncoderNoiseNm = 20.79;  // reference study §4.1.1, c axis

// MAE of a perfect predictor scored against white Gaussian noise of σ: σ·√(2/π) (16.6 nm for 20.79 nm).
inline double noise_floor_mae_nm(double sigma_nm) { return sigma_nm * std::sqrt(2.0 / M_PI); }

struct ErrorStats {
  double mae_nm = NAN, rms_nm = NAN, max_nm = NAN, mean_nm = NAN;  // mean = bias (pred − ref)
  std::size_t n = 0;
  bool valid() const { return n > 0; }
};

// Over the samples where mask[i] != 0 (empty mask = all). Sizes must match (std::invalid_argument otherwise).
ErrorStats error_stats(const std::vector<double>& predicted, const std::vector<double>& reference,
                       const std::vector<char>& mask = {});

// Standard deviation of measured − truth over the mask (the encoder noise of simulated data).
double noise_sigma_nm(const std::vector<double>& measured, const std::vector<double>& truth, const std::vector<char>& mask = {});

}  // namespace piezo::analysis
