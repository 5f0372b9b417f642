// piezo_demo: drives one axis of the simulated manipulator through a demo scenario (scripts/demo), once
// uncompensated and once compensated, one intent per encoder sample; the scenario, the pairing of the device's
// reports (io/sequence_pairer.h) and the scoring are compensation::DemoRun (compensation/demo_scenario.h), this
// node only moves messages.
// Its parameters, topics and services: predictor::demo_interface() (src/ros/demo_interface.cpp, docs/ros_interface.md).
// With ~lockstep the next intent goes out once the predictor's prediction of the sample is in, so the demo paces
// the device; it is stamped with that sample's stamp (the node then uses no ROS time: the lock-step rostests take it
// off /clock).
#include <ros/callback_queue.h>
#include <ros/ros.h>
#include <std_srvs/SetBool.h>

#include <cmath>
#include <fstream>
#include <optional>
#include <utility>
#include <vector>

#include "piezo_compensation/AxisVoltage.h"
#include "piezo_compensation/EncoderPosition.h"
#include "piezo_compensation/IntendedMotion.h"
#include "piezo_compensation/Prediction.h"
#include "piezo_compensation/compensation/demo_scenario.h"
#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/params.h"
#include "piezo_compensation/ros/predictor.h"

namespace {

using piezo::compensation::DemoRun;

std::unique_ptr<DemoRun> make_run(ros::NodeHandle& pnh, std::string& axis, std::string& out_prefix,
                                  double& progress_s, std::vector<std::pair<std::string, double>>& holds) {
  const piezo::params::NodeInterface& iface = piezo::predictor::demo_interface();
  piezo::params::ParamReader r(pnh, iface);
  const std::string scenario = r.text("scenario");
  axis = r.text("axis");
  out_prefix = r.text("out_prefix");
  const std::string model_file = r.text("model_file");
  piezo::compensation::CreepDemoOptions co;
  if (scenario == "hold_trim") co = piezo::compensation::hold_trim_demo_defaults();  // the table's rule says so
  const std::vector<double> scen_default(co.scenarios.begin(), co.scenarios.end());
  co.score_last_s = r.number("score_last_s", co.score_last_s);
  piezo::compensation::MovesDemoOptions mo;
  co.hold_s = r.number("hold_s", scenario == "tracking_trim" ? mo.hold_s : co.hold_s);
  mo.hold_s = co.hold_s;
  mo.moves = r.integer("moves", mo.moves);
  mo.seed = r.integer("moves_seed", mo.seed);
  mo.hold_score_from_s = r.number("hold_score_from_s", mo.hold_score_from_s);
  co.history_s = r.number("creep_history_s", co.history_s);
  co.seed = r.integer("creep_seed", co.seed);
  co.scenarios.clear();
  for (double s : r.numbers("creep_scenarios", scen_default)) {
    if (s != std::floor(s)) throw std::invalid_argument("parameter " + r.resolved("creep_scenarios") + ": integers only");
    co.scenarios.push_back(static_cast<int>(s));
  }
  piezo::compensation::IdealLineOptions o;
  o.hold_s = r.number("ideal_line_hold_s");
  progress_s = r.number("progress_period_s");
  const bool lockstep = r.flag("lockstep");
  const auto hold_axes = r.texts("hold_axes");
  const auto hold_v = r.numbers("hold_axes_v");
  if (hold_v.size() != hold_axes.size())
    throw std::invalid_argument("parameter " + r.resolved("hold_axes_v") + ": one voltage per ~hold_axes entry");
  for (std::size_t i = 0; i < hold_axes.size(); ++i) {
    if (hold_axes[i] == axis) throw std::invalid_argument("parameter " + r.resolved("hold_axes") + ": contains ~axis");
    holds.emplace_back(hold_axes[i], hold_v[i]);
  }
  r.warn_unknown(pnh.getNamespace());
  auto model = piezo::predictor::load_model_file(model_file, axis);
  o.sample_rate_hz = model->meta.sample_rate_hz;
  return std::make_unique<DemoRun>(scenario, co, piezo::compensation::ideal_line_from_model(*model, o),
                                   model->meta.sample_rate_hz, lockstep, mo);
}

// The other axes held at their voltages: latched, so the predictor gets the intent whenever it connects.
std::vector<ros::Publisher> hold_other_axes(ros::NodeHandle& nh, const piezo::params::NodeInterface& iface,
                                            const std::vector<std::pair<std::string, double>>& holds,
                                            const char* name) {
  using piezo_compensation::IntendedMotion;
  std::vector<ros::Publisher> hold_pubs;
  for (const auto& [ax, v] : holds) {
    hold_pubs.push_back(nh.advertise<IntendedMotion>(iface.topic_name<IntendedMotion>("<axis>/intended", ax), 1, true));
    IntendedMotion im;
    im.header.stamp = ros::Time::now();
    im.mode = IntendedMotion::VOLTAGE;
    im.voltage = v;
    hold_pubs.back().publish(im);
    ROS_INFO("demo %s: axis %s held at %.1f V", name, ax.c_str(), v);
  }
  return hold_pubs;
}

// Runs the callbacks until the scenario is done, with a progress line every progress_s, then writes the CSV and
// the JSON summary.
void spin_and_write(DemoRun& run, double progress_s, const std::string& out_prefix, const char* name) {
  const ros::WallTime start = ros::WallTime::now();
  ros::WallTime next_progress = start + ros::WallDuration(progress_s);
  while (ros::ok() && !run.done()) {
    ros::getGlobalCallbackQueue()->callAvailable(ros::WallDuration(0.05));
    const ros::WallTime now = ros::WallTime::now();
    if (now >= next_progress) {
      next_progress = now + ros::WallDuration(progress_s);
      const double f = static_cast<double>(run.progress()) / static_cast<double>(run.steps());
      const double el = (now - start).toSec();
      ROS_INFO("demo %s: progress %.0f %% (%zu/%zu samples), %.0f s elapsed, ETA %.0f s", name, 100 * f,
               run.progress(), run.steps(), el, f > 0 ? el * (1 - f) / f : NAN);
    }
  }
  std::ofstream csv(out_prefix + ".csv"), js(out_prefix + ".json");
  run.write_csv(csv);
  run.write_json(js);
  const auto& pc = run.pairing();
  ROS_INFO("demo %s: wrote %s.csv and %s.json (%zu samples) in %.0f s; pairing: %llu lost voltages, %llu lost "
           "readings, %llu lost truths, %llu dropped", name, out_prefix.c_str(), out_prefix.c_str(),
           run.rows().size(), (ros::WallTime::now() - start).toSec(),
           static_cast<unsigned long long>(pc.lost_voltages), static_cast<unsigned long long>(pc.lost_readings),
           static_cast<unsigned long long>(pc.lost_truths), static_cast<unsigned long long>(pc.dropped_samples));
}

// The predictor's switches a pass sets before its first intent (lock-step: before the device's next sample).
struct ModeSwitches {
  ros::ServiceClient compensation, hold_trim, tracking_trim;
};

void call_switch(ros::ServiceClient& c, bool on) {
  std_srvs::SetBool req;
  req.request.data = on;
  if (!c.call(req) || !req.response.success)
    throw std::runtime_error(c.getService() + " failed" + (req.response.message.empty() ? "" : ": " + req.response.message));
}

void switch_mode(const DemoRun& run, const DemoRun::Next& n, ModeSwitches& sw, const char* name) {
  call_switch(sw.compensation, n.compensated);
  if (run.switches_hold_trim()) {
    call_switch(sw.hold_trim, n.hold_trim);
    ROS_INFO("demo %s: %s run", name, n.hold_trim ? "hold-trimmed" : "feedforward-only");
  } else if (run.switches_tracking_trim()) {
    call_switch(sw.hold_trim, true);
    call_switch(sw.tracking_trim, n.tracking_trim);
    ROS_INFO("demo %s: tracking trim %s run", name, n.tracking_trim ? "on" : "off");
  } else {
    ROS_INFO("demo %s: %s run", name, n.compensated ? "compensated" : "uncompensated");
  }
}

}  // namespace

