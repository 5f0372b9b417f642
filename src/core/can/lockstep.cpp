#include "piezo_compensation/can/lockstep.h"

#include <stdexcept>

namespace piezo::can {

SyncGate::SyncGate(int max_in_flight) : max_in_flight_(max_in_flight) {
  if (max_in_flight < 0) throw std::invalid_argument("sync gate: max_in_flight must be >= 0 (0: no bound)");
}

bool SyncGate::on_command(int axis, const std::array<bool, io::kAxisCount>& has_commander) {
  commanded_.at(static_cast<std::size_t>(axis)) = true;
  for (int i = 0; i < io::kAxisCount; ++i)
    if (has_commander[static_cast<std::size_t>(i)] && !commanded_[static_cast<std::size_t>(i)]) return false;
  if (max_in_flight_ > 0 && in_flight_ >= max_in_flight_) {
    waiting_ = true;  // goes out with the reading that brings in_flight_ under the bound
    return false;
  }
  return true;
}

bool SyncGate::on_reading(int axis) {
  if (++readings_.at(static_cast<std::size_t>(axis)) <= samples_read_) return false;
  samples_read_ = readings_[static_cast<std::size_t>(axis)];
  if (in_flight_ > 0) --in_flight_;
  return waiting_ && in_flight_ < max_in_flight_;
}

void SyncGate::synced(bool sent) {
  if (sent) ++in_flight_;
  waiting_ = false;
  commanded_.fill(false);
}

void SyncGate::idle() { in_flight_ = 0; }

SyncPace::SyncPace(double max_scale, double sim0_s, double wall0_s, double restart_after_s)
    : max_scale_(max_scale), sim0_s_(sim0_s), wall0_s_(wall0_s), restart_after_s_(restart_after_s) {}

double SyncPace::delay_s(double sim_now_s, double wall_now_s) {
  if (!(max_scale_ > 0.0)) return 0.0;
  const double due = wall0_s_ + (sim_now_s - sim0_s_) / max_scale_;
  if (wall_now_s > due + restart_after_s_) {
    wall0_s_ = wall_now_s;
    sim0_s_ = sim_now_s;
    return 0.0;
  }
  return due > wall_now_s ? due - wall_now_s : 0.0;
}

}  // namespace piezo::can
