// piezo_demo: drives one axis of the simulated manipulator through the demo scenarios (scripts/demo), once
// uncompensated and once compensated, in lockstep with the encoder samples, and measures the true position.
//   ~scenario  "sawtooth": triangles of increasing amplitude (study Fig. 11) → deviation from the ideal line
//              "creep": several voltage histories, each followed by a 30-min hold → drift of the true position
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
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/compensation/ideal_line.h"
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

std::vector<Step> scenario(const std::string& name, double hz, double hold_s, double hold_v) {
  std::vector<Step> s;
  for (int mode = 0; mode < 2; ++mode) {
    if (name == "sawtooth") {
      hold(s, mode, 0, "rest", 0.0, 30.0, hz);
      // Triangles 0 → +A → −A → 0 with A = 10 … 70 V, 8 V/s (Fig. 11 of the study: increasing amplitude).
      for (double a = 10.0; a <= 70.0 + 1e-9; a += 10.0) {
        ramp(s, mode, 0, "saw", 0.0, a, a / 8.0, hz);
        ramp(s, mode, 0, "saw", a, -a, 2 * a / 8.0, hz);
        ramp(s, mode, 0, "saw", -a, 0.0, a / 8.0, hz);
      }
      hold(s, mode, 0, "rest", 0.0, 5.0, hz);
    } else {
      // Four different histories arriving at the same intended voltage, each held for hold_s.
      for (int h = 0; h < 4; ++h) {
        hold(s, mode, h, "rest", 0.0, 60.0, hz);
        if (h == 0) {
          ramp(s, mode, h, "history", 0.0, hold_v, 5.0, hz);
        } else if (h == 1) {
          ramp(s, mode, h, "history", 0.0, 70.0, 10.0, hz);
          hold(s, mode, h, "history", 70.0, 5.0, hz);
          ramp(s, mode, h, "history", 70.0, hold_v, 10.0, hz);
        } else if (h == 2) {
          ramp(s, mode, h, "history", 0.0, -60.0, 10.0, hz);
          hold(s, mode, h, "history", -60.0, 5.0, hz);
          ramp(s, mode, h, "history", -60.0, hold_v, 10.0, hz);
        } else {
          for (int k = 0; k < 3; ++k) {
            ramp(s, mode, h, "history", k == 0 ? 0.0 : -50.0, 50.0, 10.0, hz);
            ramp(s, mode, h, "history", 50.0, -50.0, 10.0, hz);
          }
          ramp(s, mode, h, "history", -50.0, hold_v, 5.0, hz);
        }
        hold(s, mode, h, "hold", hold_v, hold_s, hz);
        ramp(s, mode, h, "rest", hold_v, 0.0, 5.0, hz);
      }
    }
  }
  return s;
}

struct Row {
  Step step;
  double time_s, ideal_nm, true_nm, encoder_nm;  // time_s: scenario sample index / rate
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
    const double hold_s = pnh.param<double>("hold_s", 1800.0);
    hold_v_ = pnh.param<double>("hold_v", 20.0);
    auto model = piezo::predictor::load_model_file(model_file);
    piezo::compensation::IdealLineOptions o;  // the predictor's defaults (config/predictor.yaml)
    o.hold_s = pnh.param<double>("ideal_line_hold_s", 60.0);
    o.sample_rate_hz = model->meta.sample_rate_hz;
    line_ = piezo::compensation::ideal_line_from_model(*model, o);
    rate_hz_ = model->meta.sample_rate_hz;
    steps_ = scenario(scenario_name_, rate_hz_, hold_s, hold_v_);
    intended_ = nh_.advertise<piezo_compensation::IntendedMotion>(axis_ + "/intended", 5);
    encoder_ = nh_.subscribe(axis_ + "/encoder", 50, &Demo::on_encoder, this);
    truth_ = nh_.subscribe(axis_ + "/true_position", 50, &Demo::on_truth, this);
    switch_ = nh_.serviceClient<std_srvs::SetBool>("predictor/set_compensation");
    ROS_INFO("demo %s: %zu samples (%.0f s simulated per mode), ideal line %.4f nm/V + %.2f nm", scenario_name_.c_str(),
             steps_.size(), steps_.size() / model->meta.sample_rate_hz / 2, line_.gain_nm_per_v, line_.offset_nm);
  }

  bool done() const { return next_ > steps_.size(); }

  void finish() {
    std::ofstream csv(out_prefix_ + ".csv");
    csv << "mode,segment,phase,time_s,intent_v,ideal_nm,true_nm,encoder_nm\n";
    for (const auto& r : rows_)
      csv << r.step.mode << "," << r.step.segment << "," << r.step.phase << "," << r.time_s << "," << r.step.intent_v
          << "," << r.ideal_nm << "," << r.true_nm << "," << r.encoder_nm << "\n";
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
      js << ", \"hold_start_error_nm\": [";
      bool first = true;
      for (const auto& [key, v] : ends)
        js << (first ? "" : ", ") << (v.first - line_.position_nm(hold_v_)), first = false;
      js << "]}\n";
    }
    ROS_INFO("demo %s: wrote %s.csv and %s.json (%zu samples)", scenario_name_.c_str(), out_prefix_.c_str(),
             out_prefix_.c_str(), rows_.size());
  }

 private:
  void on_truth(const piezo_compensation::EncoderPosition::ConstPtr& m) {
    truth_by_seq_[m->sequence] = m->position * 1e9;
    pair(m->sequence);
  }
  void on_encoder(const piezo_compensation::EncoderPosition::ConstPtr& m) {
    enc_by_seq_[m->sequence] = {m->header.stamp.toSec(), m->position * 1e9};
    pair(m->sequence);
  }
  // One complete sample: record it against the intent that was in force over its step, send the next intent.
  void pair(std::uint32_t seq) {
    auto t = truth_by_seq_.find(seq);
    auto e = enc_by_seq_.find(seq);
    if (t == truth_by_seq_.end() || e == enc_by_seq_.end()) return;
    const double true_nm = t->second, enc_nm = e->second.second;
    truth_by_seq_.erase(truth_by_seq_.begin(), std::next(t));
    enc_by_seq_.erase(enc_by_seq_.begin(), std::next(e));
    if (next_ > 0 && next_ <= steps_.size()) {
      const Step& s = steps_[next_ - 1];
      rows_.push_back({s, static_cast<double>(next_ - 1) / rate_hz_, line_.position_nm(s.intent_v), true_nm, enc_nm});
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
  double hold_v_ = 20.0, rate_hz_ = 11.0;
  piezo::compensation::IdealLine line_;
  std::vector<Step> steps_;
  std::size_t next_ = 0;
  std::vector<Row> rows_;
  std::map<std::uint32_t, double> truth_by_seq_;
  std::map<std::uint32_t, std::pair<double, double>> enc_by_seq_;
  ros::Publisher intended_;
  ros::Subscriber encoder_, truth_;
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
