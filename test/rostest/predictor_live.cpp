// The predictor against a fake driver: with compensation on it sends the model-inverted voltage (different
// from the intent on a hysteretic model), with it off the intent itself; the prediction says which; the tf
// frames of the measured, predicted and intended tip exist under the base frame.
#include <gtest/gtest.h>
#include <std_srvs/SetBool.h>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_listener.h>

#include "predictor_test_driver.h"

TEST(PredictorLive, CompensationOnOffAndTfFrames) {
  tf2_ros::Buffer tf;
  tf2_ros::TransformListener listener(tf);
  piezo::test::FakeDriver drv;
  ASSERT_TRUE(drv.wait_connected(20.0)) << "predictor topics not connected";
  drv.intend(30.0);
  for (int i = 0; i < 15; ++i) drv.cycle();
  ASSERT_FALSE(drv.commands.empty());
  ASSERT_FALSE(drv.predictions.empty());
  const auto on = drv.predictions.back();
  EXPECT_TRUE(on.compensation_active) << on.status;
  EXPECT_FALSE(on.fallback) << on.status;
  EXPECT_NEAR(drv.commands.back().voltage, on.corrected_voltage, 1e-9);
  EXPECT_NEAR(on.commanded_voltage, 30.0, 1e-9);
  EXPECT_GT(std::abs(on.corrected_voltage - 30.0), 0.05) << "a hysteretic model must correct the voltage";
  EXPECT_TRUE(std::isfinite(on.predicted_position));
  EXPECT_NEAR(on.measured_position, 14e-9 * drv.reported_v, 1e-15);
  ASSERT_EQ(on.drift.size(), on.drift_horizons.size());
  EXPECT_EQ(on.drift_horizons.size(), 3u);

  std_srvs::SetBool off;
  off.request.data = false;
  ASSERT_TRUE(ros::service::waitForService("/mm1/predictor/set_compensation", ros::Duration(5)));
  ASSERT_TRUE(ros::service::call("/mm1/predictor/set_compensation", off));
  EXPECT_TRUE(off.response.success);
  const std::size_t n = drv.commands.size();
  for (int i = 0; i < 5; ++i) drv.cycle();
  ASSERT_GT(drv.commands.size(), n);
  EXPECT_NEAR(drv.commands.back().voltage, 30.0, 1e-12) << "compensation off sends the intent unchanged";
  EXPECT_FALSE(drv.predictions.back().compensation_active);

  std_srvs::SetBool again;
  again.request.data = true;
  ASSERT_TRUE(ros::service::call("/mm1/predictor/set_compensation", again));
  for (int i = 0; i < 3; ++i) drv.cycle();
  EXPECT_TRUE(drv.predictions.back().compensation_active);
  EXPECT_GT(std::abs(drv.commands.back().voltage - 30.0), 0.05);

  for (const char* child : {"mm1/tip_measured", "mm1/tip_predicted", "mm1/tip_intended"}) {
    std::string err;
    EXPECT_TRUE(tf.canTransform("mm1/base", child, ros::Time(0), ros::Duration(3.0), &err)) << child << ": " << err;
  }
  const auto t = tf.lookupTransform("mm1/base", "mm1/tip_measured", ros::Time(0));
  EXPECT_NEAR(t.transform.translation.z, drv.predictions.back().measured_position, 1e-7);  // axis c → z
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "predictor_live_test");
  return RUN_ALL_TESTS();
}
