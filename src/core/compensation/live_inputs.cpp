#include "piezo_compensation/compensation/live_inputs.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/models/augmented_model.h"

namespace piezo::compensation {
namespace {

constexpr std::size_t kKeep = 64;

void keep(std::deque<LiveInputs::Report>& q, std::uint32_t seq, double v) {
  q.push_back({seq, v});
  while (q.size() > kKeep) q.pop_front();
}

const auto by_seq = [](const LiveInputs::Report& r) { return r.seq; };
// upper_bound on the stamp: the first aux value stamped after t
const auto stamped_after = [](double t, const LiveInputs::Aux& a) { return t < a.stamp_s; };

}  // namespace

void LiveInputs::add_voltage(const std::string& axis, std::uint32_t seq, double voltage_v) {
  keep(voltages_[axis], seq, voltage_v);
}
void LiveInputs::add_reading(const std::string& axis, std::uint32_t seq, double position_nm) {
  keep(readings_[axis], seq, position_nm);
}
void LiveInputs::add_fused(const std::string& axis, std::uint32_t seq, double fused_nm) {
  keep(fused_[axis], seq, fused_nm);
}
void LiveInputs::add_aux(const std::string& name, double value, double stamp_s, double time_s) {
  auto& q = aux_[name];
  // usually appended; a message stamped before the last one goes to its place (a sensor's messages may overtake)
  auto at = std::upper_bound(q.begin(), q.end(), stamp_s, stamped_after);
  q.insert(at, Aux{value, stamp_s, time_s});
  while (q.size() > kAuxKept) q.pop_front();
}
const std::deque<LiveInputs::Report>* LiveInputs::voltages(const std::string& axis) const {
  auto it = voltages_.find(axis);
  return it == voltages_.end() ? nullptr : &it->second;
}
const std::deque<LiveInputs::Report>* LiveInputs::readings(const std::string& axis) const {
  auto it = readings_.find(axis);
  return it == readings_.end() ? nullptr : &it->second;
}
const std::deque<LiveInputs::Report>* LiveInputs::fused(const std::string& axis) const {
  auto it = fused_.find(axis);
  return it == fused_.end() ? nullptr : &it->second;
}
const LiveInputs::Aux* LiveInputs::aux(const std::string& name, double stamp_s) const {
  auto it = aux_.find(name);
  if (it == aux_.end() || it->second.empty()) return nullptr;
  const auto& q = it->second;
  auto after = std::upper_bound(q.begin(), q.end(), stamp_s, stamped_after);
  return after == q.begin() ? &q.front() : &*std::prev(after);
}

double neutral_input(const models::Model& model, const std::string& name) {
  // The training data's typical value of the signal: there a term adds only its constant part and a gain scales
  // by 1. Linear and play terms standardise their output by its training mean; gains and powers centre the
  // signal itself (pre_center). A time gain read at time 0 would scale the motion by ~10⁷ (seconds since 1970).
  if (const auto* aug = dynamic_cast<const models::AugmentedModel*>(&model))
    for (const auto& t : aug->terms()) {
      if (t.signal != name) continue;
      if (t.is_gain() || t.kind() == models::TermKind::kPowers) return t.pre_center;
      if (!t.center.empty() && (t.kind() == models::TermKind::kLinear || t.kind() == models::TermKind::kPlay))
        return t.center.front();
    }
  return 0.0;
}

InputFeeder::InputFeeder(const models::Model& model, const std::string& own_axis, const AuxFeedOptions& options)
    : o_(options), own_axis_(own_axis) {
  std::vector<std::string> axes(io::kAxisNames.begin(), io::kAxisNames.end());
  for (const auto& name : model.aux_inputs()) {
    models::InputSource s;
    try {
      s = models::classify_input(name, own_axis, axes);
    } catch (const std::exception& e) {
      throw std::runtime_error(std::string("model input: ") + e.what());
    }
    if (s.kind == models::InputSource::Kind::kTime && model.meta.time_clock != kRosTimeClock)
      throw std::runtime_error("the model reads time_s on the clock '" +
                               (model.meta.time_clock.empty() ? std::string("of its data file (not ROS time)")
                                                              : model.meta.time_clock) +
                               "', the predictor feeds ROS time: fit it on a bag the nodes recorded (e.g. a "
                               "~snapshot), whose model file says time_clock: ros");
    sources_.push_back(s);
    neutral_.push_back(neutral_input(model, name));
  }
  const std::size_t n = sources_.size();
  states_.resize(n);
  ramp_from_.assign(n, 0.0);
  ramp_start_.assign(n, 0.0);
  ever_fed_.assign(n, 0);
  ramping_.assign(n, 0);
}

bool InputFeeder::any_fallback() const {
  return std::any_of(states_.begin(), states_.end(), [](const State& s) { return s.fallback; });
}

bool InputFeeder::fill(const LiveInputs& live, const io::PairedSample& sample, double now_s, bool give_up,
                       double* out) {
  using Kind = models::InputSource::Kind;
  // cross-axis values first: the sample may have to wait for them (nothing is changed before it can go)
  std::vector<double> cross(sources_.size(), std::nan(""));
  for (std::size_t k = 0; k < sources_.size(); ++k) {
    const auto& s = sources_[k];
    if (s.kind != Kind::kAxisVoltage && s.kind != Kind::kAxisPosition && s.kind != Kind::kAxisFused) continue;
    if (s.kind == Kind::kAxisVoltage && s.axis == own_axis_) {
      cross[k] = sample.voltage_v;
      continue;
    }
    const auto* q = s.kind == Kind::kAxisVoltage  ? live.voltages(s.axis)
                    : s.kind == Kind::kAxisFused ? live.fused(s.axis)
                                                 : live.readings(s.axis);
    const std::uint32_t want = s.kind == Kind::kAxisVoltage ? sample.sequence : sample.sequence - 1;
    const LiveInputs::Report* r = nullptr;
    const io::ReportMatch m = q ? io::match_report(*q, want, give_up, by_seq, &r)
                                : (give_up ? io::ReportMatch::kLost : io::ReportMatch::kWaiting);
    if (m == io::ReportMatch::kWaiting) return false;
    if (r) cross[k] = r->value;
  }
  for (std::size_t k = 0; k < sources_.size(); ++k) {
    const auto& s = sources_[k];
    State& st = states_[k];
    double fresh = std::nan("");
    std::string why;
    switch (s.kind) {
      case Kind::kTime:
        fresh = sample.stamp_s;
        break;
      case Kind::kAxisVoltage:
      case Kind::kAxisPosition:
      case Kind::kAxisFused:
        fresh = cross[k];
        if (!std::isfinite(fresh)) why = s.name + ": no value from axis " + s.axis + " yet";
        break;
      case Kind::kAux: {
        const LiveInputs::Aux* a = live.aux(s.name, sample.stamp_s);
        if (!a) {
          why = s.name + ": no message received";
        } else if (now_s - a->time_s > o_.stale_after_s) {
          std::ostringstream w;
          w.precision(3);
          w << s.name << ": stale (last " << now_s - a->time_s << " s ago > " << o_.stale_after_s << " s)";
          why = w.str();
        } else if (!std::isfinite(a->value)) {
          why = s.name + ": not finite";
        } else {
          fresh = a->value;
        }
        break;
      }
    }
    if (!std::isfinite(fresh)) {
      // fallback: hold what was fed (the term stays where it was), before anything the neutral value
      const double held = ever_fed_[k] ? st.fed : neutral_[k];
      st.fallback = true;
      st.status = why + "; fed " + std::to_string(held) + (ever_fed_[k] ? " (held)" : " (neutral)");
      ++st.fallback_samples;
      ramping_[k] = 1;
      ramp_from_[k] = held;
      ramp_start_[k] = now_s;
      st.fed = out[k] = held;
      ever_fed_[k] = 1;
      continue;
    }
    double v = fresh;
    if (ramping_[k] && s.kind == Kind::kAux && o_.recovery_s > 0.0) {
      const double f = std::clamp((now_s - ramp_start_[k]) / o_.recovery_s, 0.0, 1.0);
      v = ramp_from_[k] + f * (fresh - ramp_from_[k]);
      if (f >= 1.0) ramping_[k] = 0;
    } else {
      ramping_[k] = 0;
    }
    st.fallback = false;
    st.status.clear();
    st.fed = out[k] = v;
    ever_fed_[k] = 1;
  }
  return true;
}

}  // namespace piezo::compensation