int main(int argc, char** argv) {
  ros::init(argc, argv, "piezo_demo");
  ros::NodeHandle nh, pnh("~");
  try {
    std::string axis, out_prefix;
    double progress_s = 10.0;
    std::vector<std::pair<std::string, double>> holds;
    auto run = make_run(pnh, axis, out_prefix, progress_s, holds);
    const char* name = run->scenario().c_str();
    ROS_INFO("demo %s: %zu samples (%.0f s simulated per mode), ideal line %.4f nm/V + %.2f nm%s", name, run->steps(),
             run->steps() / 2.0 / run->rate_hz(), run->line().gain_nm_per_v, run->line().offset_nm,
             run->lockstep() ? ", lock-step (paced by this node)" : "");
    const piezo::params::NodeInterface& iface = piezo::predictor::demo_interface();
    using piezo_compensation::IntendedMotion;
    auto intended = nh.advertise<IntendedMotion>(iface.topic_name<IntendedMotion>("<axis>/intended", axis), 5);
    const std::string set_compensation = iface.service_name<std_srvs::SetBool>("predictor/set_compensation"),
                      set_hold_trim = iface.service_name<std_srvs::SetBool>("predictor/set_hold_trim"),
                      set_tracking_trim = iface.service_name<std_srvs::SetBool>("predictor/set_tracking_trim");
    ModeSwitches sw{nh.serviceClient<std_srvs::SetBool>(set_compensation),
                    nh.serviceClient<std_srvs::SetBool>(set_hold_trim),
                    nh.serviceClient<std_srvs::SetBool>(set_tracking_trim)};
    const auto act = [&](const std::optional<DemoRun::Next>& n) {
      if (!n) return;
      if (n->set_mode) switch_mode(*run, *n, sw, name);
      piezo_compensation::IntendedMotion im;
      // lock-step: the intent follows the sample just completed, so it carries that sample's stamp (what ROS time
      // says then, without waiting on /clock: this node needs no clock of its own in lock-step)
      const auto& rows = run->rows();
      im.header.stamp = run->lockstep() && !rows.empty() && rows.back().stamp_s > 0.0 ? ros::Time(rows.back().stamp_s)
                                                                                        : ros::Time::now();
      im.mode = piezo_compensation::IntendedMotion::VOLTAGE;
      im.voltage = n->intent_v;
      intended.publish(im);
    };
    using piezo_compensation::AxisVoltage;
    using piezo_compensation::EncoderPosition;
    using piezo_compensation::Prediction;
    const auto hints = ros::TransportHints().tcpNoDelay();
    auto s1 = nh.subscribe<EncoderPosition>(iface.topic_name<EncoderPosition>("<axis>/encoder", axis), 50, [&](const EncoderPosition::ConstPtr& m) {
      act(run->on_encoder(m->sequence, m->position * 1e9, m->header.stamp.toSec(), m->valid));
    }, ros::VoidConstPtr(), hints);
    auto s2 = nh.subscribe<EncoderPosition>(iface.topic_name<EncoderPosition>("<axis>/true_position", axis), 50, [&](const EncoderPosition::ConstPtr& m) {
      act(run->on_truth(m->sequence, m->position * 1e9, m->header.stamp.toSec()));
    }, ros::VoidConstPtr(), hints);
    auto s3 = nh.subscribe<AxisVoltage>(iface.topic_name<AxisVoltage>("<axis>/voltage", axis), 50, [&](const AxisVoltage::ConstPtr& m) {
      act(run->on_voltage(m->sequence, m->voltage, m->header.stamp.toSec()));
    }, ros::VoidConstPtr(), hints);
    auto s4 = nh.subscribe<Prediction>(iface.topic_name<Prediction>("<axis>/prediction", axis), 50, [&](const Prediction::ConstPtr& m) {
      DemoRun::Estimate e;
      e.fused_nm = m->fused_position * 1e9;
      e.fused_sigma_nm = m->fused_position_sigma * 1e9;
      e.hold_trim_nm = m->hold_trim * 1e9;
      e.hold_trim_state = m->hold_trim_state;
      e.tracking_trim_nm = m->tracking_trim * 1e9;
      e.tracking_trim_state = m->tracking_trim_state;
      act(run->on_prediction(m->header.stamp.toSec(), m->commanded_voltage,
                             m->compensation_active ? m->corrected_voltage : m->commanded_voltage, m->fallback, e));
    }, ros::VoidConstPtr(), hints);
    if (!ros::service::waitForService(nh.resolveName(set_compensation), ros::Duration(60)))
      throw std::runtime_error("predictor/set_compensation not available after 60 s");
    if (run->records_estimates() &&
        !ros::service::waitForService(nh.resolveName(set_hold_trim), ros::Duration(10)))
      throw std::runtime_error("predictor/set_hold_trim not available");
    if (run->switches_tracking_trim() &&
        !ros::service::waitForService(nh.resolveName(set_tracking_trim), ros::Duration(10)))
      throw std::runtime_error("predictor/set_tracking_trim not available");
    const std::vector<ros::Publisher> hold_pubs = hold_other_axes(nh, iface, holds, name);
    spin_and_write(*run, progress_s, out_prefix, name);
  } catch (const std::exception& e) {
    ROS_FATAL("piezo_demo: %s", e.what());
    return 1;
  }
  return 0;
}
