// piezo_predictor's parameters: every wrong type and out-of-range value stops it with one error naming the
// resolved parameter (issue 15); a misspelt private parameter is listed, not ignored silently.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/ros/params.h"
#include "piezo_compensation/ros/predictor.h"

using piezo::predictor::read_settings;

TEST(PredictorParams, WrongTypeAndOutOfRangeAreNamed) {
  XmlRpc::XmlRpcValue horizons_bad_type;
  horizons_bad_type[0] = XmlRpc::XmlRpcValue(1.0);
  horizons_bad_type[1] = XmlRpc::XmlRpcValue("60");
  XmlRpc::XmlRpcValue horizons_too_long;
  for (int i = 0; i < 9; ++i) horizons_too_long[i] = XmlRpc::XmlRpcValue(1.0 * (i + 1));
  XmlRpc::XmlRpcValue axes_unknown;
  axes_unknown[0] = XmlRpc::XmlRpcValue("d");
  const std::vector<std::pair<std::string, XmlRpc::XmlRpcValue>> cases = {
      {"axes", XmlRpc::XmlRpcValue("c")},                    // a string where a list is expected
      {"axes", axes_unknown},
      {"compensation", XmlRpc::XmlRpcValue("yes")},
      {"drift_horizons_s", horizons_bad_type},
      {"drift_horizons_s", horizons_too_long},                // allocation bound
      {"ideal_line_hold_s", XmlRpc::XmlRpcValue(1e7)},        // allocation bound
      {"ideal_line_hold_s", XmlRpc::XmlRpcValue("60")},
      {"sample_rate_hz", XmlRpc::XmlRpcValue(-11.0)},
      {"watch_k", XmlRpc::XmlRpcValue(0.5)},
      {"voltage_max_v", XmlRpc::XmlRpcValue(5000.0)},
      {"fallback_max_step_v", XmlRpc::XmlRpcValue(0.0)},
      {"hardware_id", XmlRpc::XmlRpcValue(3)},
  };
  int k = 0;
  for (const auto& [param, value] : cases) {
    const std::string ns = "/predictor_bad_params/case_" + std::to_string(k++);
    ros::NodeHandle pnh(ns);
    pnh.setParam("model_file", "/nonexistent/model.yaml");
    pnh.setParam(param, value);
    try {
      read_settings(pnh);
      ADD_FAILURE() << param << ": accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find(ns + "/" + param), std::string::npos) << param << ": " << e.what();
    }
  }
  // Good values of the same names are accepted, so the failures above are the values, not the setup.
  ros::NodeHandle good("/predictor_bad_params/good");
  good.setParam("model_file", "/nonexistent/model.yaml");
  good.setParam("axes", std::vector<std::string>{"c"});
  good.setParam("drift_horizons_s", std::vector<double>{1.0, 60.0});
  good.setParam("ideal_line_hold_s", 30);
  const auto s = read_settings(good);
  EXPECT_EQ(s.axes, std::vector<std::string>{"c"});
  EXPECT_EQ(s.drift_horizons_s.size(), 2u);
  EXPECT_DOUBLE_EQ(s.ideal_line_hold_s, 30.0);
}

TEST(PredictorParams, MissingModelFileIsNamed) {
  ros::NodeHandle pnh("/predictor_no_model");
  try {
    read_settings(pnh);
    ADD_FAILURE() << "no model_file accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("/predictor_no_model/model_file"), std::string::npos) << e.what();
  }
}

TEST(PredictorParams, UnknownPrivateParametersAreListed) {
  ros::NodeHandle pnh("/predictor_unknown_params");
  pnh.setParam("model_file", "/nonexistent/model.yaml");
  pnh.setParam("watch_k", 3.0);
  pnh.setParam("watch_treshold", 5.0);  // a typo that would otherwise be ignored
  piezo::params::ParamReader r(pnh);
  r.number("watch_k", 2.0, 1.0, 1000.0);
  r.known("model_file");
  EXPECT_EQ(r.unknown(), std::vector<std::string>{"watch_treshold"});
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_params");
  ros::NodeHandle nh;
  return RUN_ALL_TESTS();
}
