// The predictor's ~reload_model (every axis' model swapped, warmed on the snapshot buffer in memory:
// compensation/reload_warmup.h) and its resume (~resume_from, ~resume_save_to: compensation/resume.h).
#include "piezo_compensation/ros/predictor.h"

#include <chrono>
#include <filesystem>
#include <iomanip>
#include <sstream>

#include "piezo_compensation/compensation/reload_warmup.h"
#include "piezo_compensation/ros/data_file.h"

namespace piezo::predictor {

models::ModelPtr PredictorNode::load_for_axis(const std::string& path, const std::string& axis) const {
  return load_axis_model(path, axis, s_, pnh_.resolveName("allow_simulated_model"));
}

const char* PredictorNode::data_origin() const {
  if (s_.transport == "real") return io::kOriginRecorded;
  return s_.transport == "simulated" ? io::kOriginSimulated : "";  // a replay: the bag played knows, the node not
}

// ~reload_model: ~model_file is read again (an operator points it at the augmented model `piezo residual` wrote).
// All or nothing: a broken file leaves every axis on its current model.
bool PredictorNode::on_reload(std_srvs::Trigger::Request&, std_srvs::Trigger::Response& res) {
  std::map<std::string, std::string> files;
  std::string timing;
  try {
    files = read_model_files(pnh_, s_.axes);
    res.message = reload_models(files, timing);
  } catch (const std::exception& e) {
    res.success = false;
    res.message = std::string("reload failed, models unchanged: ") + e.what();
    ROS_ERROR("%s", res.message.c_str());
    return true;
  }
  s_.model_files = files;
  res.success = true;
  std::string warmth = res.message;
  res.message = "models reloaded:";
  for (const auto& [axis, path] : files) res.message += " " + axis + " " + path;
  res.message += warmth + timing;
  ROS_INFO("%s", res.message.c_str());
  return true;
}

// Loads every axis' file, warms each new model on the buffered samples and swaps them in; returns what was done
// per axis ("; c: warm, on the buffered ..."). Throws (nothing swapped) when a file cannot be loaded.
std::string PredictorNode::reload_models(const std::map<std::string, std::string>& files, std::string& timing) {
  const auto t_start = std::chrono::steady_clock::now();
  const auto secs = [](auto a, auto b) { return std::chrono::duration<double>(b - a).count(); };
  std::vector<models::ModelPtr> fresh;
  for (const auto& a : axes_) fresh.push_back(load_for_axis(files.at(a->logic->axis()), a->logic->axis()));
  // Warm start on the buffered samples: a model with slow terms (a 300 s low-pass, creep) started at rest
  // would carry a transient of minutes that the offline score of the same model never saw.
  std::vector<std::string> cold(axes_.size());
  std::optional<compensation::Snapshot> recent;
  std::string no_recent = "no ~snapshot buffer (~snapshot_duration_s 0)";
  if (snapshot_) {
    try {
      recent = snapshot_->take();
    } catch (const std::exception& e) {
      no_recent = e.what();
    }
  }
  // An augmented model on the running base (`piezo residual` keeps a model file's weights) continues
  // from the running base, which has seen the true history, not from the window's start.
  std::vector<std::string> handover(axes_.size());
  const auto t_loaded = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < axes_.size(); ++i)
    cold[i] = recent ? compensation::warm_model(*fresh[i], axes_[i]->logic->axis(), *recent,
                                                &axes_[i]->logic->compensator().model(), &handover[i])
                     : no_recent;
  const auto t_warm = std::chrono::steady_clock::now();
  for (std::size_t i = 0; i < axes_.size(); ++i)
    axes_[i]->logic->reload(files.at(axes_[i]->logic->axis()), std::move(fresh[i]), cold[i].empty());
  const auto t_done = std::chrono::steady_clock::now();
  std::ostringstream took;
  took << std::fixed << std::setprecision(2) << "; took " << secs(t_start, t_done) << " s (load "
       << secs(t_start, t_loaded) << ", warm-up " << secs(t_loaded, t_warm) << ", ideal line "
       << secs(t_warm, t_done) << ")";
  timing = took.str();
  std::string message;
  if (recent && !recent->gaps.empty()) {
    // the running model skipped the same samples: the warm-up runs across the gaps as it did
    message += "; the window has " + compensation::describe_gaps(*recent) +
               ": warmed across the gap(s) as the running model ran";
  }
  for (std::size_t i = 0; i < axes_.size(); ++i)
    message += "; " + axes_[i]->logic->axis() + ": " + warmth(axes_[i]->logic->axis(), cold[i], handover[i], recent);
  return message;
}

std::string PredictorNode::warmth(const std::string& axis, const std::string& cold, const std::string& handover,
                                  const std::optional<compensation::Snapshot>& recent) const {
  if (!cold.empty()) return "cold start (" + cold + ")";
  // the span buffered, not the window: a node up for less than ~snapshot_duration_s (or a ring at
  // ~snapshot_max_messages) holds less, and the reply says so rather than read as a short window
  const double span_s = recent->end_s - recent->begin_s;
  const double window_s = snapshot_->options().duration_s;
  std::ostringstream os;
  os << std::fixed << std::setprecision(1) << "warm, on the buffered " << span_s << " s ("
     << recent->axes.at(axis).readings.size() << " readings";
  if (span_s < window_s - 2.0 * recent->period_s - recent->max_restamp_s) os << ", less than the " << window_s << " s window";
  os << ")";
  return os.str() + (handover.empty() ? "" : ", " + handover);
}

// The whole buffer (not cut to a gap-free stretch, as ~snapshot's bag is: the resume runs across lost samples as the
// running model did), written as .part and renamed, so a reader never sees half a file.
void PredictorNode::save_resume(const char* when) {
  if (!snapshot_) return;
  try {
    const compensation::Snapshot snap = snapshot_->take();
    const std::filesystem::path dir = std::filesystem::path(s_.resume_save_to).parent_path();
    if (!dir.empty()) std::filesystem::create_directories(dir);
    write_snapshot_bag(s_.resume_save_to, nh_.getNamespace(), snap, s_.frame_prefix + "base", data_origin());
    ROS_DEBUG("resume history saved (%s): %s, %.1f s", when, s_.resume_save_to.c_str(), snap.end_s - snap.begin_s);
  } catch (const std::exception& e) {
    ROS_WARN_THROTTLE(60.0, "~resume_save_to: nothing saved (%s): %s", when, e.what());
  }
}

const io::Dataset* PredictorNode::resume_history(std::string& why) {
  if (!resume_read_) {
    resume_read_ = true;
    const std::string& path = s_.resume_from;
    try {
      // a ~snapshot bag of this manipulator (its namespace), read as the reload's warm-up reads it (across lost
      // samples, as the running model ran); its rows are on the ROS clock of the live samples
      ros_io::BagOptions bo;
      bo.ns = nh_.getNamespace();
      io::Dataset d = ros_io::read_bag(path, bo);
      if (d.time_clock != "ros")
        throw io::DataError(path + ": its time column is not ROS time (a ~snapshot bag is)");
      resume_history_ = std::move(d);
    } catch (const std::exception& e) {
      resume_error_ = std::string("~resume_from: ") + e.what();
    }
  }
  why = resume_error_;
  return resume_history_ ? &*resume_history_ : nullptr;
}

}  // namespace piezo::predictor
