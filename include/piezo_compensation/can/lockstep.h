// Lock-step with the simulated device (the driver's and mm3e_sim's ~sync_mode, docs/driver.md "Synchronous mode"):
// when the driver sends the next SYNC (SyncGate) and how fast the device lets simulated time run (SyncPace).
// Pure logic, no clock of their own, so each rule is tested in milliseconds (test/unit/test_can_lockstep.cpp).
#pragma once

#include <array>
#include <cstdint>

#include "piezo_compensation/io/axes.h"

namespace piezo::can {

// A SYNC goes out once every axis with a commander has a command since the last SYNC. With max_in_flight K > 0 a
// complete set waits while K SYNCs have no reading yet, and goes out with the reading that brings the count under
// K: a commander that answers both a reading and another message (the predictor: the encoder and the intent)
// completes two sets per sample, which unbounded runs the device ahead of every consumer until a queue overflows.
// K = 0: no bound. The caller serialises the calls (the driver holds its sync mutex).
class SyncGate {
 public:
  explicit SyncGate(int max_in_flight = 0);
  // A command on `axis`; has_commander: which axes have a commander now. True: send a SYNC now.
  bool on_command(int axis, const std::array<bool, io::kAxisCount>& has_commander);
  // A reading of `axis` is out. Every axis reports each sample once, so a sample counts as read with the first of
  // its readings. True: a waiting set may go now.
  bool on_reading(int axis);
  // After a SYNC was attempted (sent: it reached the bus).
  void synced(bool sent);
  // An idle SYNC (none for ~sync_idle_s): a SYNC or its sample was lost, or nobody commands; counting starts
  // afresh with this one.
  void idle();
  int in_flight() const { return in_flight_; }
  bool waiting() const { return waiting_; }

 private:
  int max_in_flight_;
  std::array<bool, io::kAxisCount> commanded_{};
  std::array<std::uint64_t, io::kAxisCount> readings_{};
  std::uint64_t samples_read_ = 0;  // the most readings of any axis
  int in_flight_ = 0;               // SYNCs sent whose sample has not been read
  bool waiting_ = false;            // a complete set waits for a reading
};

// mm3e_sim's ~sync_max_time_scale: lock-step, but simulated time never runs ahead of max_scale × wall time. A
// consumer that stalls still costs no sample (the SYNC waits for it); the ceiling keeps the rate where the nodes'
// 1-s ROS timers keep up. After a stall of more than `restart_after_s` behind the pace, the pace restarts from then:
// lost wall time is not caught up in a burst.
class SyncPace {
 public:
  SyncPace(double max_scale, double sim0_s, double wall0_s, double restart_after_s = 0.25);
  // Wall seconds to wait before the sample at sim_now_s may be taken (0: now); max_scale <= 0: always 0.
  double delay_s(double sim_now_s, double wall_now_s);

 private:
  double max_scale_, sim0_s_, wall0_s_, restart_after_s_;
};

}  // namespace piezo::can
