// piezo_predictor's parameters: every wrong type and out-of-range value stops it with one error naming the
// resolved parameter; a misspelt private parameter is listed, not ignored silently.
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <rosgraph_msgs/Log.h>

#include <cstdio>
#include <fstream>
#include <sstream>

#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "piezo_compensation/ros/interfaces.h"
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
      {"resume_from", XmlRpc::XmlRpcValue(1.0)},
      {"resume_max_gap_s", XmlRpc::XmlRpcValue(-1.0)},
      {"resume_voltage_tolerance_v", XmlRpc::XmlRpcValue("0.05")},
      {"resume_save_period_s", XmlRpc::XmlRpcValue(1e9)},
      {"resume_save_period_s", XmlRpc::XmlRpcValue(0.01)},  // each save writes the whole buffer
      {"resume_save_to", XmlRpc::XmlRpcValue(3)},
      {"transport", XmlRpc::XmlRpcValue("usb")},
      {"allow_simulated_model", XmlRpc::XmlRpcValue("yes")},
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
  // ~resume_save_to saves the snapshot buffer: without one (~snapshot_duration_s 0) it is refused, naming it.
  {
    ros::NodeHandle pnh("/predictor_bad_params/resume_without_buffer");
    pnh.setParam("model_file", "/nonexistent/model.yaml");
    pnh.setParam("snapshot_duration_s", 0.0);
    pnh.setParam("resume_save_to", "/tmp/x.bag");
    try {
      read_settings(pnh);
      ADD_FAILURE() << "resume_save_to without a snapshot buffer: accepted";
    } catch (const std::invalid_argument& e) {
      EXPECT_NE(std::string(e.what()).find("/predictor_bad_params/resume_without_buffer/resume_save_to"), std::string::npos)
          << e.what();
    }
  }
  // Good values of the same names are accepted, so the failures above are the values, not the setup.
  ros::NodeHandle good("/predictor_bad_params/good");
  good.setParam("model_file", "/nonexistent/model.yaml");
  good.setParam("axes", std::vector<std::string>{"c"});
  good.setParam("drift_horizons_s", std::vector<double>{1.0, 60.0});
  good.setParam("ideal_line_hold_s", 30);
  good.setParam("resume_from", "/tmp/run_before.bag");
  good.setParam("resume_save_to", "/tmp/run_before.bag");
  good.setParam("resume_save_period_s", 0.0);
  const auto s = read_settings(good);
  EXPECT_EQ(s.resume_from, "/tmp/run_before.bag");
  EXPECT_EQ(s.resume_save_period_s, 0.0);
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

// A model file whose training recording did not identify it (`piezo fit` stored validation: carry_over_ratio over
// 2) is loaded, but with one WARN naming the file (at start-up and at ~reload_model, both through load_model_file);
// a file under the limit loads without one. The WARN is read back from /rosout.
TEST(PredictorParams, AnUnidentifiedModelFileIsWarnedAboutWhenLoaded) {
  std::ifstream in(std::string(PIEZO_SOURCE_DIR) + "/test/rostest/pi_creep_model_c.yaml");
  std::stringstream text;
  text << in.rdbuf();
  const std::string shipped = text.str(), empty_validation = "validation:\n  {}\n";
  ASSERT_NE(shipped.find(empty_validation), std::string::npos);
  auto write = [&](const std::string& path, const char* ratio) {
    std::string t = shipped;
    t.replace(t.find(empty_validation), empty_validation.size(), std::string("validation:\n  carry_over_ratio: ") + ratio + "\n");
    std::ofstream(path) << t;
  };
  const std::string dir = testing::TempDir(), identified = dir + "identified_model.yaml",
                    unidentified = dir + "unidentified_model.yaml";
  write(identified, "1.3");
  write(unidentified, "5.5");
  std::vector<rosgraph_msgs::Log> seen;
  ros::NodeHandle nh;
  ros::Subscriber sub = nh.subscribe<rosgraph_msgs::Log>("/rosout", 100, [&](const rosgraph_msgs::Log::ConstPtr& m) {
    if (m->msg.find("model file ") != std::string::npos) seen.push_back(*m);
  });
  for (int i = 0; i < 50 && sub.getNumPublishers() == 0; ++i) ros::WallDuration(0.05).sleep();
  EXPECT_NE(piezo::predictor::load_model_file(identified), nullptr);
  EXPECT_NE(piezo::predictor::load_model_file(unidentified), nullptr);  // loaded: a warning, not a refusal
  for (int i = 0; i < 100 && seen.empty(); ++i) ros::spinOnce(), ros::WallDuration(0.05).sleep();
  ros::spinOnce();
  ASSERT_EQ(seen.size(), 1u) << "no WARN (or more than one) on /rosout";
  EXPECT_EQ(seen[0].level, rosgraph_msgs::Log::WARN);
  EXPECT_NE(seen[0].msg.find(unidentified), std::string::npos) << seen[0].msg;
  EXPECT_NE(seen[0].msg.find("5.5x"), std::string::npos) << seen[0].msg;
  EXPECT_NE(seen[0].msg.find("refit on a longer recording"), std::string::npos) << seen[0].msg;
  std::remove(identified.c_str());
  std::remove(unidentified.c_str());
}

