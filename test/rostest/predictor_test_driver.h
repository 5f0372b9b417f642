// A fake driver for the predictor rostests: publishes voltage/encoder pairs (same sequence number) of a plain
// 14 nm/V plant, applies the last command it received, and records predictions and commands.
#pragma once

#include <ros/ros.h>

#include <cmath>
#include <cstdint>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/VoltageCommand.h"
#include "wall_wait.h"

namespace piezo::test {

// Deadline of a wait for something that comes within a second on an idle host: the waits return as soon as their
// condition holds, so only a failing run pays it.
constexpr double kPatienceS = 30.0;

class FakeDriver {
 public:
  explicit FakeDriver(const std::string& ns = "/mm1/c") : nh_() {
    voltage_ = nh_.advertise<piezo_compensation::AxisVoltage>(ns + "/voltage", 10);
    encoder_ = nh_.advertise<piezo_compensation::EncoderPosition>(ns + "/encoder", 10);
    intended_ = nh_.advertise<piezo_compensation::IntendedMotion>(ns + "/intended", 10, true);
    command_ = nh_.subscribe(ns + "/command", 10, &FakeDriver::on_command, this);
    prediction_ = nh_.subscribe(ns + "/prediction", 100, &FakeDriver::on_prediction, this);
  }

  // Waits until the predictor is connected on every topic (returns as soon as it is).
  bool wait_connected(double timeout_s = kPatienceS) {
    return wait([&] {
      return voltage_.getNumSubscribers() > 0 && encoder_.getNumSubscribers() > 0 && intended_.getNumSubscribers() > 0 &&
             command_.getNumPublishers() > 0 && prediction_.getNumPublishers() > 0;
    }, timeout_s);
  }

  // Spins until pred() holds (true) or timeout_s of wall time pass (false). Returns as soon as it holds, so only a
  // failing run pays the deadline.
  template <typename Pred>
  static bool wait(Pred pred, double timeout_s = kPatienceS) {
    return wall_wait(pred, timeout_s, 0.002, true);
  }

  void intend(double voltage_v) {
    piezo_compensation::IntendedMotion m;
    m.header.stamp = ros::Time::now();
    m.mode = piezo_compensation::IntendedMotion::VOLTAGE;
    m.voltage = voltage_v;
    intended_.publish(m);
    intent_sent_ = true;
  }

  // One sample: the plant holds the last command; report it and its position. Waits for the prediction of this
  // sample (its stamp) and, once an intent was sent, for the command the predictor sends with it (config/predictor.yaml:
  // command_on_sample and forward_when_off, so one command per sample; the first one, if the intent arrives after
  // the first sample, from ~intended itself). False when either did not come within kPatienceS: a loaded host only
  // makes this slower.
  [[nodiscard]] bool cycle() {
    const std::size_t commands_before = commands.size(), predictions_before = predictions.size();
    ++seq_;
    ++samples_sent;
    piezo_compensation::AxisVoltage v;
    v.header.stamp = ros::Time::now();
    v.axis = "c";
    v.sequence = seq_;
    v.voltage = applied_v;
    reported_v = applied_v;
    piezo_compensation::EncoderPosition e;
    e.header.stamp = v.header.stamp;
    e.axis = "c";
    e.sequence = seq_;
    e.position = 14e-9 * applied_v;
    e.valid = true;
    encoder_.publish(e);  // encoder first on purpose: the node must pair by sequence
    voltage_.publish(v);
    const double stamp_s = v.header.stamp.toSec();
    const auto predicted = [&] {
      for (std::size_t k = predictions_before; k < predictions.size(); ++k)
        if (std::abs(predictions[k].header.stamp.toSec() - stamp_s) < 1e-6) return true;
      return false;
    };
    const bool ok = wait([&] {
      return predicted() && (!intent_sent_ || !expect_commands || commands.size() > commands_before);
    });
    if (!commands.empty()) applied_v = commands.back().voltage;
    return ok;
  }

  // n samples lost on the way (never published): a gap in the sequence numbers
  void lose(std::uint32_t n) { seq_ += n; }

  bool expect_commands = true;  // false: a test step in which the predictor sends no command per sample
  double applied_v = 0.0;   // what the plant holds next (the last command)
  double reported_v = 0.0;  // what the last published sample held
  std::size_t samples_sent = 0;  // voltage/encoder pairs published (lost ones not counted)
  std::vector<piezo_compensation::VoltageCommand> commands;
  std::vector<piezo_compensation::Prediction> predictions;

 private:
  void on_command(const piezo_compensation::VoltageCommand::ConstPtr& m) { commands.push_back(*m); }
  void on_prediction(const piezo_compensation::Prediction::ConstPtr& m) { predictions.push_back(*m); }

  ros::NodeHandle nh_;
  ros::Publisher voltage_, encoder_, intended_;
  ros::Subscriber command_, prediction_;
  std::uint32_t seq_ = 100;
  bool intent_sent_ = false;
};

}  // namespace piezo::test
