// The measurement-noise floor estimated from the data itself: no sensor figure is assumed.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

namespace piezo::analysis {

struct NoiseFloor {
  double sigma_nm = 0.0;         // σ of one reading about the true position (quantisation included)
  double quantisation_nm = 0.0;  // encoder step found in the readings (0 = not quantised)
  double floor_mae_nm = 0.0;     // MAE a perfect predictor scores against the readings
  std::string method;            // "holds", "residual", "all samples" or "given"
  std::size_t samples = 0;       // second differences used
  std::string describe() const;  // one line for reports: "σ = 20.8 nm (holds, 41 230 samples; step 20 nm) → ..."
};

// Estimates σ from second differences of the readings, y[t+1] − 2y[t] + y[t−1] (variance 6σ² for white noise;
// a drift linear over three samples cancels), with outliers beyond 5 robust σ dropped:
//  - over holds (three equal voltages in a row, the first 2 % of each hold skipped) when there are ≥ 200;
//  - else of the residual position − `prediction` when one is given (its smooth part cancels likewise);
//  - else over all samples (an upper bound: motion adds to it).
// The encoder step q is the common spacing of the distinct readings; a perfect predictor's error is then
// reading noise and rounding together: σ_floor = max(σ, q/√12), MAE = σ·√(2/π) (q/4 when rounding dominates).
// Throws std::invalid_argument when the axis has fewer than 3 samples.
NoiseFloor estimate_noise_floor(const io::Dataset& data, const std::string& axis,
                                const std::vector<double>* prediction = nullptr);

// The floor for a σ the user gives (--noise-sigma-nm): method "given".
NoiseFloor noise_floor_from_sigma(double sigma_nm);

// The encoder step of readings: the spacing all distinct values share (0 if they share none).
double reading_step_nm(const std::vector<double>& readings);

}  // namespace piezo::analysis