// The node reads through its interface table: a name the table lacks, a read of another type, or a topic used with
// another message type is a programming error (std::logic_error), never a silent second definition.
TEST(PredictorParams, ReadsGoThroughTheInterfaceTable) {
  const auto& table = piezo::predictor::predictor_interface();
  ros::NodeHandle pnh("/predictor_table_reads");
  piezo::params::ParamReader r(pnh, table);
  EXPECT_DOUBLE_EQ(r.number("watch_k"), table.param("watch_k").number);
  EXPECT_THROW(r.number("watch_treshold"), std::logic_error);
  EXPECT_THROW(r.integer("watch_k"), std::logic_error);
  EXPECT_EQ(table.topic_name<piezo_compensation::Prediction>("<axis>/prediction", "b"), "b/prediction");
  EXPECT_THROW(table.topic_name<piezo_compensation::VoltageCommand>("<axis>/prediction", "b"), std::logic_error);
  EXPECT_EQ(table.service_name<std_srvs::SetBool>("~set_hold_trim"), "set_hold_trim");
  EXPECT_THROW(table.service_name<std_srvs::Trigger>("~set_hold_trim"), std::logic_error);
  pnh.setParam("watch_k", 0.5);
  EXPECT_THROW(r.number("watch_k"), std::invalid_argument);  // the table's range [1, 1000]
  pnh.deleteParam("watch_k");
}

// A model of one axis loaded for another is refused for that axis: load_model_file names both axes, and the node
// keeps the axis (uncorrected, FALLBACK) with one ERROR naming both; one path for several axes is a deprecation WARN.
TEST(PredictorParams, AModelOfAnotherAxisIsRefusedForThatAxis) {
  const std::string c_model = std::string(PIEZO_SOURCE_DIR) + "/test/rostest/pi_creep_model_c.yaml";
  EXPECT_NE(piezo::predictor::load_model_file(c_model, "c"), nullptr);
  try {
    piezo::predictor::load_model_file(c_model, "a");
    ADD_FAILURE() << "a model of axis c was loaded for axis a";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("model fitted for axis c, loaded for axis a"), std::string::npos) << e.what();
  }
  std::vector<rosgraph_msgs::Log> errors, warnings;
  ros::NodeHandle nh;
  ros::Subscriber sub = nh.subscribe<rosgraph_msgs::Log>("/rosout", 100, [&](const rosgraph_msgs::Log::ConstPtr& m) {
    if (m->level == rosgraph_msgs::Log::ERROR) errors.push_back(*m);
    if (m->level == rosgraph_msgs::Log::WARN && m->msg.find("deprecated") != std::string::npos) warnings.push_back(*m);
  });
  for (int i = 0; i < 50 && sub.getNumPublishers() == 0; ++i) ros::WallDuration(0.05).sleep();
  ros::NodeHandle ns("/mm_axis_check"), pnh("/mm_axis_check/predictor");
  XmlRpc::XmlRpcValue axes;
  axes[0] = "a", axes[1] = "c";
  pnh.setParam("axes", axes);
  pnh.setParam("model_file", c_model);  // one path for both axes
  pnh.setParam("transport", "simulated");  // the model was fitted on simulated data
  pnh.setParam("snapshot_duration_s", 0.0);
  pnh.setParam("drift_async", false);
  {
    piezo::predictor::PredictorNode node(ns, pnh);
    for (int i = 0; i < 100 && (errors.empty() || warnings.empty()); ++i) ros::spinOnce(), ros::WallDuration(0.05).sleep();
    ros::WallDuration(0.2).sleep();
    ros::spinOnce();
  }
  ASSERT_EQ(errors.size(), 1u) << "expected one ERROR for axis a";
  const std::string& msg = errors[0].msg;
  EXPECT_NE(msg.find("axis a"), std::string::npos) << msg;
  EXPECT_NE(msg.find("model fitted for axis c, loaded for axis a"), std::string::npos) << msg;
  EXPECT_NE(msg.find("fallback"), std::string::npos) << msg;
  EXPECT_EQ(warnings.size(), 1u) << "expected one deprecation WARN for one path given for two axes";
  for (const auto& p : {"axes", "model_file", "transport", "snapshot_duration_s", "drift_async"}) pnh.deleteParam(p);
}

