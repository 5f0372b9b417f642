// The driver over a pseudo-terminal to the simulated NanoControl (transport nanocontrol), checked from outside
// through its topics, services and diagnostics, and through the set points the simulated controller took
// (<axis>/device_set_point). One .test file per behaviour selects its case with --gtest_filter.
#include <diagnostic_msgs/DiagnosticArray.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <std_srvs/SetBool.h>
#include <std_srvs/Trigger.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <mutex>
#include <string>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/VoltageCommand.h"
#include "wall_wait.h"

using piezo_compensation::AxisVoltage;
using piezo_compensation::EncoderPosition;
using piezo_compensation::VoltageCommand;

namespace {

// A wait returns as soon as its condition holds: only a failing run pays the deadline.
constexpr double kPatienceS = 20.0;
const char* kAxes[] = {"a", "b", "c"};

class Bench {
 public:
  // commander: advertise <axis>/command (false when another node, the predictor, is the one commander)
  explicit Bench(bool commander = true) : nh_("mm1"), commander_(commander) {
    for (int i = 0; i < 3; ++i) {
      const std::string a = kAxes[i];
      subs_.push_back(nh_.subscribe<EncoderPosition>(a + "/encoder", 100, [this, i](const EncoderPosition::ConstPtr& m) {
        std::lock_guard<std::mutex> l(mutex_);
        encoder_stamps_[i].push_back(m->header.stamp.toSec());
        encoder_seq_[i].push_back(m->sequence);
      }));
      subs_.push_back(nh_.subscribe<AxisVoltage>(a + "/voltage", 100, [this, i](const AxisVoltage::ConstPtr& m) {
        std::lock_guard<std::mutex> l(mutex_);
        voltage_[i].push_back(m->voltage);
      }));
      subs_.push_back(nh_.subscribe<AxisVoltage>(a + "/device_set_point", 1000, [this, i](const AxisVoltage::ConstPtr& m) {
        std::lock_guard<std::mutex> l(mutex_);
        set_points_[i].push_back(m->voltage);
      }));
      if (commander_) commands_[i] = nh_.advertise<VoltageCommand>(a + "/command", 1);
    }
    subs_.push_back(ros::NodeHandle().subscribe<diagnostic_msgs::DiagnosticArray>(
        "/diagnostics", 50, [this](const diagnostic_msgs::DiagnosticArray::ConstPtr& m) {
          std::lock_guard<std::mutex> l(mutex_);
          for (const auto& s : m->status) {
            auto& d = diag_[s.name.substr(s.name.rfind(": ") + 2)];
            d["__level"] = std::to_string(int(s.level));
            d["__message"] = s.message;
            for (const auto& kv : s.values) d[kv.key] = kv.value;
          }
        }));
  }
  ~Bench() {
    for (auto& s : subs_) s.shutdown();
  }

