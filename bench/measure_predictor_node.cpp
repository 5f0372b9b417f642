// Per-message processing time of the predictor, measured by replaying a bag as fast as possible through the
// same PredictorAxis the node runs (ROS transport excluded: it is the node's own cost that is measured).
// Also writes the reference bag for the replay rostest: the input plus the predictions made here.
//
//   measure_predictor_node [--bag B] [--ns /mm1] [--axis c] [--write-reference OUT.bag] MODEL...
// Without arguments: bags/demo_sawtooth.bag with every bags/model*.yaml (what `piezo bench` runs).
#include <rosbag/bag.h>
#include <rosbag/view.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "piezo_compensation/ros/predictor.h"

namespace fs = std::filesystem;
using namespace piezo;

namespace {

struct Options {
  std::string bag, ns = "/mm1", axis = "c", reference;
  std::vector<std::string> models;
  std::vector<double> horizons{1.0, 60.0};
};

int usage(const std::string& why) {
  std::cerr << "measure_predictor_node: " << why
            << "\nusage: measure_predictor_node [--bag B] [--ns /mm1] [--axis c] [--write-reference OUT.bag] MODEL...\n";
  return 2;
}

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<std::size_t>(q * static_cast<double>(v.size())))];
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  const fs::path src = PIEZO_SOURCE_DIR;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::runtime_error(a + " needs a value");
      return argv[++i];
    };
    try {
      if (a == "--bag") o.bag = value();
      else if (a == "--ns") o.ns = value();
      else if (a == "--axis") o.axis = value();
      else if (a == "--write-reference") o.reference = value();
      else if (a.rfind("--", 0) == 0) return usage("unknown option " + a);
      else o.models.push_back(a);
    } catch (const std::exception& e) {
      return usage(e.what());
    }
  }
  if (o.bag.empty()) o.bag = (src / "bags" / "demo_sawtooth.bag").string();
  if (o.models.empty() && fs::is_directory(src / "bags"))
    for (const auto& e : fs::directory_iterator(src / "bags"))
      if (e.path().filename().string().rfind("model", 0) == 0 && e.path().extension() == ".yaml")
        o.models.push_back(e.path().string());
  std::sort(o.models.begin(), o.models.end());
  if (o.models.empty()) return usage("no model files given and none in bags/model*.yaml");
  if (!o.reference.empty() && o.models.size() != 1) return usage("--write-reference needs exactly one MODEL");

  ros::Time::init();
  const std::string t_voltage = o.ns + "/" + o.axis + "/voltage", t_encoder = o.ns + "/" + o.axis + "/encoder",
                    t_intended = o.ns + "/" + o.axis + "/intended";
  try {
    rosbag::Bag in(o.bag, rosbag::bagmode::Read);
    std::cout << "bag " << o.bag << ", axis " << o.ns << "/" << o.axis << "\n";
    int failures = 0;
    for (const auto& model_path : o.models) try {
      predictor::PredictorSettings s;
      s.axes = {o.axis};
      s.model_files[o.axis] = model_path;
      s.drift_horizons_s = o.horizons;
      // Reference bags carry the forecast of every sample (deterministic); timing runs use the node's default:
      // the forecast goes to a worker thread, here only the clone handed to it is charged.
      s.drift_async = o.reference.empty();
      s.drift_update_period_s = o.reference.empty() ? 1.0 : 0.0;
      predictor::PredictorAxis axis(o.axis, model_path, predictor::load_model_file(model_path), s);
      std::unique_ptr<rosbag::Bag> out;
      if (!o.reference.empty()) out = std::make_unique<rosbag::Bag>(o.reference, rosbag::bagmode::Write);
      std::vector<double> us;
      std::size_t messages = 0;
      rosbag::View view(in);
      for (const rosbag::MessageInstance& m : view) {
        if (out && m.getTopic() != o.ns + "/" + o.axis + "/prediction") out->write(m.getTopic(), m.getTime(), m);
        std::vector<predictor::PredictorAxis::Output> outs;
        const auto t0 = std::chrono::steady_clock::now();
        if (m.getTopic() == t_voltage) {
          if (auto v = m.instantiate<piezo_compensation::AxisVoltage>()) outs = axis.on_voltage(*v, false, m.getTime());
        } else if (m.getTopic() == t_encoder) {
          if (auto e = m.instantiate<piezo_compensation::EncoderPosition>()) outs = axis.on_encoder(*e, false, m.getTime());
        } else if (m.getTopic() == t_intended) {
          std::string err;
          if (auto im = m.instantiate<piezo_compensation::IntendedMotion>()) axis.on_intended(*im, err);
          continue;
        } else {
          continue;
        }
        for (const auto& r : outs)
          if (r.forecast_due) (void)axis.compensator().model().clone();
        const double t = std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count();
        if (!outs.empty()) us.push_back(t), messages += outs.size();
        if (out)
          for (const auto& r : outs) out->write(o.ns + "/" + o.axis + "/prediction", m.getTime(), r.prediction);
      }
      if (messages == 0) throw std::runtime_error(o.bag + ": no " + t_encoder + " messages");
      std::printf("%-12s %-40s samples %6zu  per-message processing p50 %7.2f us  p99 %7.2f us  max %8.2f us\n",
                  axis.compensator().model().kind().c_str(), fs::path(model_path).filename().c_str(), messages,
                  percentile(us, 0.5), percentile(us, 0.99), percentile(us, 1.0));
      if (out) std::cout << "wrote reference " << o.reference << "\n";
    } catch (const std::exception& e) {
      // One unloadable model must not hide the figures of the others.
      std::cerr << "measure_predictor_node: " << e.what() << "\n";
      ++failures;
    }
    if (failures) return 1;
  } catch (const std::exception& e) {
    std::cerr << "measure_predictor_node: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
