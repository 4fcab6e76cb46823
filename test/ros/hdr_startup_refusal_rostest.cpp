// rostest: a device node that refuses its parameters at start-up makes the HDR procedure fail
// with a report that names it, within its start-up timeout, never a pass or a hang.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <fstream>
#include <sstream>
#include <string>

#include "../ros_wait.h"

namespace {

constexpr double kReportWithin_s = 60.0;  // start-up timeout 5 s + planning, on a loaded machine

TEST(HdrStartupRefusal, ReportNamesTheNodeThatNeverCameUp) {
  ros::NodeHandle private_nh("~");
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  const std::string summary = report_dir + "/summary.json";
  const std::optional<std::string> text = waitForText(summary, kReportWithin_s);
  ASSERT_TRUE(text) << "no report: the procedure hung";
  EXPECT_NE(text->find("\"success\": false"), std::string::npos) << *text;
  EXPECT_NE(text->find("\"status\": \"not_started\""), std::string::npos) << *text;
  EXPECT_NE(text->find("\"dead_node\": \"/afterloader\""), std::string::npos) << *text;
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "hdr_startup_refusal_rostest");
  return RUN_ALL_TESTS();
}