  template <typename Pred>
  bool wait(Pred pred, double seconds = kPatienceS) {
    return piezo::test::wall_wait(pred, seconds, 0.01);
  }
  std::size_t encoders(int axis) {
    std::lock_guard<std::mutex> l(mutex_);
    return encoder_stamps_[axis].size();
  }
  std::vector<double> encoder_stamps(int axis) {
    std::lock_guard<std::mutex> l(mutex_);
    return encoder_stamps_[axis];
  }
  std::vector<std::uint32_t> encoder_sequences(int axis) {
    std::lock_guard<std::mutex> l(mutex_);
    return encoder_seq_[axis];
  }
  double last_voltage(int axis) {
    std::lock_guard<std::mutex> l(mutex_);
    return voltage_[axis].empty() ? std::nan("") : voltage_[axis].back();
  }
  std::vector<double> set_points(int axis) {
    std::lock_guard<std::mutex> l(mutex_);
    return set_points_[axis];
  }
  std::string diag(const std::string& status, const std::string& key) {
    std::lock_guard<std::mutex> l(mutex_);
    auto s = diag_.find(status);
    if (s == diag_.end()) return "";
    auto v = s->second.find(key);
    return v == s->second.end() ? "" : v->second;
  }
  double diag_number(const std::string& status, const std::string& key) {
    const std::string v = diag(status, key);
    return v.empty() ? std::nan("") : std::atof(v.c_str());
  }
  void command(int axis, double v) {
    VoltageCommand c;
    c.header.stamp = ros::Time::now();
    c.voltage = v;
    commands_[axis].publish(c);
  }
  // Commands v at 20 Hz until the read-back shows it (the watchdog fed meanwhile).
  bool drive(int axis, double v, double seconds = kPatienceS) {
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(seconds);
    while (ros::ok() && ros::WallTime::now() < end) {
      command(axis, v);
      if (std::abs(last_voltage(axis) - v) < 0.01) return true;
      ros::WallDuration(0.05).sleep();
    }
    return false;
  }
  void wait_ready() {
    ASSERT_TRUE(wait([&] {
      for (int i = 0; i < 3; ++i)
        if (encoders(i) < 3 || (commander_ && commands_[i].getNumSubscribers() == 0) || std::isnan(last_voltage(i)))
          return false;
      return !diag("nanocontrol", "samples").empty();
    })) << "driver and simulated NanoControl not up";
  }
  bool call(const std::string& service) {
    std_srvs::Trigger t;
    return ros::service::call(service, t) && t.response.success;
  }
  bool set(const std::string& service, bool on) {
    std_srvs::SetBool b;
    b.request.data = on;
    return ros::service::call(service, b) && b.response.success;
  }
  // Every set point the controller took lies within the driver's limits.
  void expect_within_limits(double lo, double hi) {
    for (int i = 0; i < 3; ++i)
      for (double v : set_points(i)) {
        EXPECT_GE(v, lo - 1e-9) << "axis " << kAxes[i];
        EXPECT_LE(v, hi + 1e-9) << "axis " << kAxes[i];
      }
  }

 private:
  ros::NodeHandle nh_;
  bool commander_;
  std::vector<ros::Subscriber> subs_;
  std::array<ros::Publisher, 3> commands_;
  std::mutex mutex_;
  std::array<std::vector<double>, 3> encoder_stamps_, voltage_, set_points_;
  std::array<std::vector<std::uint32_t>, 3> encoder_seq_;
  std::map<std::string, std::map<std::string, std::string>> diag_;
};

constexpr double kLimitV = 30.0;  // the .test files set min/max_voltage_v to ±30 V

double median_interval_s(std::vector<double> stamps) {
  std::vector<double> d;
  for (std::size_t k = 1; k < stamps.size(); ++k) d.push_back(stamps[k] - stamps[k - 1]);
  if (d.empty()) return std::nan("");
  std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
  return d[d.size() / 2];
}

}  // namespace

TEST(NanoControl, TopicsAtTheSampleRateAndNothingBeyondTheLimits) {
  Bench b;
  b.wait_ready();
  const std::size_t start = b.encoders(2);
  ASSERT_TRUE(b.wait([&] { return b.encoders(2) >= start + 30; }));
  for (int i = 0; i < 3; ++i) {
    const auto stamps = b.encoder_stamps(i);
    const std::vector<double> tail(stamps.end() - 25, stamps.end());
    const double period = median_interval_s(tail);
    // min_sample_period_s 0.1 and 6 exchanges of 16 ms: ≈ 10 Hz
    EXPECT_GT(period, 0.085) << "axis " << kAxes[i];
    EXPECT_LT(period, 0.14) << "axis " << kAxes[i];
    const auto seq = b.encoder_sequences(i);
    for (std::size_t k = 1; k < seq.size(); ++k) EXPECT_EQ(seq[k], seq[k - 1] + 1) << "axis " << kAxes[i];
    std::printf("axis %s: median sample interval %.4f s (%.2f Hz)\n", kAxes[i], period, 1.0 / period);
  }
  EXPECT_FALSE(b.diag("nanocontrol", "version").empty());
  EXPECT_GE(b.diag_number("nanocontrol", "reading sigma c [m]"), 0.0);
  ASSERT_TRUE(b.drive(2, 12.5));
  EXPECT_NEAR(b.set_points(2).back(), 12.5, 0.003);  // one DAC count is 2.4 mV
  // beyond the limit: clamped, never sent beyond
  for (int k = 0; k < 20; ++k) {
    b.command(2, 45.0);
    ros::WallDuration(0.05).sleep();
  }
  ASSERT_TRUE(b.wait([&] { return std::abs(b.last_voltage(2) - kLimitV) < 0.01; }));
  b.expect_within_limits(-kLimitV, kLimitV);
  EXPECT_GE(b.diag_number("axis c", "clamped"), 1.0);
}

