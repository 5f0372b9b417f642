// The simulated NanoControl's command interpreter (mm3e_sim with transport nanocontrol): the commands of the
// study's recording code, answered as docs/nanocontrol.md describes, over a plant (the simulator) stepped to the
// caller's clock at each command. ROS-free and I/O-free: the caller moves the bytes and says what time it is.
// Each fault is injected for the next command it applies to.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>

#include "piezo_compensation/nanocontrol/line_protocol.h"
#include "piezo_compensation/sim/manipulator_simulator.h"

namespace piezo::nanocontrol {

struct SimDeviceConfig {
  std::array<char, 3> channels{'A', 'B', 'C'};            // channel of simulator axis a, b, c
  std::array<double, 3> nm_per_count{20.0, 20.0, -20.0};  // [nm] per counter count, signed
  double counts_per_volt = 409.6;                         // fine16 counts per volt
  double initial_voltage_v = 0.0;                         // every channel at power-up
  std::string version = "NanoControl (simulated by piezo_compensation mm3e_sim)";
};

// Holds the voltages (a, b, c) for dt_s and returns one sample (sim::ManipulatorSimulator::step).
using SimPlant = std::function<sim::StepResult(const std::array<double, 3>& voltages_v, double dt_s)>;

enum class SimFault {
  kErrorReply,   // the next set point is refused with e and not applied
  kBreakdown,    // the next command is answered i "Piezo Voltage Breakdown" (a set point is not applied)
  kLostReply,    // the next command is carried out and never answered
  kGarbled,      // the next command is carried out and answered with bytes that are no reply
  kPartial,      // the next command is carried out and answered with the start of its reply, no CR
};
const char* to_string(SimFault fault);

class SimDevice {
 public:
  SimDevice(const SimDeviceConfig& config, SimPlant plant);

  struct Answer {
    std::string bytes;          // to write back (a whole line with CR, a partial one, or nothing)
    bool set_point = false;     // the command was a set point that was applied
    int axis = -1;              // ... on this simulator axis (-1: a channel the manipulator does not use)
    double voltage_v = 0.0;     // ... at this voltage
    // A `fine16 ?` after counter reads closes a sample as the driver takes one: the mean true position [nm] of the
    // plant at those reads (evaluation only).
    bool sample_closed = false;
    std::array<double, 3> sample_truth_nm{};
  };
  // One command line (without its CR) at time now_s [s, any monotonic clock].
  Answer handle(const std::string& line, double now_s);

  void inject(SimFault fault);
  // Every voltage the device holds, by channel A..D [V].
  std::array<double, kChannelCount> voltages_v() const;
  const std::optional<sim::StepResult>& last_sample() const { return last_; }
  std::uint64_t commands() const { return commands_; }

 private:
  std::string reply(const std::string& line);  // the o/e reply, with the device's state changed
  std::string counters_text();
  void advance(double now_s);
  int axis_of(int channel) const;

  SimDeviceConfig config_;
  SimPlant plant_;
  std::array<int, kChannelCount> fine16_{};
  std::array<std::int64_t, kChannelCount> counter_offset_{};
  std::optional<sim::StepResult> last_;
  double time_s_ = 0.0;
  bool started_ = false;
  bool error_next_set_point_ = false;
  std::optional<SimFault> next_;
  std::uint64_t commands_ = 0;
  std::array<double, 3> truth_sum_nm_{};
  int truth_reads_ = 0;
  Answer* answer_ = nullptr;
};

}  // namespace piezo::nanocontrol
