#include "piezo_compensation/ros/monitor.h"

#include <geometry_msgs/TransformStamped.h>
#include <visualization_msgs/MarkerArray.h>

#include <cmath>
#include <limits>
#include <map>
#include <stdexcept>

#include "piezo_compensation/io/axes.h"
#include "piezo_compensation/ros/interfaces.h"
#include "piezo_compensation/ros/params.h"

namespace piezo::monitor {
namespace {

using analysis::ChartPrimitive;

// The chart names the model by its folder and file ("models/mm3e_sim_c.yaml"): the full path is on the
// predictor's diagnostics, and a checkout's absolute path would fill the headline.
std::string model_label(const std::string& path) {
  const auto last = path.find_last_of('/');
  if (last == std::string::npos || last == 0) return path;
  const auto parent = path.find_last_of('/', last - 1);
  return parent == std::string::npos ? path : path.substr(parent + 1);
}

visualization_msgs::Marker to_marker(const ChartPrimitive& p, const std::string& frame, const ros::Time& stamp) {
  visualization_msgs::Marker m;
  m.header.frame_id = frame;
  m.header.stamp = stamp;
  m.ns = p.name;
  m.id = 0;
  m.action = visualization_msgs::Marker::ADD;
  m.pose.orientation.w = 1.0;
  m.pose.position.z = p.z;
  m.color.r = p.color.r, m.color.g = p.color.g, m.color.b = p.color.b, m.color.a = p.color.a;
  switch (p.type) {
    case ChartPrimitive::Type::kPoints:
      m.type = visualization_msgs::Marker::POINTS;
      m.scale.x = m.scale.y = p.size;
      break;
    case ChartPrimitive::Type::kLineStrip:
      m.type = visualization_msgs::Marker::LINE_STRIP;
      m.scale.x = p.size;
      break;
    case ChartPrimitive::Type::kLineList:
      m.type = visualization_msgs::Marker::LINE_LIST;
      m.scale.x = p.size;
      break;
    case ChartPrimitive::Type::kTriangleList:
      m.type = visualization_msgs::Marker::TRIANGLE_LIST;
      m.scale.x = m.scale.y = m.scale.z = 1.0;
      break;
    case ChartPrimitive::Type::kText:
      m.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
      m.scale.z = p.size;
      m.text = p.text;
      m.pose.position.x = p.x.at(0);
      m.pose.position.y = p.y.at(0);
      return m;
  }
  m.points.resize(p.x.size());
  for (std::size_t i = 0; i < p.x.size(); ++i) m.points[i].x = p.x[i], m.points[i].y = p.y[i];
  return m;
}

}  // namespace

const params::NodeInterface& monitor_interface() {
  using namespace params;
  static const NodeInterface t = [] {
    const analysis::StripChartOptions d;
    const std::vector<std::string> all(io::kAxisNames.begin(), io::kAxisNames.end());
    NodeInterface n;
    n.node = "piezo_monitor";
    n.summary = "the operator's strip charts (measured, predicted, intended, drift fan, error lane) as rviz markers";
    n.params = {
        texts("axes", all, all, 1, all.size(), "axes to chart (reads <axis>/prediction)"),
        number("window_s", "s", d.window_s, 1.0, 86400.0, "time span of each chart"),
        number("noise_sigma_nm", "nm", d.noise_sigma_nm, 0.0, 1e6,
               "noise-floor σ of the error bands; 0 = estimated from the window's readings"),
        structured("encoder_resolution_nm", "nm", "double or map", "0",
                   "encoder step, one number or a map per axis {a: 250.0, c: 20.0}, each in [0, 1e6]; the noise "
                   "floor is at least step/sqrt(12); 0 or a missing axis = the step seen in the readings"),
        number("publish_rate_hz", "Hz", 4.0, 0.1, 50.0, "marker updates per second (wall)"),
        text("frame_prefix", "", "frames <prefix>chart under <prefix>base"),
        text("chart_frame", "chart", "the chart's frame (after the prefix)"),
        text("parent_frame", "base", "the frame the chart hangs off (after the prefix)"),
    };
    using D = TopicDef::Direction;
    n.topics = {
        {"<axis>/prediction", "piezo_compensation/Prediction", D::kSubscribes, "the predictor's output per axis"},
        {"monitor/chart", "visualization_msgs/MarkerArray", D::kPublishes, "the strip charts (latched)"},
        {"/tf_static", "tf2_msgs/TFMessage", D::kPublishes, "<prefix>chart under <prefix>base (identity)"},
    };
    return n;
  }();
  return t;
}

MonitorNode::MonitorNode(ros::NodeHandle nh, ros::NodeHandle pnh) : nh_(nh) {
  const params::NodeInterface& iface = monitor_interface();
  params::ParamReader r(pnh, iface);
  axes_ = r.texts("axes");
  analysis::StripChartOptions o;
  o.window_s = r.number("window_s");
  o.noise_sigma_nm = r.number("noise_sigma_nm");
  // ~encoder_resolution_nm: one step for every axis, or a map {a: 250, b: 250, c: 20}
  std::map<std::string, double> resolution;
  r.structured("encoder_resolution_nm");
  XmlRpc::XmlRpcValue q;
  const auto as_step = [&](XmlRpc::XmlRpcValue& v, const std::string& name) {
    double x = std::nan("");
    if (v.getType() == XmlRpc::XmlRpcValue::TypeDouble) x = static_cast<double>(v);
    if (v.getType() == XmlRpc::XmlRpcValue::TypeInt) x = static_cast<int>(v);
    if (!(x >= 0.0 && x <= 1e6))
      throw std::invalid_argument("parameter " + pnh.resolveName(name) + " must be a number of nm in 0..1e6");
    return x;
  };
  if (pnh.getParam("encoder_resolution_nm", q)) {
    for (const auto& a : axes_) {
      if (q.getType() == XmlRpc::XmlRpcValue::TypeStruct) {
        if (q.hasMember(a)) resolution[a] = as_step(q[a], "encoder_resolution_nm/" + a);
      } else {
        resolution[a] = as_step(q, "encoder_resolution_nm");
      }
    }
  }
  const double rate_hz = r.number("publish_rate_hz");
  const std::string prefix = r.text("frame_prefix");
  frame_id_ = prefix + r.text("chart_frame");
  const std::string parent = prefix + r.text("parent_frame");
  r.warn_unknown(pnh.getNamespace());

  for (const auto& a : axes_) {
    o.encoder_resolution_nm = resolution.count(a) ? resolution[a] : 0.0;
    charts_.push_back(std::make_unique<analysis::StripChart>(a, o));
    analysis::StripChart* chart = charts_.back().get();
    subs_.push_back(nh_.subscribe<piezo_compensation::Prediction>(
        iface.topic_name<piezo_compensation::Prediction>("<axis>/prediction", a), 50, [chart](const piezo_compensation::Prediction::ConstPtr& m) {
          analysis::ChartSample s;
          s.time_s = m->header.stamp.toSec();
          s.measured_nm = m->measured_position * 1e9;
          s.predicted_nm = m->fallback ? std::numeric_limits<double>::quiet_NaN() : m->predicted_position * 1e9;
          s.intended_nm = m->intended_position * 1e9;
          // the fused estimate and its σ (NaN when the model file has no estimator block)
          s.fused_nm = m->fallback ? std::numeric_limits<double>::quiet_NaN() : m->fused_position * 1e9;
          s.fused_sigma_nm = m->fused_position_sigma * 1e9;
          s.voltage_v = m->compensation_active ? m->corrected_voltage : m->commanded_voltage;
          s.drift_horizons_s = m->drift_horizons;
          for (double d : m->drift) s.drift_nm.push_back(d * 1e9);
          s.compensation_active = m->compensation_active;
          s.fallback = m->fallback;
          s.model = model_label(m->model);
          s.status = m->status;
          chart->add(std::move(s));
        }));
  }
  pub_ = nh_.advertise<visualization_msgs::MarkerArray>(iface.topic_name<visualization_msgs::MarkerArray>("monitor/chart"), 1, true);
  // The chart frame hangs off the manipulator's base so rviz has it in its tf tree (identity: the chart is flat
  // in its own units, not in metres of the tip).
  geometry_msgs::TransformStamped t;
  t.header.stamp = ros::Time::now();
  t.header.frame_id = parent;
  t.child_frame_id = frame_id_;
  t.transform.rotation.w = 1.0;
  static_tf_.sendTransform(t);
  timer_ = nh_.createWallTimer(ros::WallDuration(1.0 / rate_hz), &MonitorNode::publish, this);
  ROS_INFO("piezo_monitor: %zu axis charts, %.0f s window, markers on %s in frame %s", axes_.size(), o.window_s,
           pub_.getTopic().c_str(), frame_id_.c_str());
}

void MonitorNode::publish(const ros::WallTimerEvent&) {
  visualization_msgs::MarkerArray arr;
  const ros::Time stamp;  // time 0: rviz draws in the frame's latest transform (a static one)
  double y = 0.0;
  for (const auto& c : charts_) {
    for (const auto& p : c->draw(0.0, y)) arr.markers.push_back(to_marker(p, frame_id_, stamp));
    y -= c->height();
  }
  pub_.publish(arr);
}

}  // namespace piezo::monitor
