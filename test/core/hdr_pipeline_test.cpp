// The HDR procedure core (src/procedures/hdr_pipeline, hdr_report): one pipeline for the node,
// the tool and the benches. A synthetic case planned by LP, delivered exactly as planned, must
// evaluate to the planned indices; a partial delivery must lower the target coverage; bad
// delivery records and bad method names are refused naming the entry; the report writes its
// files and plots, and its success means the outcome.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "needle_guidance/procedures/hdr_pipeline.h"
#include "needle_guidance/procedures/hdr_report.h"
#include "needle_guidance/report/plot.h"

namespace needle_guidance::procedures {
namespace {

constexpr double kIndexRel = 1e-9;  // delivered-as-planned indices equal the planned ones

HdrPlan plannedCase(int seed) {
  SourceCache sources;
  HdrCaseInput input;
  input.synthetic_seed = seed;
  return planHdr(loadHdrCase(input), "test_plan_" + std::to_string(seed), HdrPlanSettings{},
                 sources);
}

DeliveryRecord asPlanned(const HdrPlan& plan, double fraction = 1.0) {
  DeliveryRecord record;
  for (const auto& ch : plan.schedule.channels) {
    for (std::size_t k = 0; k < ch.time_s.size(); ++k)
      record.dwells.push_back({ch.channel, ch.dwell_index[k], fraction * ch.time_s[k]});
    record.trips.push_back({ch.channel, 1});
  }
  return record;
}

double index(const DeliveryEvaluation& ev, const std::string& name,
             double DeliveryEvaluation::Index::*field) {
  for (const auto& i : ev.indices) {
    if (i.name == name)
      return i.*field;
  }
  ADD_FAILURE() << "no index " << name;
  return std::nan("");
}

TEST(HdrPipeline, DeliveredAsPlannedEvaluatesToThePlan) {
  const HdrPlan plan = plannedCase(3);
  ASSERT_FALSE(plan.schedule.channels.empty());
  EXPECT_EQ(plan.method, DwellMethod::kLp);
  EXPECT_LE(plan.optimisation.lower_bound, plan.optimisation.objective * (1.0 + 1e-9));
  ASSERT_EQ(plan.dvh_dose_Gy.size(), 201u);
  for (const auto& [name, volume] : plan.dvh) {
    ASSERT_EQ(volume.size(), plan.dvh_dose_Gy.size()) << name;
    EXPECT_NEAR(volume.front(), 100.0, 1e-9) << name << ": all of it gets at least 0 Gy";
  }
  const DeliveryEvaluation ev = evaluateDelivery(plan, asPlanned(plan), HdrPlanSettings{});
  ASSERT_EQ(ev.indices.size(), plan.planned_indices.size());
  for (const auto& i : ev.indices) {
    EXPECT_NEAR(i.delivered, i.planned, kIndexRel * std::max(1.0, std::abs(i.planned))) << i.name;
    EXPECT_GE(i.with_transit, i.delivered - 1e-12) << i.name << ": transit only adds dose";
  }
  EXPECT_GT(ev.transit_dose_max_Gy, 0.0);
}

TEST(HdrPipeline, HalfTheDwellTimeLowersCoverage) {
  const HdrPlan plan = plannedCase(4);
  const DeliveryEvaluation ev = evaluateDelivery(plan, asPlanned(plan, 0.5), HdrPlanSettings{});
  const double planned = index(ev, "prostate_V100", &DeliveryEvaluation::Index::planned);
  const double delivered = index(ev, "prostate_V100", &DeliveryEvaluation::Index::delivered);
  EXPECT_GT(planned, 80.0) << "the LP plan covers the target";
  EXPECT_LT(delivered, 0.5 * planned) << "half the time cannot give the prescription to most of it";
}

TEST(HdrPipeline, BadRecordsAreRefusedNamingTheEntry) {
  const HdrPlan plan = plannedCase(5);
  DeliveryRecord nan_time = asPlanned(plan);
  nan_time.dwells[2].delivered_s = std::nan("");
  try {
    evaluateDelivery(plan, nan_time, HdrPlanSettings{});
    FAIL() << "a NaN delivered time was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("entry 2"), std::string::npos) << e.what();
  }
  DeliveryRecord stray = asPlanned(plan);
  stray.dwells.push_back({999, 0, 1.0});
  EXPECT_THROW(evaluateDelivery(plan, stray, HdrPlanSettings{}), std::invalid_argument);
  DeliveryRecord negative_trips = asPlanned(plan);
  negative_trips.trips[0].trips = -1;
  EXPECT_THROW(evaluateDelivery(plan, negative_trips, HdrPlanSettings{}), std::invalid_argument);
}

TEST(HdrPipeline, MethodsAndInputsAreChecked) {
  EXPECT_EQ(parseDwellMethod("lp"), DwellMethod::kLp);
  EXPECT_EQ(parseDwellMethod("sa"), DwellMethod::kAnnealing);
  EXPECT_STREQ(toString(DwellMethod::kAnnealing), "sa");
  try {
    parseDwellMethod("simplex", "parameter '~method'");
    FAIL() << "an unknown method was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("~method"), std::string::npos) << e.what();
  }
  HdrCaseInput two;
  two.case_dir = "/nonexistent";
  two.synthetic_seed = 1;
  EXPECT_THROW(loadHdrCase(two), std::invalid_argument) << "two sources at once";
  HdrCaseInput missing;
  missing.case_dir = "/nonexistent/case";
  EXPECT_THROW(loadHdrCase(missing), std::invalid_argument);
  HdrCaseInput negative;
  negative.synthetic_seed = -3;
  EXPECT_THROW(loadHdrCase(negative), std::invalid_argument);
}

TEST(HdrReport, WritesItsFilesAndSuccessMeansTheOutcome) {
  const HdrPlan plan = plannedCase(6);
  HdrDeliveryReport r;
  r.case_name = plan.hdr_case.name;
  r.plan_id = "p";
  r.status = "completed";
  r.dvh_dose_Gy = plan.dvh_dose_Gy;
  r.dvh = plan.dvh;
  for (const auto& ch : plan.schedule.channels) {
    for (std::size_t k = 0; k < ch.time_s.size(); ++k)
      r.dwells.push_back({ch.channel, ch.dwell_index[k], ch.time_s[k], ch.time_s[k], 0.0});
  }
  r.indices = evaluateDelivery(plan, asPlanned(plan), HdrPlanSettings{}).indices;
  EXPECT_TRUE(r.success());
  const auto dir = std::filesystem::temp_directory_path() / "ng_hdr_report_test";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  r.write(dir.string());
  for (const char* f : {"summary.json", "summary.md", "delivery.csv", "indices.csv"})
    EXPECT_TRUE(std::filesystem::exists(dir / f)) << f;
  for (const char* png : {"dvh.png", "dwells.png"}) {
    const cv::Mat image = cv::imread((dir / png).string());
    EXPECT_FALSE(image.empty()) << png;
  }

  HdrDeliveryReport off = r;
  off.dwells[0].delivered_s += 1.0;  // one dwell a second off: beyond the 0.1 s tolerance
  EXPECT_FALSE(off.success());
  HdrDeliveryReport died = r;
  died.dead_node = "/afterloader";
  died.cause = "node /afterloader died";
  EXPECT_FALSE(died.success()) << "a run stopped by a dead node never succeeds";
  died.write(dir.string());
  std::stringstream json;
  json << std::ifstream(dir / "summary.json").rdbuf();
  EXPECT_NE(json.str().find("\"dead_node\": \"/afterloader\""), std::string::npos) << json.str();
  EXPECT_NE(json.str().find("\"success\": false"), std::string::npos);
}

TEST(LinePlot, SkipsNonFiniteValuesAndRefusesMismatchedSeries) {
  report::LinePlot plot("t", "x", "y");
  plot.addLine("a", {0.0, 1.0, 2.0}, {0.0, std::nan(""), 2.0}, report::seriesColour(0));
  const cv::Mat image = plot.render(400, 300);
  EXPECT_EQ(image.cols, 400);
  EXPECT_EQ(image.rows, 300);
  EXPECT_THROW(plot.addLine("b", {0.0}, {1.0, 2.0}, report::seriesColour(1)),
               std::invalid_argument);
  const cv::Mat keyed = report::withColourKey(image, cv::COLORMAP_VIRIDIS, 0.0, 1.0, "P_s");
  EXPECT_GT(keyed.cols, image.cols);
}

}  // namespace
}  // namespace needle_guidance::procedures

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
