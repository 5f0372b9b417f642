// A one-line progress bar with rate and ETA on a stream (stderr), redrawn at most ~5 times a second.
#pragma once

#include <chrono>
#include <iosfwd>
#include <string>

namespace piezo::util {

class ProgressBar {
 public:
  // unit: what is counted ("epochs", "trials", "samples"); enabled=false makes every call a no-op.
  ProgressBar(std::ostream& os, std::string unit, bool enabled = true);
  ~ProgressBar();
  // Reports done out of total (total ≤ 0 = unknown); `what` is a short phase label.
  void update(double done, double total, const std::string& what = "");
  void finish();  // final line with the elapsed time
  static std::string format_duration(double seconds);  // "1 h 02 min", "3 min 05 s", "12.3 s"

 private:
  std::ostream& os_;
  std::string unit_, what_;
  bool enabled_, finished_ = false;
  double last_done_ = 0, last_total_ = 0;
  std::chrono::steady_clock::time_point start_, last_draw_, phase_start_;
  void draw(bool force);
};

}  // namespace piezo::util
