#include "piezo_compensation/compensation/base_handover.h"

#include <cmath>

namespace piezo::compensation {

BaseHandover hand_over_base(models::AugmentedModel& fresh, const models::Model& running, const io::Dataset& data,
                            const std::string& axis, const std::vector<double>& warm_prediction,
                            const std::vector<double>& warm_base, const std::vector<double>& running_base) {
  BaseHandover h;
  if (!fresh.can_adopt_base_state(running)) {
    h.why = "its base is not the running model's";
    return h;
  }
  const std::size_t n = data.size();
  if (warm_prediction.size() != n || warm_base.size() != n || running_base.size() != n) {
    h.why = "the window's rows and the recorded predictions differ in number";
    return h;
  }
  const auto& measured = data.axis(axis).position_nm;
  double sum = 0.0;
  for (std::size_t i = n / 10; i < n; ++i) {
    const double e = measured[i] - (warm_prediction[i] - warm_base[i] + running_base[i]);
    if (!std::isfinite(e)) continue;
    sum += e;
    ++h.samples;
  }
  if (h.samples < 10 || h.samples < n / 4) {
    h.why = "too few of the window's samples have the running model's prediction (" + std::to_string(h.samples) + ")";
    h.samples = 0;
    return h;
  }
  h.offset_change_nm = sum / static_cast<double>(h.samples);
  fresh.adopt_base_state(running, h.offset_change_nm);
  h.done = true;
  return h;
}

}  // namespace piezo::compensation