// A model fitted on simulated data (training.fitted_on: simulated) on a real transport (~transport's default): the
// node keeps the axis uncorrected with one ERROR naming the file and ~allow_simulated_model; with it true the model
// runs, with a WARN.
TEST(PredictorParams, ASimulatedModelIsRefusedOnARealTransport) {
  const std::string model = std::string(PIEZO_SOURCE_DIR) + "/test/rostest/pi_creep_model_c.yaml";
  std::vector<rosgraph_msgs::Log> errors, warnings;
  ros::NodeHandle nh;
  ros::Subscriber sub = nh.subscribe<rosgraph_msgs::Log>("/rosout", 100, [&](const rosgraph_msgs::Log::ConstPtr& m) {
    if (m->msg.find("simulated data") == std::string::npos) return;
    (m->level == rosgraph_msgs::Log::ERROR ? errors : warnings).push_back(*m);
  });
  for (int i = 0; i < 50 && sub.getNumPublishers() == 0; ++i) ros::WallDuration(0.05).sleep();
  for (const bool allow : {false, true}) {
    SCOPED_TRACE(allow ? "allowed" : "refused");
    errors.clear(), warnings.clear();
    const std::string at = allow ? "/mm_real_allowed" : "/mm_real";
    ros::NodeHandle ns(at), pnh(at + "/predictor");
    XmlRpc::XmlRpcValue axes;
    axes[0] = "c";
    pnh.setParam("axes", axes);
    pnh.setParam("model_file", model);
    pnh.setParam("snapshot_duration_s", 0.0);
    pnh.setParam("drift_async", false);
    if (allow) pnh.setParam("allow_simulated_model", true);
    {
      piezo::predictor::PredictorNode node(ns, pnh);
      for (int i = 0; i < 100 && errors.empty() && warnings.empty(); ++i) ros::spinOnce(), ros::WallDuration(0.05).sleep();
      ros::WallDuration(0.2).sleep();
      ros::spinOnce();
    }
    const auto& got = allow ? warnings : errors;
    ASSERT_EQ(got.size(), 1u);
    EXPECT_EQ((allow ? errors : warnings).size(), 0u);
    EXPECT_NE(got[0].msg.find(model), std::string::npos) << got[0].msg;
    EXPECT_NE(got[0].msg.find(at + "/predictor/allow_simulated_model"), std::string::npos) << got[0].msg;
    if (!allow) EXPECT_NE(got[0].msg.find("fallback"), std::string::npos) << got[0].msg;
    for (const auto& p : {"axes", "model_file", "snapshot_duration_s", "drift_async", "allow_simulated_model"})
      pnh.deleteParam(p);
  }
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_params");
  ros::NodeHandle nh;
  return RUN_ALL_TESTS();
}
