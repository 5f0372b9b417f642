// Simulated device + driver over UDP, checked from outside through the driver's topics, services and
// diagnostics. One .test file per safety behaviour selects its case with --gtest_filter and sets the
// driver's parameters for it.
#include <diagnostic_msgs/DiagnosticArray.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>

#include <algorithm>
#include <cstdio>
#include <cmath>
#include <limits>
#include <atomic>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/VoltageCommand.h"
#include "piezo_compensation/ros/mm3e_driver.h"
#include "piezo_compensation/ros/mm3e_sim.h"
#include "wall_wait.h"

using piezo_compensation::AxisVoltage;
using piezo_compensation::EncoderPosition;
using piezo_compensation::VoltageCommand;

namespace {

const char* kAxes[] = {"a", "b", "c"};

// Deadline of a wait for something that comes within a second on an idle host: a wait returns as soon as its
// condition holds, so only a failing run pays it. The tests wait on conditions (reports counted on the
// controller's clock, diagnostics, services), not on fixed wall-clock times, so a loaded host only makes them slower.
constexpr double kPatienceS = 30.0;

struct Sample {
  double stamp_s, receive_s, value;
  std::uint32_t sequence;
  std::string frame_id;
};

class Bench {
 public:
  Bench() : nh_("mm1") {
    for (int i = 0; i < 3; ++i) {
      const std::string a = kAxes[i];
      subs_.push_back(nh_.subscribe<AxisVoltage>(a + "/voltage", 100, [this, i](const AxisVoltage::ConstPtr& m) {
        std::lock_guard<std::mutex> l(mutex_);
        voltage_[i].push_back({m->header.stamp.toSec(), ros::WallTime::now().toSec(), m->voltage, m->sequence,
                               m->header.frame_id});
      }));
      subs_.push_back(nh_.subscribe<EncoderPosition>(a + "/encoder", 100, [this, i](const EncoderPosition::ConstPtr& m) {
        std::lock_guard<std::mutex> l(mutex_);
        encoder_[i].push_back({m->header.stamp.toSec(), ros::WallTime::now().toSec(), m->position, m->sequence,
                               m->header.frame_id});
      }));
      subs_.push_back(nh_.subscribe<EncoderPosition>(a + "/true_position", 100,
                                                     [this, i](const EncoderPosition::ConstPtr& m) {
                                                       std::lock_guard<std::mutex> l(mutex_);
                                                       truth_[i].push_back({m->header.stamp.toSec(), 0, m->position,
                                                                            m->sequence, m->header.frame_id});
                                                     }));
      commands_[i] = nh_.advertise<VoltageCommand>(a + "/command", 1);
    }
    diag_sub_ = ros::NodeHandle().subscribe<diagnostic_msgs::DiagnosticArray>(
        "/diagnostics", 20, [this](const diagnostic_msgs::DiagnosticArray::ConstPtr& m) {
          std::lock_guard<std::mutex> l(mutex_);
          for (const auto& s : m->status) {
            auto& d = diag_[s.name.substr(s.name.rfind(": ") + 2)];
            d["__updates"] = std::to_string(++diag_updates_[s.name.substr(s.name.rfind(": ") + 2)]);
            d["__level"] = std::to_string(int(s.level));
            d["__message"] = s.message;
            for (const auto& kv : s.values) d[kv.key] = kv.value;
          }
        });
  }

  // The subscriptions go first: a callback still running would write into the sample vectors, which are destroyed
  // before the subscribers (shutdown waits for a callback in progress). A test that ends on a report ends while
  // the reports of the other axes are being delivered.
  ~Bench() {
    for (auto& s : subs_) s.shutdown();
    diag_sub_.shutdown();
  }

  // Waits until the driver publishes on every axis and listens to our command topics.
  void wait_ready() {
    ASSERT_TRUE(wait([&] {
      for (int i = 0; i < 3; ++i)
        if (voltage_count(i) < 2 || commands_[i].getNumSubscribers() == 0) return false;
      return true;
    }, kPatienceS)) << "driver not up";
  }

  template <typename Pred>
  bool wait(Pred pred, double seconds) {
    return piezo::test::wall_wait(pred, seconds, 0.01);
  }

  void command(int axis, double v) {
    VoltageCommand c;
    c.header.stamp = ros::Time::now();
    c.voltage = v;
    commands_[axis].publish(c);
  }
  // Publishes v at rate_hz until done() holds or seconds pass (a commander keeping the watchdog fed); done() then.
  template <typename Pred>
  bool command_until(int axis, double v, Pred done, double seconds = kPatienceS, double rate_hz = 50.0) {
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(seconds);
    while (ros::ok() && ros::WallTime::now() < end && !done()) {
      command(axis, v);
      ros::WallDuration(1.0 / rate_hz).sleep();
    }
    return done();
  }
  // Publishes v until the axis reports it (within tol_v).
  bool command_reached(int axis, double v, double tol_v = 1e-6) {
    return command_until(axis, v, [&] { return std::abs(last_voltage(axis) - v) < tol_v; });
  }
  // Waits until n more reports of the axis arrived than `since` (a time span on the controller's clock).
  bool wait_reports(int axis, std::size_t since, std::size_t n) {
    return wait([&] { return voltage_count(axis) >= since + n; }, kPatienceS);
  }
  // Publishes v at rate_hz for seconds (a commander keeping the watchdog fed).
  void command_for(int axis, double v, double seconds, double rate_hz = 50.0) {
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(seconds);
    while (ros::ok() && ros::WallTime::now() < end) {
      command(axis, v);
      ros::WallDuration(1.0 / rate_hz).sleep();
    }
  }

