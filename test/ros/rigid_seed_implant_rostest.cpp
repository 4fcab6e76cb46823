// rostest for the rigid seed-implant procedure: the real robot, tissue_sim, rigid_planner and
// insertion_procedure run two targets end to end; the procedure's report is checked: every move
// succeeded and each seed's measured error agrees with the plan's prediction.
#include <gtest/gtest.h>

#include <ros/ros.h>
#include "../csv_rows.h"
#include "../ros_wait.h"

#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

namespace {

// The depth grid: the live loop executes the planner's verified FEM steps, so the
// measured seed error is the verified one (to the report's 6 digits).
constexpr double kPredictionAgreement_mm = 1e-5;
constexpr int kTargets = 2;
constexpr double kPlacementTolerance_mm = 0.1;  // the scene's needle.placement_tolerance (default)

TEST(RigidSeedImplant, TwoTargetsLandWherePredicted) {
  ros::NodeHandle private_nh("~");
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  const std::string summary = report_dir + "/summary.json";
  ASSERT_TRUE(waitForFile(summary, 200.0)) << "the procedure wrote no report in 200 s";
  const auto rows = readCsvRows(report_dir + "/moves.csv");
  ASSERT_EQ(rows.size(), static_cast<std::size_t>(kTargets));
  for (const auto& row : rows) {
    EXPECT_EQ(row.at("status"), "ok") << row.at("target");
    const double measured_mm = std::stod(row.at("seed_error_mm"));
    const double predicted_mm = std::stod(row.at("predicted_error_mm"));
    const double unplanned_mm = std::stod(row.at("unplanned_predicted_mm"));
    EXPECT_NEAR(measured_mm, predicted_mm, kPredictionAgreement_mm) << row.at("target");
    EXPECT_NEAR(measured_mm, std::stod(row.at("verified_error_mm")), kPredictionAgreement_mm)
        << row.at("target");
    EXPECT_LT(measured_mm, 0.25 * unplanned_mm) << row.at("target") << ": planning did not help";
    // Success means the seed landed: the outcome follows the measured error and the tolerance.
    EXPECT_EQ(row.at("outcome"), measured_mm <= kPlacementTolerance_mm ? "placed" : "missed")
        << row.at("target");
    EXPECT_FALSE(row.at("verified_error_mm").empty())
        << row.at("target") << ": the plan was not verified";
  }
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "rigid_seed_implant_rostest");
  return RUN_ALL_TESTS();
}
