// Live residual watch, ROS-free: per axis, the rolling mean absolute free-run residual (measured − predicted) over
// a window of samples, against the noise floor. It warns when the rolling MAE has stayed above k × floor for
// hold_s seconds, and clears when it is back under that threshold.
#pragma once

#include <cstddef>
#include <deque>
#include <string>

namespace piezo::compensation {

struct ResidualWatchOptions {
  double window_s = 60.0;         // rolling window [s]
  double noise_floor_nm = 0.0;    // the encoder's noise floor (MAE of pure noise) [nm]; > 0
  double k = 2.0;                 // warn above k × floor
  double hold_s = 30.0;           // ... for this long [s]
};

class ResidualWatch {
 public:
  explicit ResidualWatch(const ResidualWatchOptions& o);  // throws std::invalid_argument naming the bad option

  // One free-run sample at time t_s (non-finite residuals are skipped).
  void add(double t_s, double residual_nm);
  void clear();  // a new model: the window starts again

  double rolling_mae_nm() const;             // NaN while the window holds less than half its length
  double threshold_nm() const { return o_.k * o_.noise_floor_nm; }
  bool warning() const { return warning_; }
  double above_for_s() const;                // how long the rolling MAE has been above the threshold
  std::size_t samples() const { return window_.size(); }
  // One line for an operator: the axis, the figure and what to do.
  std::string message(const std::string& axis) const;

 private:
  ResidualWatchOptions o_;
  std::deque<std::pair<double, double>> window_;  // (t, |residual|)
  double sum_ = 0.0, now_ = 0.0, above_since_ = -1.0;
  bool warning_ = false;
};

}  // namespace piezo::compensation