  std::vector<Sample> voltage(int i) { std::lock_guard<std::mutex> l(mutex_); return voltage_[i]; }
  std::vector<Sample> encoder(int i) { std::lock_guard<std::mutex> l(mutex_); return encoder_[i]; }
  std::vector<Sample> truth(int i) { std::lock_guard<std::mutex> l(mutex_); return truth_[i]; }
  std::size_t voltage_count(int i) { std::lock_guard<std::mutex> l(mutex_); return voltage_[i].size(); }
  std::size_t encoder_count(int i) { std::lock_guard<std::mutex> l(mutex_); return encoder_[i].size(); }
  double last_voltage(int i) {
    std::lock_guard<std::mutex> l(mutex_);
    return voltage_[i].empty() ? std::nan("") : voltage_[i].back().value;
  }
  std::string diag(const std::string& status, const std::string& key) {
    std::lock_guard<std::mutex> l(mutex_);
    auto it = diag_.find(status);
    if (it == diag_.end()) return "";
    auto kv = it->second.find(key);
    return kv == it->second.end() ? "" : kv->second;
  }
  double diag_number(const std::string& status, const std::string& key) {
    const std::string v = diag(status, key);
    return v.empty() ? std::nan("") : std::stod(v);
  }
  // Every key of one status as one diagnostics message had it ("__updates": how many messages had it so far).
  std::map<std::string, std::string> diag_status(const std::string& status) {
    std::lock_guard<std::mutex> l(mutex_);
    auto it = diag_.find(status);
    return it == diag_.end() ? std::map<std::string, std::string>{} : it->second;
  }
  void clear() {
    std::lock_guard<std::mutex> l(mutex_);
    for (int i = 0; i < 3; ++i) voltage_[i].clear(), encoder_[i].clear(), truth_[i].clear();
  }

 private:
  ros::NodeHandle nh_;
  std::vector<ros::Subscriber> subs_;
  ros::Subscriber diag_sub_;
  ros::Publisher commands_[3];
  std::mutex mutex_;
  std::vector<Sample> voltage_[3], encoder_[3], truth_[3];
  std::map<std::string, std::map<std::string, std::string>> diag_;
  std::map<std::string, long> diag_updates_;
};

// The driver's slew guarantee, on the driver's own clock. Every step moves the applied voltage by at most
// slew_rate_v_per_s × (ROS time since the previous step), and one step covers at most max_step_dt_s (mm3e_driver:
// one spinner thread, command and tick steps in time order; CommandLimiter::step). So a frame written at time t,
// after a moment t0 when the driver had applied v0 and had been stepping since, carries at most
//   |v − v0| ≤ slew × (t − t0 + max_step_dt_s)
// (the first step after t0 may reach back one max_step_dt_s). The test cannot see t, but a voltage report shows a
// frame written before the device sent the report, and its stamp is the driver's kernel receive time of that report
// (stamp_with_receive_time, wall clock = the driver's ROS time here): t ≤ stamp. Hence the check below is exact
// however the host schedules the device, the driver or us. Comparing consecutive reports is not: a device that
// reads its socket late takes in a few samples' worth of frames at once and reports them in one sample interval.
struct SlewGuarantee {
  double slew_v_per_s = 0, max_step_dt_s = 0, report_tolerance_v = 0, report_lag_s = 0;
  double output_rate_hz = 0, voltage_lsb_v = 0;
};
SlewGuarantee driver_slew_guarantee() {
  ros::NodeHandle p("mm1/mm3e_driver");
  SlewGuarantee g;
  p.param("slew_rate_v_per_s", g.slew_v_per_s, 0.0);
  p.param("max_step_dt_s", g.max_step_dt_s, 0.1);  // mm3e_driver's defaults
  p.param("report_tolerance_v", g.report_tolerance_v, 0.5);
  p.param("report_lag_s", g.report_lag_s, 0.5);
  p.param("output_rate_hz", g.output_rate_hz, 200.0);
  p.param("protocol/voltage_lsb_v", g.voltage_lsb_v, 1e-4);
  return g;
}
// Every report of one axis stamped after t0_s is within slew of v0 as above. The frames such a report may show
// were all written after t0_s, or are v0 (the caller's anchor says which voltage the axis held at t0_s); slack_v:
// how far the driver's applied voltage at t0_s may be from v0 by its own rules.
// Encoding: the applied voltage is the encoded value, rounded to the LSB at each step, so each step may add half
// an LSB; steps come from the ramp tick (output_rate_hz) and from commands (our commanders: 50 Hz), at most
// 2 × output_rate_hz per second here. Plus 1 mV for the reports' own encoding and µs stamps.
// The most the driver may move an axis in span_s of its clock (span_s includes the max_step_dt_s reach-back).
double slew_bound_v(const SlewGuarantee& g, double span_s) {
  const double rounding_v = 0.5 * g.voltage_lsb_v * 2.0 * g.output_rate_hz * span_s + 1e-3;
  return g.slew_v_per_s * span_s + rounding_v;
}
void expect_ramp_from(const std::vector<Sample>& v, double v0, double t0_s, const SlewGuarantee& g, const char* what,
                      double slack_v = 0.0) {
  int checked = 0;
  for (std::size_t k = 0; k < v.size(); ++k) {
    if (v[k].stamp_s <= t0_s) continue;
    const double bound = slack_v + slew_bound_v(g, v[k].stamp_s - t0_s + g.max_step_dt_s);
    EXPECT_LE(std::abs(v[k].value - v0), bound)
        << what << ": report " << k << " (sequence " << v[k].sequence << ") " << v[k].value << " V, "
        << v[k].stamp_s - t0_s << " s (stamp) after " << v0 << " V was held: more than " << slack_v << " V + "
        << g.slew_v_per_s << " V/s × (" << v[k].stamp_s - t0_s << " + " << g.max_step_dt_s << ") s allows";
    ++checked;
  }
  EXPECT_GT(checked, 0) << what << ": no report after the anchor";
}

// Rate on the stamps (the driver's kernel receive times of the device's reports): the median over every run of
// `intervals` consecutive intervals, as a rate. A report the device sends late, or that we read late, moves one or two
// runs, not the median: the device's own rate, whatever the host's load.
double median_rate_hz(const std::vector<Sample>& s, std::size_t intervals) {
  std::vector<double> spans;
  for (std::size_t k = intervals; k < s.size(); ++k) spans.push_back(s[k].stamp_s - s[k - intervals].stamp_s);
  if (spans.empty()) return 0.0;
  std::nth_element(spans.begin(), spans.begin() + spans.size() / 2, spans.end());
  return intervals / spans[spans.size() / 2];
}

}  // namespace

