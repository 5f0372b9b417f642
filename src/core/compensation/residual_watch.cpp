#include "piezo_compensation/compensation/residual_watch.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

namespace piezo::compensation {

ResidualWatch::ResidualWatch(const ResidualWatchOptions& o) : o_(o) {
  if (!(o_.window_s > 0.0) || !std::isfinite(o_.window_s)) throw std::invalid_argument("watch_window_s must be > 0");
  if (!(o_.noise_floor_nm > 0.0) || !std::isfinite(o_.noise_floor_nm))
    throw std::invalid_argument("watch_noise_floor_nm must be > 0");
  if (!(o_.k >= 1.0) || !std::isfinite(o_.k)) throw std::invalid_argument("watch_k must be ≥ 1");
  if (!(o_.hold_s >= 0.0) || !std::isfinite(o_.hold_s)) throw std::invalid_argument("watch_hold_s must be ≥ 0");
}

void ResidualWatch::clear() {
  window_.clear();
  sum_ = 0.0;
  above_since_ = -1.0;
  warning_ = false;
}

void ResidualWatch::add(double t_s, double residual_nm) {
  if (!std::isfinite(residual_nm) || !std::isfinite(t_s)) return;
  if (!window_.empty() && t_s < window_.back().first) clear();  // time went back (bag loop, sim restart)
  now_ = t_s;
  window_.emplace_back(t_s, std::abs(residual_nm));
  sum_ += std::abs(residual_nm);
  while (!window_.empty() && window_.front().first <= t_s - o_.window_s) {
    sum_ -= window_.front().second;
    window_.pop_front();
  }
  const double mae = rolling_mae_nm();
  if (std::isfinite(mae) && mae > threshold_nm()) {
    if (above_since_ < 0.0) above_since_ = t_s;
    if (t_s - above_since_ >= o_.hold_s) warning_ = true;
  } else if (std::isfinite(mae)) {
    above_since_ = -1.0;
    warning_ = false;
  }
}

double ResidualWatch::rolling_mae_nm() const {
  if (window_.size() < 2 || window_.back().first - window_.front().first < 0.5 * o_.window_s) return std::nan("");
  return sum_ / static_cast<double>(window_.size());
}

double ResidualWatch::above_for_s() const { return above_since_ < 0.0 ? 0.0 : now_ - above_since_; }

std::string ResidualWatch::message(const std::string& axis) const {
  std::ostringstream m;
  m.precision(3);
  m << "axis " << axis << ": rolling free-run MAE " << rolling_mae_nm() << " nm over " << o_.window_s << " s";
  if (warning_)
    m << " has been above " << o_.k << " x noise floor (" << threshold_nm() << " nm) for " << above_for_s()
      << " s: the model no longer matches the stage; call ~snapshot and run `piezo residual` on the bag, then "
         "~reload_model with the model it writes";
  else
    m << " (threshold " << threshold_nm() << " nm)";
  return m.str();
}

}  // namespace piezo::compensation