TEST(NanoControl, ErrorReplyIsRefusedNamedAndNotGuessed) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.drive(2, 5.0));
  const std::size_t before = b.set_points(2).size();
  ASSERT_TRUE(b.call("/mm1/mm3e_sim/inject_error_reply"));
  b.command(2, 6.0);
  ASSERT_TRUE(b.wait([&] { return b.diag_number("nanocontrol", "refused (e)") >= 1; }));
  EXPECT_NE(b.diag("nanocontrol", "last refusal").find("`fine16 C "), std::string::npos) << b.diag("nanocontrol", "last refusal");
  EXPECT_NE(b.diag("nanocontrol", "last refusal").find("refused"), std::string::npos);
  ASSERT_TRUE(b.wait([&] { return b.diag_number("axis c", "frames refused by the transport") >= 1; }));
  // the refused set point was not applied; the next one starts from the read-back
  ASSERT_TRUE(b.drive(2, 6.0));
  const auto sp = b.set_points(2);
  ASSERT_GT(sp.size(), before);
  EXPECT_NEAR(b.last_voltage(2), 6.0, 0.01);
  b.expect_within_limits(-kLimitV, kLimitV);
}

TEST(NanoControl, LostPartialAndGarbledRepliesHoldReportAndCarryOn) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.drive(2, -4.0));
  ASSERT_TRUE(b.call("/mm1/mm3e_sim/inject_lost_reply"));
  ASSERT_TRUE(b.wait([&] { return b.diag_number("nanocontrol", "timeouts") >= 1; }));
  EXPECT_NE(b.diag("nanocontrol", "last timeout").find("no reply within 0.2 s"), std::string::npos)
      << b.diag("nanocontrol", "last timeout");
  ASSERT_TRUE(b.call("/mm1/mm3e_sim/inject_partial_reply"));
  ASSERT_TRUE(b.wait([&] { return b.diag_number("nanocontrol", "timeouts") >= 2; }));
  ASSERT_TRUE(b.call("/mm1/mm3e_sim/inject_garbled_reply"));
  ASSERT_TRUE(b.wait([&] { return b.diag_number("nanocontrol", "garbled replies") >= 1; }));
  EXPECT_NE(b.diag("nanocontrol", "last garbled").find("does not start with a status"), std::string::npos)
      << b.diag("nanocontrol", "last garbled");
  EXPECT_GE(b.diag_number("nanocontrol", "samples dropped"), 1.0);
  // no reconnect for a lost reply; the samples and the axis go on
  EXPECT_EQ(b.diag_number("bus", "connects"), 1.0);
  const std::size_t n = b.encoders(2);
  ASSERT_TRUE(b.wait([&] { return b.encoders(2) >= n + 5; }));
  ASSERT_TRUE(b.drive(2, 3.0));
  b.expect_within_limits(-kLimitV, kLimitV);
}

TEST(NanoControl, BreakdownHoldsEveryAxisUntilRecover) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.drive(2, 2.0));
  ASSERT_TRUE(b.call("/mm1/mm3e_sim/inject_breakdown"));
  ASSERT_TRUE(b.wait([&] { return b.diag("nanocontrol", "breakdown latched") == "True"; }));
  ASSERT_TRUE(b.wait([&] { return b.diag("axis c", "__level") == "2" && b.diag("axis a", "__level") == "2"; }));
  EXPECT_NE(b.diag("nanocontrol", "__message").find("Piezo Voltage Breakdown"), std::string::npos)
      << b.diag("nanocontrol", "__message");
  const std::size_t held = b.set_points(2).size();
  for (int k = 0; k < 20; ++k) {
    b.command(2, 8.0);
    ros::WallDuration(0.05).sleep();
  }
  EXPECT_EQ(b.set_points(2).size(), held) << "a set point went out after the breakdown";
  EXPECT_GE(b.diag_number("axis c", "rejected held"), 1.0);
  ASSERT_TRUE(b.call("/mm1/mm3e_driver/recover"));
  ASSERT_TRUE(b.wait([&] { return b.diag("nanocontrol", "breakdown latched") == "False"; }));
  ASSERT_TRUE(b.drive(2, 8.0));
  b.expect_within_limits(-kLimitV, kLimitV);
}