TEST(Driver, TopicsAtEncoderRate) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.wait_reports(2, 0, 11));  // a second of reports before measuring
  b.clear();
  // About 4 s of reports on every axis.
  ASSERT_TRUE(b.wait([&] {
    for (int i = 0; i < 3; ++i)
      if (b.encoder_count(i) < 45 || b.voltage_count(i) < 45) return false;
    return true;
  }, kPatienceS));
  for (int i = 0; i < 3; ++i) {
    const auto enc = b.encoder(i), volt = b.voltage(i);
    ASSERT_GE(enc.size(), 35u) << kAxes[i];
    // sample to sample, and over a second (11 intervals: a slow drift of the period shows there)
    EXPECT_NEAR(median_rate_hz(enc, 1), 11.0, 0.5) << "encoder stamps, median interval, axis " << kAxes[i];
    EXPECT_NEAR(median_rate_hz(enc, 11), 11.0, 0.5) << "encoder stamps, median second, axis " << kAxes[i];
    EXPECT_NEAR(median_rate_hz(volt, 1), 11.0, 0.5) << "voltage stamps, median interval, axis " << kAxes[i];
    EXPECT_NEAR(median_rate_hz(volt, 11), 11.0, 0.5) << "voltage stamps, median second, axis " << kAxes[i];
    for (std::size_t k = 1; k < enc.size(); ++k) {
      EXPECT_EQ(enc[k].sequence, enc[k - 1].sequence + 1) << "dropped or reordered on loopback";
      EXPECT_GT(enc[k].stamp_s, enc[k - 1].stamp_s);
    }
    EXPECT_EQ(enc.front().frame_id, "mm1/base");
    // The stamp is the frame's receive time (the driver's kernel receive time): after the device took the sample
    // (the simulated device's own sample time, its /true_position stamp of the same sequence) and before we got
    // the message. Both ends are events, not a latency bound, so a loaded host cannot make this fail.
    std::map<std::uint32_t, double> sampled_s;
    for (const auto& t : b.truth(i)) sampled_s[t.sequence] = t.stamp_s;
    std::size_t matched = 0;
    for (const auto& e : enc) {
      EXPECT_LE(e.stamp_s, e.receive_s) << "stamped after we received it, sequence " << e.sequence;
      const auto it = sampled_s.find(e.sequence);
      if (it == sampled_s.end()) continue;
      EXPECT_GE(e.stamp_s, it->second) << "stamped before the device sampled it, sequence " << e.sequence;
      ++matched;
    }
    EXPECT_GE(matched, enc.size() / 2) << "device sample times for too few encoder reports, axis " << kAxes[i];
  }
  ASSERT_TRUE(b.wait([&] { return !b.diag("bus", "state").empty(); }, kPatienceS));
  EXPECT_EQ(b.diag("bus", "state"), "active");
  EXPECT_NEAR(b.diag_number("axis a", "encoder rate [Hz]"), 11.0, 1.5);
  EXPECT_EQ(b.diag_number("axis b", "encoder dropped"), 0.0);
}

TEST(Driver, CommandReachesThePiezo) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.wait([&] { return !b.truth(2).empty() && b.encoder_count(2) > 3; }, kPatienceS));
  const double v0 = b.last_voltage(2);
  const double x0 = b.truth(2).back().value;
  ASSERT_TRUE(b.command_reached(2, 20.0, 1e-3)) << b.last_voltage(2);
  // Half a second of the controller's clock at 20 V (the encoder mean below needs 5 readings there).
  const std::size_t at_target = b.encoder_count(2);
  ASSERT_TRUE(b.wait([&] { return b.encoder_count(2) >= at_target + 6 && !b.truth(2).empty(); }, kPatienceS));
  const double x1 = b.truth(2).back().value;
  const auto enc = b.encoder(2);
  double enc_mean = 0;
  for (std::size_t k = enc.size() - 5; k < enc.size(); ++k) enc_mean += enc[k].value / 5;
  // +20 V moves the simulated piezo by roughly a hundred nanometres or more; noise is ~20 nm.
  EXPECT_GT(x1 - x0, 100e-9) << "true position did not follow " << v0 << " V -> 20 V";
  EXPECT_NEAR(enc_mean, x1, 60e-9) << "encoder does not follow the true position";
  EXPECT_NEAR(b.last_voltage(0), 0.0, 1e-3) << "other axes must not move";
}

