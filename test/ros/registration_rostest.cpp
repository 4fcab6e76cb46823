// rostest node for the registration node (registration.test).
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <visualization_msgs/MarkerArray.h>

#include <cmath>
#include <limits>
#include <mutex>
#include <optional>

#include "../ros_wait.h"
#include "needle_guidance/Register.h"

namespace {

using needle_guidance::Register;
constexpr double kMinDice = 0.97;          // synthetic balloon case, default options
constexpr double kMaxPointError_mm = 1.0;  // test-point error target

class RegistrationNodeTest : public ::testing::Test {
protected:
  void SetUp() override {
    client_ = nh_.serviceClient<Register>("registration/register");
    ASSERT_TRUE(client_.waitForExistence(ros::Duration(30.0)));
    sub_ = nh_.subscribe("registration/markers", 1, &RegistrationNodeTest::onMarkers, this);
  }
  void onMarkers(const visualization_msgs::MarkerArrayConstPtr& m) {
    std::lock_guard<std::mutex> lock(mutex_);
    markers_ = *m;
  }
  std::optional<visualization_msgs::MarkerArray> markers() {
    std::lock_guard<std::mutex> lock(mutex_);
    return markers_;
  }
  static geometry_msgs::Polygon square(double cx, double cy, double half) {
    geometry_msgs::Polygon p;
    for (const auto& [dx, dy] : {std::pair{-1.0, -1.0}, {1.0, -1.0}, {1.0, 1.0}, {-1.0, 1.0}}) {
      geometry_msgs::Point32 v;
      v.x = static_cast<float>(cx + dx * half);
      v.y = static_cast<float>(cy + dy * half);
      p.points.push_back(v);
    }
    return p;
  }
  ros::NodeHandle nh_;
  ros::ServiceClient client_;
  ros::Subscriber sub_;
  std::mutex mutex_;
  std::optional<visualization_msgs::MarkerArray> markers_;
};

TEST_F(RegistrationNodeTest, SyntheticCaseRegistersAndBeatsTheRigidBaseline) {
  Register srv;
  srv.request.synthetic_seed = 1;
  srv.request.probe_type = "balloon";
  srv.request.alpha = -1.0;
  ASSERT_TRUE(client_.call(srv));
  EXPECT_TRUE(srv.response.success) << srv.response.status << ": " << srv.response.message;
  EXPECT_GE(srv.response.dice, kMinDice);
  EXPECT_GT(srv.response.dice, srv.response.initial_dice);
  EXPECT_LE(srv.response.point_error_mm, kMaxPointError_mm);
  EXPECT_LT(srv.response.point_error_mm, srv.response.rigid_point_error_mm);
  ASSERT_EQ(srv.response.modulus_kPa.size(), 3U);
  for (double e : srv.response.modulus_kPa) {
    EXPECT_GE(e, 1.0);
    EXPECT_LE(e, 600.0);
  }
  ASSERT_FALSE(srv.response.grid_probe_in.empty());
  EXPECT_EQ(srv.response.grid_probe_in.size(), srv.response.grid_probe_out.size());
  EXPECT_EQ(srv.response.grid_probe_in.size(), srv.response.grid_valid.size());
  // 7 mm MRSI grid (3.3.3): neighbours in a row are 7 mm apart in the probe-in slice.
  EXPECT_NEAR(std::hypot(srv.response.grid_probe_in[1].x - srv.response.grid_probe_in[0].x,
                         srv.response.grid_probe_in[1].y - srv.response.grid_probe_in[0].y),
              0.007, 1e-9);
  ASSERT_TRUE(waitFor([this] { return markers().has_value(); }, 10.0, 0.05))
      << "no markers published";
  EXPECT_GT(markers()->markers.size(), 3U);
}

TEST_F(RegistrationNodeTest, BadRequestsAreRefusedWithAReason) {
  Register srv;
  srv.request.synthetic_seed = 1;
  srv.request.probe_type = "inflatable";
  ASSERT_TRUE(client_.call(srv));
  EXPECT_FALSE(srv.response.success);
  EXPECT_NE(srv.response.message.find("probe_type"), std::string::npos) << srv.response.message;

  Register bad_optimizer;
  bad_optimizer.request.synthetic_seed = 1;
  bad_optimizer.request.optimizer = "newton";
  ASSERT_TRUE(client_.call(bad_optimizer));
  EXPECT_FALSE(bad_optimizer.response.success);
  EXPECT_NE(bad_optimizer.response.message.find("optimizer"), std::string::npos);

  // Explicit segmentations: a probe far from the rectum does not enclose it.
  Register far;
  far.request.domain = square(0.0, 0.0, 0.05);
  far.request.cg = square(0.0, 0.01, 0.008);
  far.request.pz = square(0.02, 0.01, 0.004);
  far.request.rectum = square(0.0, -0.02, 0.008);
  far.request.probe_in_prostate = square(0.0, 0.012, 0.01);
  far.request.probe = square(0.03, 0.03, 0.005);
  ASSERT_TRUE(client_.call(far));
  EXPECT_FALSE(far.response.success);
  EXPECT_FALSE(far.response.message.empty());
  EXPECT_TRUE(std::isfinite(far.response.dice));

  Register nan = far;
  nan.request.cg.points[1].x = std::numeric_limits<float>::quiet_NaN();
  ASSERT_TRUE(client_.call(nan));
  EXPECT_FALSE(nan.response.success);
  EXPECT_NE(nan.response.message.find("cg"), std::string::npos) << nan.response.message;
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "registration_rostest");
  ros::AsyncSpinner spinner(1);
  spinner.start();
  return RUN_ALL_TESTS();
}