TEST(NanoControl, PortLostReconnectsAndRebaselinesFromTheReadBack) {
  Bench b;
  b.wait_ready();
  ASSERT_TRUE(b.drive(2, 8.0));
  ASSERT_TRUE(b.set("/mm1/mm3e_sim/inject_port_lost", true));
  ASSERT_TRUE(b.wait([&] { return b.diag("bus", "state") == "disconnected"; }));
  // the loss, or (a diagnostics period later) the reopen attempts while the link is gone
  const std::string error = b.diag("bus", "last error");
  EXPECT_TRUE(error.find("port lost") != std::string::npos || error.find("cannot open") != std::string::npos) << error;
  // commanded while the port is away: refused, never queued
  EXPECT_TRUE(b.wait([&] {
    b.command(2, 20.0);
    ros::WallDuration(0.05).sleep();
    return b.diag_number("axis c", "rejected no link") >= 1.0;
  }));
  const std::size_t before = b.set_points(2).size();
  ASSERT_TRUE(b.set("/mm1/mm3e_sim/inject_port_lost", false));
  ASSERT_TRUE(b.wait([&] { return b.diag_number("bus", "connects") >= 2 && b.diag("bus", "state") == "active"; }));
  ASSERT_TRUE(b.drive(2, 20.0));
  const auto sp = b.set_points(2);
  ASSERT_GT(sp.size(), before);
  // from the read-back 8 V, one frame step (max_frame_step_v 5 V) at a time, each rounded to the nearest DAC count
  // (half a count: 1.22 mV)
  const double count_v = 0.5 / 409.6 + 1e-9;
  EXPECT_LE(sp[before], 8.0 + 5.0 + 2 * count_v);
  for (std::size_t k = before + 1; k < sp.size(); ++k) EXPECT_LE(std::abs(sp[k] - sp[k - 1]), 5.0 + 2 * count_v);
  b.expect_within_limits(-kLimitV, kLimitV);
}

// The predictor (axis c, compensation on) commands through the serial path: its corrected voltage is what the
// controller takes, and it predicts on every sample.
TEST(NanoControlLoop, PredictorCompensatesThroughTheSerialPath) {
  Bench b(false);
  b.wait_ready();
  ros::NodeHandle nh("mm1");
  std::mutex m;
  std::vector<piezo_compensation::Prediction> predictions;
  auto sub = nh.subscribe<piezo_compensation::Prediction>("c/prediction", 100,
                                                          [&](const piezo_compensation::Prediction::ConstPtr& p) {
                                                            std::lock_guard<std::mutex> l(m);
                                                            predictions.push_back(*p);
                                                          });
  auto intended = nh.advertise<piezo_compensation::IntendedMotion>("c/intended", 1);
  ASSERT_TRUE(b.wait([&] { return intended.getNumSubscribers() > 0; }));
  const double intent_v = 20.0;
  piezo_compensation::Prediction last;
  const bool settled = b.wait([&] {
    piezo_compensation::IntendedMotion im;
    im.header.stamp = ros::Time::now();
    im.mode = piezo_compensation::IntendedMotion::VOLTAGE;
    im.voltage = intent_v;
    intended.publish(im);
    ros::WallDuration(0.1).sleep();
    std::lock_guard<std::mutex> l(m);
    if (predictions.size() < 30) return false;
    last = predictions.back();
    return last.compensation_active && std::abs(b.last_voltage(2) - last.corrected_voltage) < 0.05;
  }, 40.0);
  ASSERT_TRUE(settled) << predictions.size() << " predictions";
  EXPECT_FALSE(last.fallback) << last.status;
  EXPECT_TRUE(std::isfinite(last.predicted_position));
  EXPECT_TRUE(std::isfinite(last.measured_position));
  EXPECT_GT(std::abs(last.corrected_voltage - intent_v), 0.01) << "the correction changes the voltage";
  EXPECT_NEAR(b.set_points(2).back(), last.corrected_voltage, 0.05) << "the controller took the corrected voltage";
  std::printf("intent %.2f V -> corrected %.3f V, predicted %.1f nm, measured %.1f nm, intended %.1f nm\n", intent_v,
              last.corrected_voltage, last.predicted_position * 1e9, last.measured_position * 1e9,
              last.intended_position * 1e9);
  b.expect_within_limits(-kLimitV, kLimitV);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "nanocontrol_rostest");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  return RUN_ALL_TESTS();
}