TEST(Driver, ClampsToTheLimits) {
  Bench b;
  b.wait_ready();
  // the ramp runs at most max_unconfirmed_v (10 V) ahead of the last matching report: ~110 V/s at 11 Hz, less
  // when reports are late on a loaded host; the commander keeps the watchdog fed long enough for 160 V
  ASSERT_TRUE(b.command_until(0, 150.0, [&] { return std::abs(b.last_voltage(0) - 80.0) < 1e-6; })) << b.last_voltage(0);
  ASSERT_TRUE(b.command_until(0, -1e6, [&] { return std::abs(b.last_voltage(0) + 80.0) < 1e-6; })) << b.last_voltage(0);
  for (const auto& s : b.voltage(0)) {
    EXPECT_LE(s.value, 80.0 + 1e-9);
    EXPECT_GE(s.value, -80.0 - 1e-9);
  }
  EXPECT_GT(b.diag_number("axis a", "clamped"), 0.0);
}

TEST(Driver, SlewLimited) {
  Bench b;
  b.wait_ready();
  const SlewGuarantee g = driver_slew_guarantee();
  const double slew = g.slew_v_per_s;
  ASSERT_GT(slew, 0.0) << "driver ~slew_rate_v_per_s not set";
  // Nothing has commanded axis b yet: the driver holds what the device reports.
  const double v0 = b.last_voltage(1);
  ASSERT_GT(std::abs(v0 - 30.0), 10.0) << "starts too close to the target to see a ramp: " << v0;
  b.clear();
  const ros::WallTime t0 = ros::WallTime::now();
  ASSERT_TRUE(b.command_reached(1, 30.0)) << b.last_voltage(1);
  const auto v = b.voltage(1);
  double first_at_target = 0;
  for (std::size_t k = 1; k < v.size(); ++k) {
    EXPECT_GT(v[k].stamp_s, v[k - 1].stamp_s) << "sample " << k;
    if (first_at_target == 0 && std::abs(v[k].value - 30.0) < 1e-6) first_at_target = v[k].receive_s;
  }
  // Every report is within slew of v0 since t0 on the driver's clock (the report's stamp).
  expect_ramp_from(v, v0, t0.toSec(), g, "ramp to 30 V");
  EXPECT_GE(first_at_target - t0.toSec(), 0.9 * std::abs(30.0 - v0) / slew)
      << "reached 30 V faster than the slew limit allows";
}

TEST(Driver, RejectsNonFinite) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.command_reached(2, 10.0)) << b.last_voltage(2);
  b.clear();
  for (double bad : {std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(),
                     -std::numeric_limits<double>::infinity()})
    b.command_for(2, bad, 0.5);
  ASSERT_TRUE(b.wait([&] { return b.diag_number("axis c", "rejected non-finite") > 0; }, kPatienceS));
  ASSERT_TRUE(b.wait_reports(2, 0, 10));
  for (const auto& s : b.voltage(2)) EXPECT_NEAR(s.value, 10.0, 1e-6);
}

TEST(Driver, TimeoutHoldsLastVoltage) {
  Bench b;
  b.wait_ready();
  ros::NodeHandle p("mm1/mm3e_driver");
  double timeout = 0;
  ASSERT_TRUE(p.getParam("command_timeout_s", timeout));
  const SlewGuarantee g = driver_slew_guarantee();
  const double slew = g.slew_v_per_s;
  ASSERT_GT(slew, 0.0) << "driver ~slew_rate_v_per_s not set";
  // One burst of commands towards 60 V, then silence: the ramp must stop where it is.
  const double v_start = b.last_voltage(0);
  const double burst_from_s = ros::WallTime::now().toSec();
  b.command_for(0, 60.0, 0.3);
  const double burst_to_s = ros::WallTime::now().toSec();  // after the last command's stamp
  // The diagnostics message that reports the timeout has the applied voltage it froze (target := applied).
  std::map<std::string, std::string> at_timeout;
  ASSERT_TRUE(b.wait([&] {
    at_timeout = b.diag_status("axis a");
    return at_timeout["timed out"] == "True";
  }, kPatienceS)) << b.diag("axis a", "timed out");
  const double frozen = std::stod(at_timeout.at("applied voltage [V]"));
  // The device shows that last set point once it has read it (a loaded host may take a while).
  ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(0) - frozen) < 1e-3; }, kPatienceS))
      << b.last_voltage(0) << " V reported, " << frozen << " V applied";
  const double held = b.last_voltage(0);
  EXPECT_GT(held, 1.0) << "fell back towards 0 V";
  EXPECT_LT(held, 60.0 - 1.0) << "kept ramping after the timeout";
  // The driver ramps only from the first command (after burst_from_s; its first step may reach back max_step_dt_s)
  // until command_timeout_s after the last command's stamp (before burst_to_s), on its own clock.
  EXPECT_LE(std::abs(held - v_start),
            slew_bound_v(g, burst_to_s - burst_from_s + timeout + g.max_step_dt_s))
      << "moved further than the commands allowed: " << v_start << " → " << held << " V, commands for "
      << burst_to_s - burst_from_s << " s, timeout " << timeout << " s";
  b.clear();
  ASSERT_TRUE(b.wait_reports(0, 0, 22));  // two seconds of the controller's clock
  for (const auto& s : b.voltage(0)) EXPECT_DOUBLE_EQ(s.value, held);
  EXPECT_GE(b.diag_number("axis a", "timeouts"), 1.0);
}

