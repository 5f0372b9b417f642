// The predictor's tf frames (<prefix>tip_measured, tip_predicted, tip_intended under <prefix>base) and rviz markers.
#include "piezo_compensation/ros/predictor.h"

#include <geometry_msgs/TransformStamped.h>
#include <tf2_ros/transform_broadcaster.h>
#include <visualization_msgs/MarkerArray.h>

#include <iomanip>
#include <sstream>

namespace piezo::predictor {

void PredictorNode::publish_tf_and_markers(const ros::Time& stamp) {
  // Axis a → x, b → y, c → z of <prefix>base.
  double measured[3] = {0, 0, 0}, predicted[3] = {0, 0, 0}, intended[3] = {0, 0, 0}, drift[3] = {0, 0, 0};
  std::ostringstream text;
  text << std::fixed << std::setprecision(0);
  for (const auto& a : axes_) {
    const PredictorAxis& l = *a->logic;
    const int i = io::axis_index_or_none(l.axis());
    if (i < 0 || !l.compensator().started()) continue;
    measured[i] = l.has_measurement() ? l.measured_nm() : std::nan("");
    predicted[i] = l.predicted_nm();
    intended[i] = l.intended_nm();
    const double d = l.drift_longest_nm();
    drift[i] = std::isfinite(d) ? d : 0.0;
    text << l.axis() << ": err " << (predicted[i] - intended[i]) << " nm, meas-pred "
         << (l.has_measurement() ? measured[i] - predicted[i] : 0.0) << " nm, drift " << drift[i] << " nm"
         << (l.fallback_now() ? " FALLBACK" : "") << "\n";
  }
  const std::string base = s_.frame_prefix + "base";
  auto tfm = [&](const std::string& child, const double* x) {
    geometry_msgs::TransformStamped t;
    t.header.stamp = stamp;
    t.header.frame_id = base;
    t.child_frame_id = s_.frame_prefix + child;
    t.transform.translation.x = std::isfinite(x[0]) ? x[0] / kNmPerM : 0.0;
    t.transform.translation.y = std::isfinite(x[1]) ? x[1] / kNmPerM : 0.0;
    t.transform.translation.z = std::isfinite(x[2]) ? x[2] / kNmPerM : 0.0;
    t.transform.rotation.w = 1.0;
    return t;
  };
  tf_->sendTransform(std::vector<geometry_msgs::TransformStamped>{
      tfm("tip_measured", measured), tfm("tip_predicted", predicted), tfm("tip_intended", intended)});
  publish_markers(stamp, measured, predicted, intended, drift, text.str());
}

// Markers at marker_scale: nanometre motion is invisible at rviz's smallest view distance.
void PredictorNode::publish_markers(const ros::Time& stamp, const double* measured, const double* predicted,
                                    const double* intended, const double* drift, const std::string& text) {
  const std::string base = s_.frame_prefix + "base";
  const double k = s_.marker_scale / kNmPerM;
  visualization_msgs::MarkerArray arr;
  auto marker = [&](int id, int type, const char* ns) {
    visualization_msgs::Marker m;
    m.header.stamp = stamp;
    m.header.frame_id = base;
    m.ns = ns;
    m.id = id;
    m.type = type;
    m.action = visualization_msgs::Marker::ADD;
    m.pose.orientation.w = 1.0;
    m.color.a = 1.0;
    return m;
  };
  auto point = [&](const double* x) {
    geometry_msgs::Point p;
    p.x = std::isfinite(x[0]) ? x[0] * k : 0.0;
    p.y = std::isfinite(x[1]) ? x[1] * k : 0.0;
    p.z = std::isfinite(x[2]) ? x[2] * k : 0.0;
    return p;
  };
  const double r = 100.0 * k;  // spheres of 100 nm (scaled)
  struct Tip { const char* ns; const double* x; float rgb[3]; };
  const Tip tips[] = {{"tip_measured", measured, {0.2f, 0.4f, 1.0f}},
                      {"tip_predicted", predicted, {1.0f, 0.5f, 0.0f}},
                      {"tip_intended", intended, {0.1f, 0.8f, 0.1f}}};
  int id = 0;
  for (const auto& t : tips) {
    auto m = marker(id++, visualization_msgs::Marker::SPHERE, t.ns);
    m.pose.position = point(t.x);
    m.scale.x = m.scale.y = m.scale.z = r;
    m.color.r = t.rgb[0], m.color.g = t.rgb[1], m.color.b = t.rgb[2];
    arr.markers.push_back(m);
  }
  auto arrow = marker(id++, visualization_msgs::Marker::ARROW, "drift");
  const double end[3] = {predicted[0] + drift[0], predicted[1] + drift[1], predicted[2] + drift[2]};
  arrow.points = {point(predicted), point(end)};
  arrow.scale.x = r * 0.3, arrow.scale.y = r * 0.7, arrow.scale.z = r * 0.7;
  arrow.color.r = 1.0, arrow.color.g = 0.1, arrow.color.b = 0.1;
  arr.markers.push_back(arrow);
  auto label = marker(id++, visualization_msgs::Marker::TEXT_VIEW_FACING, "error_text");
  label.pose.position = point(predicted);
  label.pose.position.z += 6.0 * r;
  label.scale.z = r * 0.8;
  label.color.r = label.color.g = label.color.b = 1.0;
  label.text = text;
  arr.markers.push_back(label);
  markers_pub_.publish(arr);
}

}  // namespace piezo::predictor
