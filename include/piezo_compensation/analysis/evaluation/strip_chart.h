// The operator's strip chart of one axis (the rviz monitor, docs/predictor.md): the last window of predictor
// output laid out as drawing primitives in a flat chart frame. ROS-free: the monitor node turns the primitives
// into markers. Lanes from top to bottom: a text line, the position lane (measured dots, predicted line,
// intended target, the fused estimate as a line in its ±1σ band when the predictor publishes one, drift-forecast
// fan to the right of "now"), the error lane (measured − predicted, magnified,
// with ±σ and ±2σ bands of the noise floor estimated from the window).
#pragma once

#include <cstddef>
#include <deque>
#include <limits>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/evaluation/noise_floor.h"

namespace piezo::analysis {

struct ChartSample {
  double time_s = 0.0;
  double measured_nm = 0.0;   // NaN when no encoder reading yet
  double predicted_nm = 0.0;  // NaN in fallback
  double intended_nm = 0.0;
  // Model and encoder fused (Prediction.fused_position, fused_position_sigma): NaN when not published
  double fused_nm = std::numeric_limits<double>::quiet_NaN();
  double fused_sigma_nm = std::numeric_limits<double>::quiet_NaN();
  double voltage_v = 0.0;     // the voltage sent (for the noise floor's hold detection)
  std::vector<double> drift_horizons_s, drift_nm;  // forecast of further motion if the voltage is held
  bool compensation_active = false, fallback = false;
  std::string model, status;
};

struct ChartColor {
  float r = 1, g = 1, b = 1, a = 1;
};

struct ChartPrimitive {
  enum class Type { kPoints, kLineStrip, kLineList, kText, kTriangleList };  // triangles: filled, 3 points each
  Type type = Type::kLineStrip;
  std::string name;                        // stable per primitive: the marker namespace
  std::vector<double> x, y;                // chart frame [chart units]; one point for text
  ChartColor color;
  double size = 0.02;                      // line width / point size / text height [chart units]
  std::string text;
  double z = 0.0;                          // layer: higher is drawn over lower (rviz looks down the z axis)
};

struct StripChartOptions {
  double window_s = 60.0;           // time shown
  double width = 9.0;               // chart units for the window
  double fan_width = 2.0;           // chart units right of "now" for the drift fan (log-spaced horizons)
  double position_height = 2.2;     // position lane
  double error_height = 1.2;        // error lane
  double text_height = 0.2;         // headline; labels are smaller
  double noise_sigma_nm = 0.0;      // > 0: the floor's σ as given; 0: estimated from the window
  double encoder_resolution_nm = 0.0;  // encoder step q: σ ≥ q/√12 (a held axis' readings sit on one step and
                                       // show no spread); 0 = the step found in the window's readings
  std::size_t min_noise_samples = 30;  // fewer finite errors than this: no floor yet
};

class StripChart {
 public:
  StripChart(std::string axis, StripChartOptions options);

  // Samples arrive in time order; an older one (time jumped back: bag loop, sim restart) clears the chart.
  void add(ChartSample s);
  void clear() { samples_.clear(); }
  std::size_t size() const { return samples_.size(); }

  struct Stats {
    std::size_t errors = 0;   // samples with measured and predicted
    double mae_nm = 0.0;      // mean |measured − predicted| over the window
    NoiseFloor floor;         // σ and the MAE a perfect predictor scores (sigma_nm 0 = not known yet)
    std::string floor_source; // how σ was found, for the headline: "given", "estimated (holds)", "q/√12 (...)"
  };
  Stats stats() const;

  // Primitives with the chart's top-left corner at (x0, y0); y grows upwards, the chart extends to
  // y0 − height(). Names are prefixed with the axis.
  std::vector<ChartPrimitive> draw(double x0, double y0) const;
  double height() const { return 3.2 * o_.text_height + o_.position_height + 0.3 + o_.error_height + 0.45; }

 private:
  std::string axis_;
  StripChartOptions o_;
  std::deque<ChartSample> samples_;
};

}  // namespace piezo::analysis