TEST(Driver, RecoversAfterBusFault) {
  Bench b;
  b.wait_ready();
  ros::ServiceClient inject = ros::NodeHandle().serviceClient<std_srvs::Trigger>("/mm1/mm3e_sim/inject_bus_off");
  ASSERT_TRUE(inject.waitForExistence(ros::Duration(kPatienceS)));
  std_srvs::Trigger t;
  ASSERT_TRUE(inject.call(t));
  ASSERT_TRUE(t.response.success) << t.response.message;
  const ros::WallTime fault = ros::WallTime::now();
  ASSERT_TRUE(b.wait([&] { return b.diag_number("bus", "bus-off events") >= 1; }, kPatienceS)) << "bus-off not reported";
  // The device is silent for a while; the driver reconnects and the encoder comes back.
  b.clear();
  ASSERT_TRUE(b.wait([&] { return b.encoder_count(1) >= 5; }, kPatienceS)) << "encoder did not come back";
  EXPECT_GT(ros::WallTime::now().toSec() - fault.toSec(), 0.9);  // not before the silence ended
  ASSERT_TRUE(b.wait([&] { return b.diag("bus", "state") == "active"; }, kPatienceS)) << b.diag("bus", "state");
  EXPECT_GE(b.diag_number("bus", "connects"), 2.0);
  // And commands work again.
  EXPECT_TRUE(b.command_reached(1, 12.0)) << b.last_voltage(1);
  // Garbage on the bus is counted, not fatal.
  ros::ServiceClient garbage = ros::NodeHandle().serviceClient<std_srvs::Trigger>("/mm1/mm3e_sim/inject_garbage");
  ASSERT_TRUE(garbage.call(t));
  // 7 reach the decoder (3 bad DLC, 3 reserved flags, 1 bad heartbeat state); the RTR frames stop at the filter.
  ASSERT_TRUE(b.wait([&] { return b.diag_number("bus", "malformed frames") >= 7; }, kPatienceS))
      << b.diag("bus", "malformed frames");
  const std::size_t n = b.encoder_count(1);
  EXPECT_TRUE(b.wait([&] { return b.encoder_count(1) > n + 5; }, kPatienceS));
}

TEST(Driver, SecondCommanderHolds) {
  Bench b;
  b.wait_ready();
  // The .test file starts another node publishing 5 V on mm1/a/command; we add our own publisher.
  ASSERT_TRUE(b.wait([&] { return b.diag("axis a", "multiple commanders") == "True"; }, kPatienceS))
      << "second commander not detected";
  const double held = b.last_voltage(0);
  // Our commands go on for 16 reports (1.5 s of the controller's clock) and until the driver counts one rejected.
  const std::size_t n0 = b.voltage_count(0);
  b.command_until(0, 40.0, [&] { return b.voltage_count(0) >= n0 + 16 && b.diag_number("axis a", "rejected held") > 0; });
  EXPECT_NEAR(b.last_voltage(0), held, 1e-9) << "moved with two commanders";
  EXPECT_GT(b.diag_number("axis a", "rejected held"), 0.0);
  EXPECT_EQ(b.diag("axis a", "__level"), "2");
}

// Start-up validation: each bad parameter stops the node with a message naming it (constructed in-process).
TEST(Driver, InvalidParametersAreNamed) {
  const std::vector<std::pair<std::string, XmlRpc::XmlRpcValue>> cases = {
      {"slew_rate_v_per_s", XmlRpc::XmlRpcValue(-1.0)},
      {"max_voltage_v", XmlRpc::XmlRpcValue(-90.0)},
      {"transport", XmlRpc::XmlRpcValue("carrier_pigeon")},
      {"command_timeout_s", XmlRpc::XmlRpcValue("soon")},
      {"udp_local_port", XmlRpc::XmlRpcValue(70000)},
      {"protocol/byte_order", XmlRpc::XmlRpcValue("middle")},
      {"protocol/voltage_lsb_v", XmlRpc::XmlRpcValue(0.0)},
      {"protocol/encoder_function_id", XmlRpc::XmlRpcValue(0x180)},  // collides with the voltage reports
      {"protocol/sync_function_id", XmlRpc::XmlRpcValue(0x180)},     // SYNC on axis a's voltage report id
      {"sync_max_in_flight", XmlRpc::XmlRpcValue(2)},                // without sync_mode: nothing to bound
  };
  int k = 0;
  for (const auto& [param, value] : cases) {
    const std::string ns = "/bad_params/driver_" + std::to_string(k++);
    ros::NodeHandle pnh(ns);
    pnh.setParam("transport", "udp");
    pnh.setParam("udp_local_port", 47990);
    pnh.setParam("udp_remote_port", 47991);
    pnh.setParam(param, value);
    try {
      piezo::mm3e::DriverNode node(ros::NodeHandle("/bad_params"), pnh);
      ADD_FAILURE() << param << ": accepted";
    } catch (const std::invalid_argument& e) {
      const std::string leaf = param.substr(param.rfind('/') + 1);
      EXPECT_NE(std::string(e.what()).find(leaf), std::string::npos) << param << ": " << e.what();
    }
  }
  // Synchronous mode: an idle SYNC interval the silence watchdog would take for a dead device.
  {
    ros::NodeHandle pnh("/bad_params/driver_sync");
    pnh.setParam("transport", "udp");
    pnh.setParam("udp_local_port", 47990);
    pnh.setParam("udp_remote_port", 47991);
    pnh.setParam("sync_mode", true);
    pnh.setParam("sync_idle_s", 5.0);
    try {
      piezo::mm3e::DriverNode node(ros::NodeHandle("/bad_params"), pnh);
      ADD_FAILURE() << "sync_idle_s 5 s with silence_reconnect_s 2 s accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("sync_idle_s"), std::string::npos) << e.what();
    }
  }
  {
    ros::NodeHandle spnh("/bad_params/sim_sync");
    spnh.setParam("transport", "udp");
    spnh.setParam("sync_mode", true);  // without publish_clock: nobody would move simulated time
    try {
      piezo::mm3e::SimNode node(ros::NodeHandle("/bad_params"), spnh);
      ADD_FAILURE() << "sync_mode without publish_clock accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("sync_mode"), std::string::npos) << e.what();
    }
  }
  // The simulated device too, including its own rule: a time scale needs the device to own /clock.
  ros::NodeHandle spnh("/bad_params/sim");
  spnh.setParam("transport", "udp");
  spnh.setParam("time_scale", 50.0);
  try {
    piezo::mm3e::SimNode node(ros::NodeHandle("/bad_params"), spnh);
    ADD_FAILURE() << "time_scale without publish_clock accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("time_scale"), std::string::npos) << e.what();
  }
}

