// Simulated data as a controller log with a real log's faults (sim/controller_log.h).
#include "piezo_compensation/sim/controller_log.h"

#include <cmath>
#include <fstream>
#include <iomanip>
#include <stdexcept>

#include "piezo_compensation/util/splitmix64.h"

namespace piezo::sim {

namespace {
// Uniform and normal numbers from splitmix64: the same sequence on every platform.
class LogRng {
 public:
  explicit LogRng(std::uint64_t seed) : s_(seed ^ 0x6c6f67u) {}
  double uniform() { return static_cast<double>(util::splitmix64(s_) >> 11) * 0x1.0p-53; }
  double normal() {
    const double u = std::max(uniform(), 1e-300), v = uniform();
    return std::sqrt(-2.0 * std::log(u)) * std::cos(6.283185307179586 * v);
  }

 private:
  std::uint64_t s_;
};
}  // namespace

ControllerLogFaults write_controller_log(const std::string& path, const io::Dataset& data, const ControllerLogSpec& spec,
                                         std::uint64_t seed) {
  const io::AxisSeries& ax = data.axis(spec.axis);
  if (!ax.has_truth()) throw io::DataError(data.source_or_data() + ": axis " + spec.axis + " has no true position to read");
  const io::AuxSignal* temperature = data.find_aux("temperature_c");
  std::ofstream f(path);
  if (!f) throw std::runtime_error(path + ": cannot open for writing");
  f << "finestep,time";
  for (int k = 0; k < spec.reads; ++k) f << "," << spec.axis << "_" << k;
  f << ",temp," << spec.axis << "_mean\n";
  LogRng rng(seed);
  ControllerLogFaults faults;
  const double dt = data.sample_period_s();
  double t = 0.05;
  bool gap_done = spec.gap_at_s < 0;
  f << std::setprecision(12);
  for (std::size_t i = 0; i < data.size(); ++i) {
    if (i > 0) {
      double step = dt + spec.jitter_s * rng.normal();
      step = std::max(step, 0.3 * dt);
      if (rng.uniform() < spec.late_fraction) step += dt, ++faults.late_steps;
      if (!gap_done && t >= spec.gap_at_s) step += spec.gap_s, gap_done = true, faults.gap = true;
      t += step;
    }
    const double setpoint = std::round(ax.voltage_v[i] / spec.volts_per_step);
    f << setpoint << "," << t;
    double sum = 0;
    int finite = 0;
    for (int k = 0; k < spec.reads; ++k) {
      const bool nan = (spec.row_without_reads && i == spec.row_without_reads) || rng.uniform() < spec.read_nan_fraction;
      if (nan) {
        f << ",NaN";
        ++faults.read_cells_nan;
        continue;
      }
      const double x = ax.true_position_nm[i] - spec.zero_nm + spec.read_noise_nm * rng.normal();
      const double count = std::round(x / spec.nm_per_count);
      f << "," << count;
      sum += count, ++finite;
    }
    const double u = rng.uniform();
    f << ",";
    if (u < spec.temperature_nan_fraction) {
      f << "NaN";
      ++faults.temperature_nan;
    } else if (u < spec.temperature_nan_fraction + spec.temperature_glitch_fraction) {
      f << (rng.uniform() < 0.5 ? -1.0 : 75.0 + 6.0 * rng.uniform());
      ++faults.temperature_glitches;
    } else {
      f << std::round(10.0 * (temperature ? temperature->values[i] : spec.temperature_c)) / 10.0;
    }
    f << ",";
    if (finite == spec.reads) f << sum / spec.reads;
    else f << "NaN";
    f << "\n";
    ++faults.rows;
  }
  if (!f) throw std::runtime_error(path + ": write failed");
  return faults;
}

}  // namespace piezo::sim
