// rostest for the rigid seed-implant procedure's fault path: SIGKILL tissue_sim while
// the needle is in tissue during the second target; the procedure retracts within 2 s and its
// report names /tissue_sim, the time, and counts only the targets actually tried.
#include <gtest/gtest.h>
#include <ros/network.h>
#include <ros/ros.h>
#include <sensor_msgs/JointState.h>
#include <signal.h>
#include <xmlrpcpp/XmlRpcClient.h>

#include <atomic>
#include <fstream>
#include <iostream>
#include <mutex>
#include <sstream>
#include <string>

#include "../csv_rows.h"
#include "../ros_wait.h"
#include "needle_guidance/TissueStatus.h"

namespace {

constexpr double kDetectAndStop_s = 2.0;  // death seen and robot stopped within 2 s
constexpr double kRetractStart_m = 2e-4;  // the tip has moved back this far: retraction started

/// A node's process id, asked from the node itself (what `rosnode info` does).

TEST(RigidSeedImplantFault, KilledTissueSimStopsTheRobotAndIsReported) {
  ros::NodeHandle nh, private_nh("~");
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  std::mutex mutex;
  int seeds = 0;
  bool in_tissue = false;
  ros::Subscriber status = nh.subscribe<needle_guidance::TissueStatus>(
      "tissue_sim/status", 10, [&](const needle_guidance::TissueStatusConstPtr& m) {
        std::lock_guard<std::mutex> lock(mutex);
        seeds = std::max(seeds, static_cast<int>(m->seeds));
        in_tissue = m->needle_in_tissue;
      });
  double depth = 0.0, deepest_after_kill = -1.0;
  ros::WallTime kill_time, retract_seen;
  std::atomic<bool> killed{false};
  ros::Subscriber js = nh.subscribe<sensor_msgs::JointState>(
      "insertion_robot/measured_js", 50, [&](const sensor_msgs::JointStateConstPtr& m) {
        std::lock_guard<std::mutex> lock(mutex);
        for (std::size_t i = 0; i < m->name.size() && i < m->position.size(); ++i) {
          if (m->name[i] == "insertion")
            depth = m->position[i];
        }
        if (killed) {
          deepest_after_kill = std::max(deepest_after_kill, depth);
          if (retract_seen.isZero() && depth < deepest_after_kill - kRetractStart_m) {
            retract_seen = ros::WallTime::now();
          }
        }
      });
  ros::AsyncSpinner spinner(2);
  spinner.start();
  // The first target is done (a seed implanted, the needle back out; the tissue resets after it)
  // and the needle is back in tissue, 1 cm deep, for the second.
  ASSERT_TRUE(waitFor(
      [&] {
        std::lock_guard<std::mutex> l(mutex);
        return seeds >= 1;
      },
      150.0))
      << "the first seed was never implanted";
  ASSERT_TRUE(waitFor(
      [&] {
        std::lock_guard<std::mutex> l(mutex);
        return depth < 0.0;
      },
      60.0))
      << "the first needle never came out";
  ASSERT_TRUE(waitFor(
      [&] {
        std::lock_guard<std::mutex> l(mutex);
        return in_tissue && depth > 0.01;
      },
      60.0))
      << "the second insertion never went 1 cm deep";
  const int pid = nodePid("/tissue_sim");
  ASSERT_GT(pid, 0);
  kill_time = ros::WallTime::now();
  killed = true;
  ASSERT_EQ(::kill(pid, SIGKILL), 0);
  const std::string summary = report_dir + "/summary.json";
  ASSERT_TRUE(waitForFile(summary, 60.0)) << "no report after the kill";
  {
    std::lock_guard<std::mutex> l(mutex);
    ASSERT_FALSE(retract_seen.isZero()) << "the robot never retracted after the kill";
    EXPECT_LT((retract_seen - kill_time).toSec(), kDetectAndStop_s);
    std::cout << "retraction began " << (retract_seen - kill_time).toSec()
              << " s after tissue_sim was killed\n";
    EXPECT_LT(depth, 0.0) << "the needle is still in the tissue";
  }
  const std::string json = readText(summary);
  EXPECT_NE(json.find("\"success\": false"), std::string::npos) << json;
  EXPECT_NE(json.find("\"node\": \"/tissue_sim\""), std::string::npos) << json;
  EXPECT_NE(json.find("\"targets_tried\": 2"), std::string::npos) << json;
  EXPECT_NE(json.find("\"safe_stop\": \"needle retracted"), std::string::npos) << json;
  const auto rows = readCsvRows(report_dir + "/moves.csv");
  ASSERT_EQ(rows.size(), 2U);  // the third target was never tried: no row
  EXPECT_EQ(rows[1].at("outcome"), "error");
  EXPECT_NE(rows[1].at("status").find("/tissue_sim died"), std::string::npos)
      << rows[1].at("status");
  EXPECT_TRUE(rows[1].at("seed_error_mm").empty());
  EXPECT_TRUE(std::ifstream(report_dir + "/seed_errors.png").good());
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "rigid_seed_implant_fault_rostest");
  return RUN_ALL_TESTS();
}