// `--second-commander AXIS VOLTS`: run as a plain publisher node (a second commander for SecondCommanderHolds).
namespace {
// A commander that keeps publishing one value at 50 Hz on its own thread (the watchdog stays fed).
class Commander {
 public:
  Commander(Bench& b, int axis, double v) : b_(b), axis_(axis), v_(v), thread_([this] {
    while (running_ && ros::ok()) {
      b_.command(axis_, v_);
      ros::WallDuration(0.02).sleep();
    }
  }) {}
  ~Commander() {
    running_ = false;
    thread_.join();
  }

 private:
  Bench& b_;
  int axis_;
  double v_;
  std::atomic<bool> running_{true};
  std::thread thread_;
};

bool call_trigger(const std::string& name) {
  ros::ServiceClient c = ros::NodeHandle().serviceClient<std_srvs::Trigger>(name);
  if (!c.waitForExistence(ros::Duration(kPatienceS))) return false;
  std_srvs::Trigger t;
  return c.call(t) && t.response.success;
}

}  // namespace

TEST(Driver, ControllerRestartHoldsAndRampsFromPowerUp) {
  Bench b;
  b.wait_ready();
  const SlewGuarantee g = driver_slew_guarantee();
  const double slew = g.slew_v_per_s;
  ASSERT_GT(slew, 0.0) << "driver ~slew_rate_v_per_s not set";
  Commander commander(b, 0, 20.0);
  ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(0) - 20.0) < 1e-3; }, 20.0 / slew + kPatienceS))
      << b.last_voltage(0);
  const std::size_t before_restart = b.voltage_count(0);
  ASSERT_TRUE(call_trigger("/mm1/mm3e_sim/inject_restart"));
  // The driver sees the counter go back (and the boot heartbeat): axis held, ERROR naming both voltages.
  ASSERT_TRUE(b.wait([&] { return b.diag("axis a", "__level") == "2" && !b.diag("axis a", "device fault").empty(); },
                     kPatienceS))
      << b.diag("axis a", "__message");
  const std::string fault = b.diag("axis a", "device fault");
  EXPECT_NE(fault.find("axis a"), std::string::npos) << fault;
  EXPECT_NE(fault.find("reported 0.000 V"), std::string::npos) << fault;
  EXPECT_NE(fault.find("commanded 20.000 V"), std::string::npos) << fault;
  // Held at the power-up voltage while the commander keeps asking for 20 V: from the first report at 0 V on (the
  // restarted controller's), the next 11 reports (one second of the controller's clock) all stay at 0 V.
  auto first_power_up = [&](const std::vector<Sample>& v) {
    std::size_t k = before_restart;
    while (k < v.size() && std::abs(v[k].value) > 1e-6) ++k;
    return k;
  };
  constexpr std::size_t kHeldReports = 11;
  ASSERT_TRUE(b.wait([&] {
    const auto v = b.voltage(0);
    return first_power_up(v) + kHeldReports < v.size();
  }, kPatienceS)) << "no second of reports after the restart";
  {
    const auto v = b.voltage(0);
    for (std::size_t k = first_power_up(v); k < v.size(); ++k) EXPECT_NEAR(v[k].value, 0.0, 1e-6) << "moved while held";
  }
  // Until ~recover the driver holds the axis: no frame is written, every report (stamped before the call) is 0 V.
  const double recover_s = ros::WallTime::now().toSec();
  ASSERT_TRUE(call_trigger("/mm1/mm3e_driver/recover"));
  ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(0) - 20.0) < 1e-3; }, 20.0 / slew + kPatienceS))
      << b.last_voltage(0);
  const auto v = b.voltage(0);
  const std::size_t power_up = first_power_up(v);
  ASSERT_LT(power_up, v.size());
  const double power_up_v = v[power_up].value;
  for (std::size_t k = power_up; k < v.size() && v[k].stamp_s <= recover_s; ++k)
    EXPECT_NEAR(v[k].value, power_up_v, 1e-6) << "moved while held, report " << k;
  // From ~recover on the ramp starts at the power-up voltage, not at 20 V: every report is within slew of it since
  // the call, on the driver's clock (the device's restart itself, 20 V → 0 V, is no driver step and not checked).
  expect_ramp_from(v, power_up_v, recover_s, g, "after the restart");
  EXPECT_TRUE(b.wait([&] { return b.diag("axis a", "device fault").empty(); }, kPatienceS)) << "~recover did not clear it";
}

