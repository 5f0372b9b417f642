// The predictor started with a broken model file keeps the axis movable: uncorrected commands in bounded
// steps, every prediction flagged as fallback with the reason, diagnostics at ERROR with the hardware id.
#include <diagnostic_msgs/DiagnosticArray.h>
#include <gtest/gtest.h>
#include <std_srvs/Trigger.h>

#include "predictor_test_driver.h"

TEST(PredictorFallback, BrokenModelFileGivesBoundedUncorrectedCommands) {
  ros::NodeHandle nh;
  std::vector<diagnostic_msgs::DiagnosticStatus> diags;
  auto sub = nh.subscribe<diagnostic_msgs::DiagnosticArray>("/diagnostics", 10,
      [&](const diagnostic_msgs::DiagnosticArray::ConstPtr& m) {
        for (const auto& s : m->status) diags.push_back(s);
      });
  piezo::test::FakeDriver drv;
  ASSERT_TRUE(drv.wait_connected()) << "predictor topics not connected";
  drv.intend(5.0);
  for (int i = 0; i < 12; ++i) ASSERT_TRUE(drv.cycle()) << "no prediction and command for sample " << i;
  ASSERT_GE(drv.commands.size(), 6u);
  double prev = 0.0;
  for (const auto& c : drv.commands) {
    EXPECT_LE(std::abs(c.voltage - prev), 1.0 + 1e-9) << "fallback step above ~fallback_max_step_v";
    prev = c.voltage;
  }
  EXPECT_NEAR(drv.commands.back().voltage, 5.0, 1e-9) << "fallback must still reach the intent";
  ASSERT_FALSE(drv.predictions.empty());
  const auto& p = drv.predictions.back();
  EXPECT_TRUE(p.fallback);
  EXPECT_FALSE(p.compensation_active);
  EXPECT_NE(p.status.find("model unavailable"), std::string::npos) << p.status;
  EXPECT_NE(p.status.find("broken_model.yaml"), std::string::npos) << p.status;

  // Reloading the same broken file fails and says so.
  std_srvs::Trigger t;
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/reload_model", ros::Duration(piezo::test::kPatienceS)));
  ASSERT_TRUE(ros::service::call("/mm1/predictor/reload_model", t));
  EXPECT_FALSE(t.response.success);
  EXPECT_NE(t.response.message.find("broken_model.yaml"), std::string::npos) << t.response.message;

  // The diagnostics updater publishes on its own period: wait until a status at ERROR names the model.
  const bool seen = piezo::test::FakeDriver::wait([&] {
    for (const auto& s : diags)
      if (s.level == diagnostic_msgs::DiagnosticStatus::ERROR && s.hardware_id == "piezo_predictor" &&
          s.message.find("model unavailable") != std::string::npos)
        return true;
    return false;
  });
  EXPECT_TRUE(seen) << "no ERROR diagnostics naming the unavailable model";
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_fallback_test");
  return RUN_ALL_TESTS();
}
