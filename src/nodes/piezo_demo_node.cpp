// piezo_demo: drives one axis of the simulated manipulator through the demo scenarios (scripts/demo), once
// uncompensated and once compensated, in lockstep with the encoder samples, and measures the true position.
//   ~scenario  "sawtooth": triangles of increasing amplitude (study Fig. 11) → deviation from the ideal line
//              "creep": histories of the package's own `creep` protocol (~creep_seed, ~creep_scenarios), each
//              followed by its hold (the intent held ~hold_s) → drift of the true position
//   ~model_file  the predictor's model (for the ideal line, same definition as the predictor)
//   ~out_prefix  writes <prefix>.csv (every sample) and <prefix>.json (the metrics)
#include <ros/ros.h>
#include <std_srvs/SetBool.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/compensation/ideal_line.h"
#include "piezo_compensation/io/sequence_pairer.h"
#include "piezo_compensation/protocols/protocol.h"
#include "piezo_compensation/ros/predictor.h"

namespace {

struct Step {
  int mode;          // 0 uncompensated, 1 compensated
  int segment;       // history index (creep) or 0
  std::string phase; // "rest", "history", "hold", "saw"
  double intent_v;
};

void ramp(std::vector<Step>& s, int mode, int seg, const std::string& ph, double from, double to, double dur_s, double hz) {
  const int n = std::max(1, static_cast<int>(std::lround(dur_s * hz)));
  for (int i = 1; i <= n; ++i) s.push_back({mode, seg, ph, from + (to - from) * i / n});
}
void hold(std::vector<Step>& s, int mode, int seg, const std::string& ph, double v, double dur_s, double hz) {
  const int n = static_cast<int>(std::lround(dur_s * hz));
  for (int i = 0; i < n; ++i) s.push_back({mode, seg, ph, v});
}

struct CreepOptions {
  int seed = 3;                  // protocol seed (the demo's training plan uses the creep set of seed + 7)
  std::vector<int> scenarios;    // protocol segments (0-based)
  double history_s = 1800.0, hold_s = 1800.0;
};

std::vector<Step> sawtooth(double hz) {
  std::vector<Step> s;
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

// The chosen scenarios of the creep protocol (axis c column): its ~30-min history, then its hold. A short ramp
// (≤ 8 V/s) joins the scenarios, which in the protocol follow other scenarios.
std::vector<Step> creep(const CreepOptions& o, double hz) {
  YAML::Node params;
  params["history_s"] = o.history_s;
  params["hold_s"] = o.hold_s;
  const auto protocol = piezo::protocols::make_protocol("creep", params, hz, static_cast<std::uint64_t>(o.seed));
  std::map<int, std::vector<piezo::protocols::ProtocolSample>> by_segment;
  for (std::size_t i = 0; i < protocol->size(); ++i) {
    const auto p = protocol->at(i);
    by_segment[p.segment].push_back(p);
  }
  std::vector<Step> s;
  double v = 0.0;
  for (int mode = 0; mode < 2; ++mode) {
    for (std::size_t h = 0; h < o.scenarios.size(); ++h) {
      const int seg = o.scenarios[h];
      const int n_scen = static_cast<int>(by_segment.size());
      if (seg < 0 || seg >= n_scen)
        throw std::invalid_argument("~creep_scenarios: " + std::to_string(seg) + " outside 0.." +
                                    std::to_string(n_scen - 1));
      const auto& samples = by_segment.at(seg);
      const double first = samples.front().voltage_v[2];
      ramp(s, mode, static_cast<int>(h), "rest", v, first, std::max(5.0, std::abs(first - v) / 8.0), hz);
      for (const auto& p : samples)
        s.push_back({mode, static_cast<int>(h), p.phase == piezo::protocols::Phase::kHold ? "hold" : "history",
                     p.voltage_v[2]});
      v = samples.back().voltage_v[2];
    }
  }
  ramp(s, 1, static_cast<int>(o.scenarios.size()) - 1, "rest", v, 0.0, std::max(5.0, std::abs(v) / 8.0), hz);
  return s;
}

// A list parameter given as a YAML list or, from the command line (_name:="[11, 8]"), as a string holding one.
std::vector<int> int_list(const ros::NodeHandle& pnh, const std::string& name, const std::vector<int>& def) {
  XmlRpc::XmlRpcValue v;
  if (!pnh.getParam(name, v)) return def;
  std::vector<int> out;
  try {
    if (v.getType() == XmlRpc::XmlRpcValue::TypeString) {
      for (const auto& x : YAML::Load(static_cast<std::string>(v))) out.push_back(x.as<int>());
    } else if (v.getType() == XmlRpc::XmlRpcValue::TypeArray) {
      for (int i = 0; i < v.size(); ++i) {
        if (v[i].getType() != XmlRpc::XmlRpcValue::TypeInt) throw std::invalid_argument("element not an integer");
        out.push_back(static_cast<int>(v[i]));
      }
    } else {
      throw std::invalid_argument("not a list");
    }
  } catch (const std::exception& e) {
    throw std::invalid_argument("~" + name + ": expected a list of integers such as [11, 8] (" + e.what() + ")");
  }
  return out;
}

struct Row {
  Step step;
  double time_s, ideal_nm, true_nm, encoder_nm, applied_v;  // time_s: scenario sample index / rate
};

class Demo {
 public:
  Demo(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh) {
    scenario_name_ = pnh.param<std::string>("scenario", "sawtooth");
    if (scenario_name_ != "sawtooth" && scenario_name_ != "creep")
      throw std::invalid_argument("~scenario: sawtooth or creep, got '" + scenario_name_ + "'");
    axis_ = pnh.param<std::string>("axis", "c");
    out_prefix_ = pnh.param<std::string>("out_prefix", "demo");
    const std::string model_file = pnh.param<std::string>("model_file", "");
    CreepOptions co;
    co.hold_s = pnh.param<double>("hold_s", 1800.0);
    co.history_s = pnh.param<double>("creep_history_s", 1800.0);
    co.seed = pnh.param<int>("creep_seed", 3);
    co.scenarios = int_list(pnh, "creep_scenarios", {11, 8, 13, 6});
    if (co.scenarios.empty()) throw std::invalid_argument("~creep_scenarios: empty list");
    if (!(co.hold_s > 0.0) || !(co.history_s > 0.0))
      throw std::invalid_argument("~hold_s and ~creep_history_s must be > 0 s");
    auto model = piezo::predictor::load_model_file(model_file);
    piezo::compensation::IdealLineOptions o;  // the predictor's defaults (config/predictor.yaml)
    o.hold_s = pnh.param<double>("ideal_line_hold_s", 60.0);
    o.sample_rate_hz = model->meta.sample_rate_hz;
    line_ = piezo::compensation::ideal_line_from_model(*model, o);
    rate_hz_ = model->meta.sample_rate_hz;
    creep_seed_ = co.seed;
    creep_scenarios_ = co.scenarios;
    steps_ = scenario_name_ == "sawtooth" ? sawtooth(rate_hz_) : creep(co, rate_hz_);
    intended_ = nh_.advertise<piezo_compensation::IntendedMotion>(axis_ + "/intended", 5);
    encoder_ = nh_.subscribe(axis_ + "/encoder", 50, &Demo::on_encoder, this);
    truth_ = nh_.subscribe(axis_ + "/true_position", 50, &Demo::on_truth, this);
    voltage_ = nh_.subscribe(axis_ + "/voltage", 50, &Demo::on_voltage, this);
    prediction_ = nh_.subscribe(axis_ + "/prediction", 50, &Demo::on_prediction, this);
    switch_ = nh_.serviceClient<std_srvs::SetBool>("predictor/set_compensation");
    ROS_INFO("demo %s: %zu samples (%.0f s simulated per mode), ideal line %.4f nm/V + %.2f nm", scenario_name_.c_str(),
             steps_.size(), steps_.size() / model->meta.sample_rate_hz / 2, line_.gain_nm_per_v, line_.offset_nm);
  }

  bool done() const { return next_ > steps_.size(); }

  void finish() {
    std::ofstream csv(out_prefix_ + ".csv");
    csv << "mode,segment,phase,time_s,intent_v,applied_v,ideal_nm,true_nm,encoder_nm\n";
    csv.precision(10);
    for (const auto& r : rows_)
      csv << r.step.mode << "," << r.step.segment << "," << r.step.phase << "," << r.time_s << "," << r.step.intent_v
          << "," << r.applied_v << "," << r.ideal_nm << "," << r.true_nm << "," << r.encoder_nm << "\n";
    std::ofstream js(out_prefix_ + ".json");
    js.precision(6);
    if (scenario_name_ == "sawtooth") {
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
      js << "{\"stroke_nm\": " << stroke << ", \"uncompensated_max_pct\": " << 100 * mx[0] / stroke
         << ", \"compensated_max_pct\": " << 100 * mx[1] / stroke
         << ", \"uncompensated_rms_pct\": " << 100 * std::sqrt(ss[0] / std::max<std::size_t>(1, n[0])) / stroke
         << ", \"compensated_rms_pct\": " << 100 * std::sqrt(ss[1] / std::max<std::size_t>(1, n[1])) / stroke << "}\n";
    } else {
      // drift = |true position at the end of the hold − true position at its start|, per history.
      std::map<std::pair<int, int>, std::pair<double, double>> ends;
      for (const auto& r : rows_) {
        if (r.step.phase != "hold") continue;
        auto key = std::make_pair(r.step.mode, r.step.segment);
        auto it = ends.find(key);
        if (it == ends.end()) ends[key] = {r.true_nm, r.true_nm};
        else it->second.second = r.true_nm;
      }
      js << "{";
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
      list("hold_v", [&](auto key, auto) { return hold_v[key]; });
      list("hold_start_error_nm", [&](auto key, auto v) { return v.first - line_.position_nm(hold_v[key]); });
      list("hold_start_delay_samples", [&](auto key, auto) { return hold_delay_[key]; });
      list("hold_start_forced", [&](auto key, auto) { return forced_[key] ? 1 : 0; });
      // In-step check: uncompensated samples of the histories whose applied voltage was not the intent in force
      // (a command that reached the device late).
      std::size_t late = 0, moving = 0;
      for (const auto& r : rows_)
        if (r.step.mode == 0 && r.step.phase == "history") ++moving, late += std::abs(r.applied_v - r.step.intent_v) > 5e-4;
      js << ", \"uncompensated_history_samples\": " << moving << ", \"uncompensated_late_samples\": " << late;
      js << ", \"creep_seed\": " << creep_seed_ << ", \"creep_scenarios\": [";
      for (std::size_t i = 0; i < creep_scenarios_.size(); ++i) js << (i ? ", " : "") << creep_scenarios_[i];
      js << "]}\n";
    }
    ROS_INFO("demo %s: wrote %s.csv and %s.json (%zu samples)", scenario_name_.c_str(), out_prefix_.c_str(),
             out_prefix_.c_str(), rows_.size());
  }

 private:
  void on_truth(const piezo_compensation::EncoderPosition::ConstPtr& m) {
    for (const auto& p : pairer_.add_truth(m->sequence, m->position * 1e9, m->header.stamp.toSec())) on_sample(p);
  }
  void on_voltage(const piezo_compensation::AxisVoltage::ConstPtr& m) {
    for (const auto& p : pairer_.add_voltage(m->sequence, m->voltage, m->header.stamp.toSec())) on_sample(p);
  }
  // Voltages the predictor sent for the hold intent: the hold starts when one of them is applied.
  void on_prediction(const piezo_compensation::Prediction::ConstPtr& m) {
    if (next_ == 0 || next_ > steps_.size()) return;
    const Step& s = steps_[next_ - 1];
    if (s.phase != "hold" || m->fallback) return;
    if (std::abs(m->commanded_voltage - s.intent_v) > 1e-6) return;
    hold_sent_v_.push_back(m->compensation_active ? m->corrected_voltage : m->commanded_voltage);
  }
  void on_encoder(const piezo_compensation::EncoderPosition::ConstPtr& m) {
    for (const auto& p : pairer_.add_reading(m->sequence, m->position * 1e9, m->valid, m->header.stamp.toSec()))
      on_sample(p);
  }
  // One complete sample (paired by the one rule, io/sequence_pairer.h): record it against the intent that was in
  // force over its step, send the next intent. A sample without a reading advances the scenario unrecorded.
  void on_sample(const piezo::io::PairedSample& p) {
    const double true_nm = p.truth_nm, enc_nm = p.position_nm, applied_v = p.voltage_v;
    if (next_ > 0 && next_ <= steps_.size() && p.measured && std::isfinite(true_nm)) {
      Step s = steps_[next_ - 1];
      if (s.phase == "hold") {
        // The hold (and its drift) starts at the first sample that has the hold's command applied; before
        // that the tip is still on the approach, one or two samples behind the intent.
        const auto key = std::make_pair(s.mode, s.segment);
        if (!hold_started_[key]) {
          const bool hit = std::any_of(hold_sent_v_.begin(), hold_sent_v_.end(),
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
      rows_.push_back(
          {s, static_cast<double>(next_ - 1) / rate_hz_, line_.position_nm(s.intent_v), true_nm, enc_nm, applied_v});
    }
    if (next_ >= steps_.size()) {
      ++next_;
      return;
    }
    const Step& s = steps_[next_];
    if (next_ == 0 || steps_[next_ - 1].mode != s.mode) {
      std_srvs::SetBool sw;
      sw.request.data = s.mode == 1;
      if (!switch_.call(sw) || !sw.response.success) throw std::runtime_error("predictor/set_compensation failed");
      ROS_INFO("demo %s: %s run", scenario_name_.c_str(), s.mode ? "compensated" : "uncompensated");
    }
    piezo_compensation::IntendedMotion im;
    im.header.stamp = ros::Time::now();
    im.mode = piezo_compensation::IntendedMotion::VOLTAGE;
    im.voltage = s.intent_v;
    intended_.publish(im);
    ++next_;
    if (next_ % 2000 == 0)
      ROS_INFO("demo %s: %.0f %%", scenario_name_.c_str(), 100.0 * next_ / steps_.size());
  }

  ros::NodeHandle nh_;
  std::string scenario_name_, axis_, out_prefix_;
  double rate_hz_ = 11.0;
  int creep_seed_ = 3;
  std::vector<int> creep_scenarios_;
  std::map<std::pair<int, int>, bool> hold_started_, forced_;
  std::map<std::pair<int, int>, int> hold_delay_;
  std::vector<double> hold_sent_v_;
  piezo::compensation::IdealLine line_;
  std::vector<Step> steps_;
  std::size_t next_ = 0;
  std::vector<Row> rows_;
  piezo::io::SequencePairer pairer_{[] {
    piezo::io::PairerOptions o;
    o.with_truth = true;
    return o;
  }()};
  ros::Publisher intended_;
  ros::Subscriber encoder_, truth_, voltage_, prediction_;
  ros::ServiceClient switch_;
};

}  // namespace

int main(int argc, char** argv) {
  ros::init(argc, argv, "piezo_demo");
  ros::NodeHandle nh, pnh("~");
  try {
    Demo demo(nh, pnh);
    if (!ros::service::waitForService(nh.resolveName("predictor/set_compensation"), ros::Duration(60)))
      throw std::runtime_error("predictor/set_compensation not available after 60 s");
    while (ros::ok() && !demo.done()) {
      ros::spinOnce();
      ros::WallDuration(0.0002).sleep();
    }
    demo.finish();
  } catch (const std::exception& e) {
    ROS_FATAL("piezo_demo: %s", e.what());
    return 1;
  }
  return 0;
}