TEST(Driver, StuckAmplifierHolds) {
  Bench b;
  b.wait_ready();
  const SlewGuarantee g = driver_slew_guarantee();
  const double slew = g.slew_v_per_s;
  ASSERT_GT(slew, 0.0) << "driver ~slew_rate_v_per_s not set";
  {
    Commander commander(b, 1, 10.0);
    ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(1) - 10.0) < 1e-3; }, 10.0 / slew + kPatienceS));
  }
  ros::ServiceClient stuck = ros::NodeHandle().serviceClient<std_srvs::SetBool>("/mm1/mm3e_sim/inject_stuck_amplifier");
  ASSERT_TRUE(stuck.waitForExistence(ros::Duration(kPatienceS)));
  std_srvs::SetBool sb;
  sb.request.data = true;
  ASSERT_TRUE(stuck.call(sb) && sb.response.success);
  const std::size_t stuck_from = b.voltage_count(1);
  double recover_s = 0;
  {
    Commander commander(b, 1, 30.0);
    ASSERT_TRUE(b.wait([&] { return b.diag("axis b", "__level") == "2" && !b.diag("axis b", "device fault").empty(); },
                       kPatienceS))
        << b.diag("axis b", "__message");
    const std::string fault = b.diag("axis b", "device fault");
    EXPECT_NE(fault.find("axis b"), std::string::npos) << fault;
    EXPECT_NE(fault.find("device reports 10.000 V"), std::string::npos) << fault;
    // it ramped a little (at most max_unconfirmed_v past the last report that matched), then held
    const auto at = fault.find("commanded ");
    ASSERT_NE(at, std::string::npos) << fault;
    const double commanded = std::stod(fault.substr(at + 10));
    EXPECT_GT(commanded, 10.0) << fault;
    EXPECT_LE(commanded, 10.0 + 10.0 + 0.5) << fault;
    EXPECT_NE(b.diag("axis b", "__message").find("device reports"), std::string::npos);
    // Held: no frame moves the set point while the commander keeps asking for 30 V.
    // 1.5 s of the controller's clock (17 reports) while the commander asks for 30 V.
    ASSERT_TRUE(b.wait_reports(1, b.voltage_count(1), 17));
    EXPECT_NEAR(b.diag_number("axis b", "applied voltage [V]"), 10.0, 1e-6) << "re-baselined on the stuck voltage";
    sb.request.data = false;
    ASSERT_TRUE(stuck.call(sb) && sb.response.success);
    EXPECT_NEAR(b.last_voltage(1), 10.0, 1e-6) << "the released amplifier jumped to a frame sent while stuck";
    recover_s = ros::WallTime::now().toSec();
    ASSERT_TRUE(call_trigger("/mm1/mm3e_driver/recover"));
    ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(1) - 30.0) < 1e-3; }, 20.0 / slew + kPatienceS))
        << b.last_voltage(1);
  }
  // Stuck, then held by the fault until ~recover: the device shows the voltage it was stuck at; from the call on the
  // ramp starts there (every report within slew of it since the call, on the driver's clock).
  const auto v = b.voltage(1);
  ASSERT_LT(stuck_from, v.size());
  const double stuck_v = v[stuck_from].value;
  EXPECT_NEAR(stuck_v, 10.0, 1e-3);
  for (std::size_t k = stuck_from; k < v.size() && v[k].stamp_s <= recover_s; ++k)
    EXPECT_NEAR(v[k].value, stuck_v, 1e-6) << "moved while stuck or held, report " << k;
  expect_ramp_from(v, stuck_v, recover_s, g, "after the stuck amplifier");
}

