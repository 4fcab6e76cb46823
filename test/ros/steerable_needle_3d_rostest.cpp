// rostest for the 3-D closed-loop steerable-needle trials: steering_planner_3d,
// insertion_robot in its 3-D steerable mode (the noisy needle) and steerable_procedure_3d run 4
// trials on prostate_3d (steerable_needle_3d_biplane.test: 3 trials whose tips come from the
// frames of two imager nodes, views along z and along y, triangulated by the procedure; the report
// names the source and more than half of the view pairs were fused); the report is
// checked against the scene independently of the procedure (each recorded path re-checked for
// contact with the scene's collision world, each success's last tip against the target ball),
// the success count against the bench's rate, and the planner refuses non-finite and wrong-frame
// tip poses with status bad_input and no NaN while the procedure runs. After the last trial the
// robot is left safe: summary.json says "needle retracted" and the robot's insertion joint reads
// 0. steerable_needle_3d_travel.test gives the robot a 30 mm insertion travel: every trial ends
// as a refusal naming the travel (success 0), none as a fault, and the run completes.
// steerable_needle_3d_biplane_no_imager.test: tip_source biplane with no imager running ends as a
// fault whose message names the imager's topic.
#include <geometry_msgs/PoseWithCovarianceStamped.h>
#include <gtest/gtest.h>
#include <ros/ros.h>
#include <sensor_msgs/JointState.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "../csv_rows.h"
#include "../ros_wait.h"
#include "needle_guidance/SteeringControl3.h"
#include "needle_guidance/needle_model/scene_3d.h"

namespace {

// Defaults (the launch may set ~trials, ~min_successes, ~biplane): the bench measures 0.98
// [0.95, 0.99] on prostate_3d at 1x; with p = 0.95 fewer than 3 of 4 successes has probability
// 1.4 % (fewer than 2 of 3: 0.7 %).
constexpr int kTrials = 4;
constexpr int kMinSuccesses = 3;
constexpr double kMmTol = 1e-3;  // [mm] CSV rounding of positions (6 significant digits)
constexpr double kRefusalWaitS = 10.0;
constexpr double kJointTolM = 1e-9;  // [m] a retracted insertion joint reads exactly 0
// Biplane: more than half of the view pairs fused (the rest dropped or gated), i.e. the views,
// not the prediction from the controls, carry the loop.
constexpr double kMinFusedFraction = 0.5;

/// Publishes `tip` to the planner and returns its answer (matched by stamp).
std::optional<needle_guidance::SteeringControl3> askPlanner(
    const geometry_msgs::PoseWithCovarianceStamped& tip) {
  ros::NodeHandle nh;
  std::optional<needle_guidance::SteeringControl3> answer;
  ros::Subscriber sub = nh.subscribe<needle_guidance::SteeringControl3>(
      "/steering_planner_3d/control", 10, [&](const needle_guidance::SteeringControl3ConstPtr& m) {
        if (m->header.stamp == tip.header.stamp)
          answer = *m;
      });
  ros::Publisher pub =
      nh.advertise<geometry_msgs::PoseWithCovarianceStamped>("/steerable_procedure_3d/tip", 1);
  waitFor([&] { return pub.getNumSubscribers() > 0 && sub.getNumPublishers() > 0; }, kRefusalWaitS);
  pub.publish(tip);
  waitFor(
      [&] {
        ros::spinOnce();
        return answer.has_value();
      },
      kRefusalWaitS, 0.02);
  return answer;
}

void expectRefused(const needle_guidance::SteeringControl3& c, const std::string& what) {
  EXPECT_EQ(c.status, "bad_input");
  EXPECT_NE(c.message.find(what), std::string::npos) << c.message;
  for (double v : {c.rotate_rad, c.curvature_per_m, c.insertion_m, c.plan_length_m, c.p_success}) {
    EXPECT_EQ(v, 0.0);
  }
}

TEST(SteerableNeedle3d, PlannerRefusesBadTipPoses) {
  struct Case {
    std::string frame;
    double x, w;           // position x [m], quaternion w
    std::string expected;  // in the refusal's message
  };
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const std::vector<Case> cases = {{"scene", nan, 1.0, "not finite"},
                                   {"world", 0.01, 1.0, "frame 'world'"},
                                   {"scene", 0.01, 2.0, "norm"}};
  for (std::size_t k = 0; k < cases.size(); ++k) {
    geometry_msgs::PoseWithCovarianceStamped tip;
    tip.header.frame_id = cases[k].frame;
    tip.header.stamp = ros::Time(12345, static_cast<std::uint32_t>(k + 1));
    tip.pose.pose.position.x = cases[k].x;
    tip.pose.pose.orientation.w = cases[k].w;
    const auto answer = askPlanner(tip);
    ASSERT_TRUE(answer) << "no answer to bad tip " << k << " (" << cases[k].expected << ")";
    expectRefused(*answer, cases[k].expected);
  }
}

TEST(SteerableNeedle3d, TrialsReachTheTargetAndTheReportMatchesTheScene) {
  ros::NodeHandle private_nh("~");
  std::string report_dir, scene_path;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  ASSERT_TRUE(private_nh.getParam("scene", scene_path));
  const int n_trials = private_nh.param("trials", kTrials);
  const int min_successes = private_nh.param("min_successes", kMinSuccesses);
  const double wait_s = private_nh.param("report_wait_s", 100.0);
  ASSERT_TRUE(waitForFile(report_dir + "/summary.json", wait_s))
      << "no report in " << wait_s << " s";
  const std::string summary = readText(report_dir + "/summary.json");
  EXPECT_NE(summary.find("\"trials\": " + std::to_string(n_trials) + ","), std::string::npos)
      << summary;
  if (private_nh.param("biplane", false)) {  // the tips came from the rendered views
    EXPECT_NE(summary.find("\"tip_source\": \"biplane\""), std::string::npos) << summary;
    const double fused = jsonNumber(summary, "views_fused");
    const double pairs =
        fused + jsonNumber(summary, "views_dropped") + jsonNumber(summary, "views_gated");
    ASSERT_GT(pairs, 0.0) << summary;  // NaN (a key missing) fails too
    EXPECT_GT(fused / pairs, private_nh.param("min_fused_fraction", kMinFusedFraction)) << summary;
  }
  EXPECT_NE(summary.find("\"status\": \"completed\""), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"faults\": 0"), std::string::npos) << summary;

