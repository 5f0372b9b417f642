#include "piezo_compensation/compensation/demo_scenario.h"

#include <algorithm>
#include <cmath>
#include <iterator>
#include <stdexcept>

#include <yaml-cpp/yaml.h>

#include "piezo_compensation/protocols/protocol.h"

namespace piezo::compensation {
namespace {

void ramp(std::vector<DemoStep>& s, int mode, int seg, const std::string& ph, double from, double to, double dur_s,
          double hz) {
  const int n = std::max(1, static_cast<int>(std::lround(dur_s * hz)));
  for (int i = 1; i <= n; ++i) s.push_back({mode, seg, ph, from + (to - from) * i / n});
}
void hold(std::vector<DemoStep>& s, int mode, int seg, const std::string& ph, double v, double dur_s, double hz) {
  const int n = static_cast<int>(std::lround(dur_s * hz));
  for (int i = 0; i < n; ++i) s.push_back({mode, seg, ph, v});
}

}  // namespace

std::vector<DemoStep> sawtooth_demo_steps(double hz) {
  std::vector<DemoStep> s;
  for (int mode = 0; mode < 2; ++mode) {
    hold(s, mode, 0, "rest", 0.0, 30.0, hz);
    // Triangles 0 → +A → −A → 0 with A = 10 … 70 V, 8 V/s (Fig. 11 of the study: increasing amplitude).
    for (double a = 10.0; a <= 70.0 + 1e-9; a += 10.0) {
      ramp(s, mode, 0, "saw", 0.0, a, a / 8.0, hz);
      ramp(s, mode, 0, "saw", a, -a, 2 * a / 8.0, hz);
      ramp(s, mode, 0, "saw", -a, 0.0, a / 8.0, hz);
    }
    hold(s, mode, 0, "rest", 0.0, 5.0, hz);
  }
  return s;
}

// The chosen scenarios of the creep protocol (axis c column): its history, then its hold. A short ramp
// (≤ 8 V/s) joins the scenarios, which in the protocol follow other scenarios.
std::vector<DemoStep> creep_demo_steps(const CreepDemoOptions& o, double hz) {
  if (o.scenarios.empty()) throw std::invalid_argument("~creep_scenarios: empty list");
  if (!(o.hold_s > 0.0) || !(o.history_s > 0.0)) throw std::invalid_argument("~hold_s and ~creep_history_s must be > 0 s");
  YAML::Node params;
  params["history_s"] = o.history_s;
  params["hold_s"] = o.hold_s;
  const auto protocol = protocols::make_protocol("creep", params, hz, static_cast<std::uint64_t>(o.seed));
  std::map<int, std::vector<protocols::ProtocolSample>> by_segment;
  for (std::size_t i = 0; i < protocol->size(); ++i) {
    const auto p = protocol->at(i);
    by_segment[p.segment].push_back(p);
  }
  std::vector<DemoStep> s;
  double v = 0.0;
  const int n_scen = static_cast<int>(by_segment.size());
  for (int mode = 0; mode < 2; ++mode) {
    for (std::size_t h = 0; h < o.scenarios.size(); ++h) {
      const int seg = o.scenarios[h];
      if (seg < 0 || seg >= n_scen)
        throw std::invalid_argument("~creep_scenarios: " + std::to_string(seg) + " outside 0.." +
                                    std::to_string(n_scen - 1));
      const auto& samples = by_segment.at(seg);
      const double first = samples.front().voltage_v[2];
      ramp(s, mode, static_cast<int>(h), "rest", v, first, std::max(5.0, std::abs(first - v) / 8.0), hz);
      for (const auto& p : samples)
        s.push_back({mode, static_cast<int>(h), p.phase == protocols::Phase::kHold ? "hold" : "history", p.voltage_v[2]});
      v = samples.back().voltage_v[2];
    }
  }
  ramp(s, 1, static_cast<int>(o.scenarios.size()) - 1, "rest", v, 0.0, std::max(5.0, std::abs(v) / 8.0), hz);
  return s;
}

CreepDemoOptions hold_trim_demo_defaults() {
  CreepDemoOptions o;
  o.seed = 3;
  o.scenarios = {0};
  o.history_s = 120.0;
  o.hold_s = 1800.0;
  o.score_last_s = 1680.0;
  return o;
}

namespace {
io::PairerOptions demo_pairing() {
  io::PairerOptions o;
  o.with_truth = true;  // the score is the simulator's true position
  return o;
}
}  // namespace

DemoRun::DemoRun(std::string scenario, const CreepDemoOptions& creep, IdealLine line, double rate_hz, bool lockstep,
                 const MovesDemoOptions& moves)
    : scenario_(std::move(scenario)), creep_(creep), moves_(moves), line_(line), rate_hz_(rate_hz),
      lockstep_(lockstep), pairer_(demo_pairing()) {
  if (scenario_ != "sawtooth" && scenario_ != "creep" && scenario_ != "hold_trim" && scenario_ != "tracking_trim")
    throw std::invalid_argument("~scenario: sawtooth, creep, hold_trim or tracking_trim, got '" + scenario_ + "'");
  if (!(rate_hz_ > 0.0)) throw std::invalid_argument("demo: sample rate must be > 0 Hz");
  if (!(creep_.score_last_s > 0.0)) throw std::invalid_argument("~score_last_s must be > 0 s");
  if (scenario_ == "sawtooth") steps_ = sawtooth_demo_steps(rate_hz_);
  else if (scenario_ == "tracking_trim") steps_ = moves_demo_steps(moves_, rate_hz_);
  else steps_ = creep_demo_steps(creep_, rate_hz_);
}

std::optional<DemoRun::Next> DemoRun::on_truth(std::uint32_t seq, double true_nm, double stamp_s) {
  return take(pairer_.add_truth(seq, true_nm, stamp_s));
}
std::optional<DemoRun::Next> DemoRun::on_encoder(std::uint32_t seq, double encoder_nm, double stamp_s, bool valid) {
  return take(pairer_.add_reading(seq, encoder_nm, valid, stamp_s));
}
std::optional<DemoRun::Next> DemoRun::on_voltage(std::uint32_t seq, double applied_v, double stamp_s) {
  return take(pairer_.add_voltage(seq, applied_v, stamp_s));
}

// Voltages the predictor sent for the hold intent: the hold starts when one of them is applied.
std::optional<DemoRun::Next> DemoRun::on_prediction(double stamp_s, double commanded_v, double sent_v, bool fallback,
                                                    const Estimate& estimate) {
  newest_prediction_s_ = std::max(newest_prediction_s_, stamp_s);
  if (records_estimates()) estimates_.emplace_back(stamp_s, estimate);
  if (next_ > 0 && next_ <= steps_.size()) {
    const DemoStep& s = steps_[next_ - 1];
    if (s.phase == "hold" && !fallback && std::abs(commanded_v - s.intent_v) <= 1e-6) hold_sent_v_.push_back(sent_v);
  }
  return release();
}

std::optional<DemoRun::Next> DemoRun::take(const std::vector<io::PairedSample>& samples) {
  std::optional<Next> merged;
  for (const auto& p : samples) {
    auto n = step(p);
    if (!n) continue;
    if (merged && merged->set_mode) n->set_mode = true;
    merged = n;
  }
  if (!merged) return std::nullopt;
  if (!lockstep_) return merged;
  if (pending_ && pending_->set_mode) merged->set_mode = true;  // a newer sample overtook it: keep the switch
  pending_ = merged;
  pending_stamp_s_ = samples.back().stamp_s;
  return release();
}

std::optional<DemoRun::Next> DemoRun::release() {
  // stamps of one sample agree to well within a period (driver stamp → predictor stamp, via ros::Time)
  if (!pending_ || newest_prediction_s_ < pending_stamp_s_ - 0.25 / rate_hz_) return std::nullopt;
  auto n = pending_;
  pending_.reset();
  return n;
}

// One complete sample: record it against the intent that was in force over its step, give the next intent.
std::optional<DemoRun::Next> DemoRun::step(const io::PairedSample& sample) {
  const double true_nm = sample.truth_nm, applied_v = sample.voltage_v;
  const double enc_nm = sample.measured ? sample.position_nm : std::nan("");
  if (next_ > 0 && next_ <= steps_.size()) {
    DemoStep s = steps_[next_ - 1];
    if (s.phase == "hold") {
      // The hold (and its drift) starts at the first sample that has the hold's command applied; free-running,
      // the tip is before that still on the approach, one or two samples behind the intent. In lock-step the
      // hold's command is in the hold's first sample.
      const auto key = std::make_pair(s.mode, s.segment);
      if (!hold_started_[key]) {
        const bool hit = lockstep_ || std::any_of(hold_sent_v_.begin(), hold_sent_v_.end(),
                                                  [&](double x) { return std::abs(x - applied_v) <= 5e-4; });
        if (hit || hold_delay_[key] >= 20) {
          hold_started_[key] = true;
          forced_[key] = !hit;
        } else {
          ++hold_delay_[key];
          s.phase = "hold_wait";
        }
      }
    } else {
      hold_sent_v_.clear();
    }
    rows_.push_back({s, static_cast<double>(next_ - 1) / rate_hz_, line_.position_nm(s.intent_v), true_nm, enc_nm,
                     applied_v, sample.stamp_s});
  }
  if (next_ >= steps_.size()) {
    ++next_;
    return std::nullopt;
  }
  const DemoStep& s = steps_[next_];
  Next n;
  n.set_mode = next_ == 0 || steps_[next_ - 1].mode != s.mode;
  n.compensated = s.mode == 1 || records_estimates();
  n.hold_trim = (switches_hold_trim() && s.mode == 1) || switches_tracking_trim();
  n.tracking_trim = switches_tracking_trim() && s.mode == 1;
  n.intent_v = s.intent_v;
  ++next_;
  return n;
}

// The prediction of the sample stamped `stamp_s` (stamps of one sample agree to well within a period).
const DemoRun::Estimate* DemoRun::estimate_at(double stamp_s) const {
  const double tol = 0.25 / rate_hz_;
  auto it = std::lower_bound(estimates_.begin(), estimates_.end(), stamp_s - tol,
                             [](const auto& e, double t) { return e.first < t; });
  for (; it != estimates_.end() && it->first <= stamp_s + tol; ++it)
    if (std::abs(it->first - stamp_s) <= tol) return &it->second;
  return nullptr;
}

void DemoRun::write_csv(std::ostream& csv) const {
  const bool est = records_estimates(), track = switches_tracking_trim();
  csv << "mode,segment,phase,time_s,intent_v,applied_v,ideal_nm,true_nm,encoder_nm"
      << (est ? ",fused_nm,fused_sigma_nm,hold_trim_nm,hold_trim_state" : "")
      << (track ? ",tracking_trim_nm,tracking_trim_state" : "") << "\n";
  csv.precision(10);
  const Estimate none;
  for (const auto& r : rows_) {
    csv << r.step.mode << "," << r.step.segment << "," << r.step.phase << "," << r.time_s << "," << r.step.intent_v
        << "," << r.applied_v << "," << r.ideal_nm << "," << r.true_nm << "," << r.encoder_nm;
    if (est) {
      const Estimate* e = estimate_at(r.stamp_s);
      if (!e) e = &none;
      csv << "," << e->fused_nm << "," << e->fused_sigma_nm << "," << e->hold_trim_nm << ","
          << (e->hold_trim_state.empty() ? "none" : e->hold_trim_state);
      if (track)
        csv << "," << e->tracking_trim_nm << "," << (e->tracking_trim_state.empty() ? "none" : e->tracking_trim_state);
    }
    csv << "\n";
  }
}

std::vector<DemoRun::HoldScore> DemoRun::hold_scores() const {
  std::vector<HoldScore> out;
  std::map<std::pair<int, int>, std::size_t> index, length;
  for (const auto& r : rows_) {
    if (r.step.phase != "hold") continue;
    const auto key = std::make_pair(r.step.mode, r.step.segment);
    if (!index.count(key)) {
      index[key] = out.size();
      HoldScore h;
      h.mode = key.first, h.segment = key.second, h.hold_v = r.step.intent_v, h.intended_nm = r.ideal_nm;
      h.start_error_nm = r.true_nm - r.ideal_nm;
      out.push_back(h);
    }
    ++length[key];
  }
  const auto skip = [&](const std::pair<int, int>& key) {
    const double n = static_cast<double>(length[key]), keep = std::round(creep_.score_last_s * rate_hz_);
    return static_cast<std::size_t>(std::max(0.0, n - keep));
  };
  std::map<std::pair<int, int>, std::size_t> k;
  for (const auto& r : rows_) {
    if (r.step.phase != "hold") continue;
    const auto key = std::make_pair(r.step.mode, r.step.segment);
    if (k[key]++ < skip(key)) continue;
    HoldScore& h = out[index[key]];
    const double e = std::abs(r.true_nm - r.ideal_nm);
    h.worst_nm = std::max(h.worst_nm, e);
    h.mae_nm += e;
    ++h.samples;
    if (const Estimate* est = estimate_at(r.stamp_s); est && est->hold_trim_state == "active") ++h.active_samples;
  }
  for (auto& h : out) h.mae_nm /= std::max<std::size_t>(1, h.samples);
  return out;
}

void DemoRun::write_json(std::ostream& js) const {
  js.precision(6);
  if (scenario_ == "sawtooth") return write_sawtooth_json(js);
  if (switches_hold_trim()) return write_hold_trim_json(js);
  if (switches_tracking_trim()) return write_tracking_trim_json(js);
  write_creep_json(js);
}

// The sawtooth scenario: |true − ideal| over the saw, max and RMS as % of the stroke, per mode.
void DemoRun::write_sawtooth_json(std::ostream& js) const {
  double mx[2] = {0, 0}, ss[2] = {0, 0}, lo = 1e300, hi = -1e300;
  std::size_t n[2] = {0, 0};
  for (const auto& r : rows_) {
    if (r.step.phase != "saw") continue;
    const double d = r.true_nm - r.ideal_nm;
    mx[r.step.mode] = std::max(mx[r.step.mode], std::abs(d));
    ss[r.step.mode] += d * d;
    ++n[r.step.mode];
    lo = std::min(lo, r.ideal_nm), hi = std::max(hi, r.ideal_nm);
  }
  const double stroke = hi - lo;
  std::size_t moving = 0, late = 0;  // in-step check, as for the creep histories below
  for (const auto& r : rows_)
    if (r.step.mode == 0 && r.step.phase == "saw") ++moving, late += std::abs(r.applied_v - r.step.intent_v) > 5e-4;
  js << "{\"lockstep\": " << (lockstep_ ? "true" : "false") << ", \"uncompensated_saw_samples\": " << moving
     << ", \"uncompensated_late_samples\": " << late << ", \"stroke_nm\": " << stroke << ", \"uncompensated_max_pct\": " << 100 * mx[0] / stroke
     << ", \"compensated_max_pct\": " << 100 * mx[1] / stroke
     << ", \"uncompensated_rms_pct\": " << 100 * std::sqrt(ss[0] / std::max<std::size_t>(1, n[0])) / stroke
     << ", \"compensated_rms_pct\": " << 100 * std::sqrt(ss[1] / std::max<std::size_t>(1, n[1])) / stroke << "}\n";
}

// The hold-trim scenario: each hold's scores, feedforward against trimmed.
void DemoRun::write_hold_trim_json(std::ostream& js) const {
  const auto scores = hold_scores();
  double worst[2] = {0, 0}, mae[2] = {0, 0};
  std::size_t n[2] = {0, 0};
  for (const auto& h : scores) {
    const int m = h.mode ? 1 : 0;
    worst[m] = std::max(worst[m], h.worst_nm), mae[m] += h.mae_nm, ++n[m];
  }
  const auto list = [&](const char* name, int mode, auto value) {
    js << ", \"" << name << "\": [";
    bool first = true;
    for (const auto& h : scores)
      if (h.mode == mode) js << (first ? "" : ", ") << value(h), first = false;
    js << "]";
  };
  js << "{\"lockstep\": " << (lockstep_ ? "true" : "false") << ", \"scenario\": \"hold_trim\""
     << ", \"score_last_s\": " << creep_.score_last_s << ", \"history_s\": " << creep_.history_s
     << ", \"hold_s\": " << creep_.hold_s << ", \"hold_trim_ff_worst_nm\": " << worst[0]
     << ", \"hold_trim_trimmed_worst_nm\": " << worst[1]
     << ", \"hold_trim_ff_mae_nm\": " << mae[0] / std::max<std::size_t>(1, n[0])
     << ", \"hold_trim_trimmed_mae_nm\": " << mae[1] / std::max<std::size_t>(1, n[1]);
  for (int mode = 0; mode < 2; ++mode) {
    const std::string p = mode ? "trimmed_" : "ff_";
    list((p + "worst_nm").c_str(), mode, [](const HoldScore& h) { return h.worst_nm; });
    list((p + "mae_nm").c_str(), mode, [](const HoldScore& h) { return h.mae_nm; });
    list((p + "start_error_nm").c_str(), mode, [](const HoldScore& h) { return h.start_error_nm; });
    list((p + "scored_samples").c_str(), mode, [](const HoldScore& h) { return h.samples; });
    list((p + "active_samples").c_str(), mode, [](const HoldScore& h) { return h.active_samples; });
  }
  list("hold_v", 0, [](const HoldScore& h) { return h.hold_v; });
  list("intended_nm", 0, [](const HoldScore& h) { return h.intended_nm; });
  js << ", \"creep_seed\": " << creep_.seed << ", \"creep_scenarios\": [";
  for (std::size_t i = 0; i < creep_.scenarios.size(); ++i) js << (i ? ", " : "") << creep_.scenarios[i];
  js << "]}\n";
}

// The creep scenario: the drift in each hold per mode, and the holds' start errors and command latency.
void DemoRun::write_creep_json(std::ostream& js) const {
  // drift = |true position at the end of the hold − true position at its start|, per history.
  std::map<std::pair<int, int>, std::pair<double, double>> ends;
  for (const auto& r : rows_) {
    if (r.step.phase != "hold") continue;
    auto key = std::make_pair(r.step.mode, r.step.segment);
    auto it = ends.find(key);
    if (it == ends.end()) ends[key] = {r.true_nm, r.true_nm};
    else it->second.second = r.true_nm;
  }
  js << "{\"lockstep\": " << (lockstep_ ? "true" : "false") << ", ";
  for (int mode = 0; mode < 2; ++mode) {
    js << (mode ? ", \"compensated_drift_nm\": [" : "\"uncompensated_drift_nm\": [");
    bool first = true;
    for (const auto& [key, v] : ends)
      if (key.first == mode) js << (first ? "" : ", ") << std::abs(v.second - v.first), first = false;
    js << "]";
  }
  // Per hold: intended voltage, true − intended position where the hold starts, samples until the hold's
  // command was applied (command latency through predictor → driver → device), whether that was forced.
  std::map<std::pair<int, int>, double> hold_v;
  for (const auto& r : rows_)
    if (r.step.phase == "hold") hold_v[{r.step.mode, r.step.segment}] = r.step.intent_v;
  const auto list = [&](const char* name, auto value) {
    js << ", \"" << name << "\": [";
    bool first = true;
    for (const auto& [key, v] : ends) js << (first ? "" : ", ") << value(key, v), first = false;
    js << "]";
  };
  const auto at = [](const auto& m, const auto& key, auto def) {
    auto it = m.find(key);
    return it == m.end() ? def : it->second;
  };
  list("hold_v", [&](auto key, auto) { return hold_v[key]; });
  list("hold_start_error_nm", [&](auto key, auto v) { return v.first - line_.position_nm(hold_v[key]); });
  list("hold_start_delay_samples", [&](auto key, auto) { return at(hold_delay_, key, 0); });
  list("hold_start_forced", [&](auto key, auto) { return at(forced_, key, false) ? 1 : 0; });
  // In-step check: uncompensated samples of the histories whose applied voltage was not the intent in force
  // (a command that reached the device late).
  std::size_t late = 0, moving = 0;
  for (const auto& r : rows_)
    if (r.step.mode == 0 && r.step.phase == "history") ++moving, late += std::abs(r.applied_v - r.step.intent_v) > 5e-4;
  js << ", \"uncompensated_history_samples\": " << moving << ", \"uncompensated_late_samples\": " << late;
  js << ", \"creep_seed\": " << creep_.seed << ", \"creep_scenarios\": [";
  for (std::size_t i = 0; i < creep_.scenarios.size(); ++i) js << (i ? ", " : "") << creep_.scenarios[i];
  js << "]}\n";
}

}  // namespace piezo::compensation