// The controller's socket is closed mid-ramp (at least 0.5 s, and until the driver has counted a refused send):
// the kernel refuses the driver's sends (ECONNREFUSED) and the device hears nothing. Afterwards the ramp goes on
// from the voltage the device reports, not from where the lost and refused frames would have put it.
TEST(Driver, RefusedSendsDoNotJumpAfterwards) {
  Bench b;
  b.wait_ready();
  const SlewGuarantee g = driver_slew_guarantee();
  const double slew = g.slew_v_per_s;
  ASSERT_GT(slew, 0.0) << "driver ~slew_rate_v_per_s not set";
  ros::ServiceClient port = ros::NodeHandle().serviceClient<std_srvs::SetBool>("/mm1/mm3e_sim/inject_closed_port");
  ASSERT_TRUE(port.waitForExistence(ros::Duration(kPatienceS)));
  ASSERT_TRUE(b.wait([&] { return !b.diag("axis c", "frames refused by the transport").empty(); }, kPatienceS));
  const double refused_before = b.diag_number("axis c", "frames refused by the transport");
  Commander commander(b, 2, 40.0);
  ASSERT_TRUE(b.wait([&] { return b.last_voltage(2) > 10.0; }, 10.0 / slew + kPatienceS)) << b.last_voltage(2);
  std_srvs::SetBool sb;
  sb.request.data = true;
  ASSERT_TRUE(port.call(sb) && sb.response.success);
  const double closed_s = ros::WallTime::now().toSec();
  ros::WallDuration(0.5).sleep();
  // Still closed: the driver refuses a send and stops (nothing is proposed until the device reports again). The
  // diagnostics message that first counts the refusal gives the voltage the driver had applied then.
  std::map<std::string, std::string> at_refusal;
  ASSERT_TRUE(b.wait([&] {
    at_refusal = b.diag_status("axis c");
    const auto it = at_refusal.find("frames refused by the transport");
    return it != at_refusal.end() && std::stod(it->second) > refused_before;
  }, kPatienceS)) << "no send was refused: " << b.diag("axis c", "frames refused by the transport");
  const double applied_at_refusal = std::stod(at_refusal.at("applied voltage [V]"));
  // And closed for report_lag_s more: when the device reports again, every frame the driver wrote is older than
  // the window of values a report may still show, so the report is checked against the last one written only.
  ros::WallDuration(g.report_lag_s).sleep();
  const double reopened_s = ros::WallTime::now().toSec();
  sb.request.data = false;
  ASSERT_TRUE(port.call(sb) && sb.response.success);
  ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(2) - 40.0) < 1e-3; }, 40.0 / slew + kPatienceS))
      << b.last_voltage(2) << " V; device fault: " << b.diag("axis c", "device fault");
  const auto v = b.voltage(2);
  // Reports the driver received before the socket closed, and the first one after it reopened (the device sends
  // none while closed; the close took effect before the refusal, the reopening after reopened_s).
  double last_before = std::nan("");
  std::size_t after = v.size();
  for (std::size_t k = 0; k < v.size(); ++k) {
    if (v[k].receive_s < closed_s) last_before = v[k].value;
    if (v[k].stamp_s > reopened_s && after == v.size()) after = k;
  }
  ASSERT_FALSE(std::isnan(last_before));
  ASSERT_LT(after, v.size()) << "no report after the reopening";
  const double first_after = v[after].value;
  EXPECT_LT(last_before, 40.0 - 10.0) << "the ramp was over before the socket closed";
  // The device heard at most the frames written until the kernel refused one: its first report after the
  // reopening (sent before the driver, waiting for it, wrote anything new) is at most what the driver had applied.
  EXPECT_LE(first_after, applied_at_refusal + 1e-3) << "the device moved while its socket was closed";
  EXPECT_GE(first_after, last_before - 1e-3) << "went back while the socket was closed";
  // The driver goes on from the device's report: from an applied voltage that matches it within
  // report_tolerance_v (anything else pauses the ramp and then trips a device fault, checked below).
  EXPECT_LE(applied_at_refusal - first_after, g.report_tolerance_v)
      << "the driver went on ramping while the device heard nothing";
  // No jump: from that first report on (the driver writes nothing new before it has received it, so its stamp
  // bounds every later write from below), every report is within slew of it on the driver's clock.
  expect_ramp_from(v, first_after, v[after].stamp_s, g, "after the refused sends", g.report_tolerance_v);
  EXPECT_TRUE(b.diag("axis c", "device fault").empty()) << b.diag("axis c", "device fault");
}

int second_commander(int argc, char** argv) {
  ros::init(argc, argv, "second_commander");
  const std::string axis = argc > 2 ? argv[2] : "a";
  const double volts = argc > 3 ? std::stod(argv[3]) : 5.0;
  ros::NodeHandle nh("mm1");
  ros::Publisher pub = nh.advertise<VoltageCommand>(axis + "/command", 1);
  ros::Rate rate(5.0);
  while (ros::ok()) {
    VoltageCommand c;
    c.header.stamp = ros::Time::now();
    c.voltage = volts;
    pub.publish(c);
    rate.sleep();
  }
  return 0;
}

int main(int argc, char** argv) {
  if (argc > 1 && std::string(argv[1]) == "--second-commander") return second_commander(argc, argv);
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "driver_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  // A .test file whose --gtest_filter names no test must not pass silently (rostest only reads the XML).
  const std::string filter = testing::GTEST_FLAG(filter);
  bool matched = filter == "*";
  const auto* unit = testing::UnitTest::GetInstance();
  for (int i = 0; i < unit->total_test_suite_count(); ++i)
    for (int j = 0; j < unit->GetTestSuite(i)->total_test_count(); ++j) {
      const auto* info = unit->GetTestSuite(i)->GetTestInfo(j);
      matched |= filter == std::string(info->test_suite_name()) + "." + info->name();
    }
  if (!matched) {
    struct NoMatch : testing::Test {
      explicit NoMatch(std::string f) : f_(std::move(f)) {}
      void TestBody() override { FAIL() << "--gtest_filter=" << f_ << " names no test"; }
      std::string f_;
    };
    testing::RegisterTest("Driver", "FilterNamesNoTest", nullptr, nullptr, __FILE__, __LINE__,
                          [filter]() -> testing::Test* { return new NoMatch(filter); });
    testing::GTEST_FLAG(filter) = "Driver.FilterNamesNoTest";
  }
  return RUN_ALL_TESTS();
}