  namespace sd = needle_guidance::needle_model;
  const sd::Scene3d scene = sd::loadScene3d(scene_path);
  const sd::CollisionWorld3 world = scene.collisionWorld();
  const auto trials = readCsvRows(report_dir + "/trials.csv");
  ASSERT_EQ(trials.size(), static_cast<std::size_t>(n_trials));
  std::map<std::string, std::vector<sd::Vector3>> paths;
  for (const auto& row : readCsvRows(report_dir + "/paths.csv")) {
    paths[row.at("trial")].push_back(1e-3 * sd::Vector3(std::stod(row.at("x_mm")),
                                                        std::stod(row.at("y_mm")),
                                                        std::stod(row.at("z_mm"))));
  }
  int successes = 0;
  for (const auto& row : trials) {
    const std::vector<sd::Vector3>& path = paths[row.at("trial")];
    ASSERT_GE(path.size(), 2U) << "trial " << row.at("trial");
    const sd::Vector3 from_centre = path.front() - scene.entry.center_m;
    const double along = from_centre.dot(scene.entry.direction);
    EXPECT_NEAR(along * 1e3, 0.0, kMmTol)
        << "trial " << row.at("trial") << " starts off the entry disc";
    EXPECT_LE((from_centre - along * scene.entry.direction).norm() * 1e3,
              scene.entry.radius_m * 1e3 + kMmTol)
        << "trial " << row.at("trial") << " starts outside the entry disc";
    const double error_mm = (path.back() - scene.target.center_m).norm() * 1e3;
    EXPECT_NEAR(std::stod(row.at("target_error_mm")), error_mm, kMmTol);
    if (row.at("success") == "1") {
      ++successes;
      EXPECT_LE(error_mm, scene.target.radius_m * 1e3 + kMmTol) << "trial " << row.at("trial");
      EXPECT_EQ(world.checkPolyline(path).contact, sd::Contact3::kFree)
          << "trial " << row.at("trial");
    }
  }
  EXPECT_GE(successes, min_successes) << summary;
  if (private_nh.param("travel_refusals", false)) {  // the robot's travel is shorter than a plan
    for (const auto& row : trials) {
      EXPECT_EQ(row.at("success"), "0");
      EXPECT_EQ(row.at("fault"), "0");
      EXPECT_NE(row.at("message").find("beyond the insertion joint's travel of 0.03 m"),
                std::string::npos)
          << "trial " << row.at("trial") << ": " << row.at("message");
    }
  }
  EXPECT_NE(summary.find("\"successes\": " + std::to_string(successes) + ","), std::string::npos);

  // The robot left safe after the last trial: the needle out of the tissue.
  EXPECT_NE(summary.find("\"safe_stop\": \"needle retracted\""), std::string::npos) << summary;
  const auto js = firstMessage<sensor_msgs::JointState>("/insertion_robot/measured_js", 5.0);
  ASSERT_TRUE(js) << "no joint state from the robot";
  const auto insertion = std::find(js->name.begin(), js->name.end(), "insertion");
  ASSERT_NE(insertion, js->name.end());
  EXPECT_NEAR(js->position.at(static_cast<std::size_t>(insertion - js->name.begin())), 0.0,
              kJointTolM);
}

TEST(SteerableNeedle3d, AMissingImagerIsAFaultNamingItsTopic) {
  // steerable_needle_3d_biplane_no_imager.test: tip_source biplane but no imager runs. The first
  // step's wait for a frame ends after ~control_timeout_s as a fault (not a miss) whose message
  // names the topic; the run stops there, the robot is left safe.
  ros::NodeHandle private_nh("~");
  if (!private_nh.param("missing_imager", false)) {
    GTEST_SKIP() << "only in steerable_needle_3d_biplane_no_imager.test";
  }
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  const double wait_s = private_nh.param("report_wait_s", 60.0);
  ASSERT_TRUE(waitForFile(report_dir + "/summary.json", wait_s))
      << "no report in " << wait_s << " s";
  const std::string summary = readText(report_dir + "/summary.json");
  EXPECT_NE(summary.find("\"status\": \"fault\""), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"faults\": 1"), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"safe_stop\": \"needle retracted\""), std::string::npos) << summary;
  const auto trials = readCsvRows(report_dir + "/trials.csv");
  ASSERT_EQ(trials.size(), 1U);
  EXPECT_EQ(trials[0].at("fault"), "1");
  EXPECT_EQ(trials[0].at("success"), "0");
  EXPECT_NE(trials[0].at("message").find("/imager_along_z/image: no frame after the step within"),
            std::string::npos)
      << trials[0].at("message");
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "steerable_needle_3d_rostest");
  return RUN_ALL_TESTS();
}
