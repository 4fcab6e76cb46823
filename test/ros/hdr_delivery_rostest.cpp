// rostest for the HDR delivery procedure: the real dwell_scheduler, afterloader and hdr_procedure
// plan, deliver (with one operator pause) and report; the report is checked.
#include <gtest/gtest.h>
#include <ros/ros.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "../csv_rows.h"
#include "../ros_wait.h"

namespace {

constexpr double kExactS =
    1e-6;  // [s] delivered vs planned per dwell (journal, 1e-9 s + CSV rounding)

TEST(HdrDelivery, PlanDeliverEvaluateReport) {
  ros::NodeHandle private_nh("~");
  std::string report_dir;
  ASSERT_TRUE(private_nh.getParam("report_dir", report_dir));
  const std::string summary = report_dir + "/summary.json";
  const std::optional<std::string> text = waitForText(summary, 200.0);
  ASSERT_TRUE(text) << "the procedure wrote no report in 200 s";
  EXPECT_NE(text->find("\"success\": true"), std::string::npos) << *text;
  EXPECT_NE(text->find("\"status\": \"completed\""), std::string::npos) << *text;
  EXPECT_EQ(text->find("\"interruptions\": 0,"), std::string::npos)
      << "the operator pause is not in the record";

  const auto dwells = readCsvRows(report_dir + "/delivery.csv");
  ASSERT_GT(dwells.size(), 20u);
  double planned = 0.0;
  for (const auto& row : dwells) {
    EXPECT_NEAR(std::stod(row.at("delivered_s")), std::stod(row.at("planned_s")), kExactS)
        << "channel " << row.at("channel") << " dwell " << row.at("dwell_index");
    planned += std::stod(row.at("planned_s"));
  }
  EXPECT_GT(planned, 60.0);

  const auto indices = readCsvRows(report_dir + "/indices.csv");
  bool found_d90 = false;
  for (const auto& row : indices) {
    const double p = std::stod(row.at("planned")), d = std::stod(row.at("delivered")),
                 t = std::stod(row.at("delivered_with_transit"));
    EXPECT_NEAR(d, p, 1e-6 * std::max(1.0, std::abs(p)))
        << row.at("index") << ": delivered as planned";
    if (row.at("index") == "prostate_D90") {
      found_d90 = true;
      EXPECT_GT(t, d) << "the transit adds dose";
      EXPECT_LT(t, 1.1 * d) << "transit dose is a few percent at most";
    }
  }
  EXPECT_TRUE(found_d90);
  // A plain roslaunch writes the plots too: the planned DVH and the dwell times.
  for (const char* png : {"/dvh.png", "/dwells.png"})
    EXPECT_TRUE(std::filesystem::exists(report_dir + png)) << png << " missing";
}

}  // namespace

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "hdr_delivery_rostest");
  return RUN_ALL_TESTS();
}
