// RigidImplantProcedure with in-process devices: the planner's verified error is the
// seed error the procedure measures when the tissue follows the robot in its own samples; a
// refused target has no error figures; a fault stops the robot and the report counts only the
// targets tried; the report writes its files and plot.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "needle_guidance/procedures/rigid_implant.h"
#include "needle_guidance/rigid_planning/rigid_planner.h"

namespace needle_guidance::procedures {
namespace {

using geometry::Point2;

constexpr double kSameSeed_m = 1e-9;  // the live samples and the verification: the same FEM steps

/// The robot and the tissue in process: moves are streamed to the tissue in 0.05 mm samples (the
/// live loop's, not the planner's); a fault can be injected before the n-th device call.
class SimDevices : public RigidImplantDevices {
public:
  explicit SimDevices(const scene::Scene& scene)
      : planner_(scene, unbudgeted()),
        sim_(planner_.makeSimulation(scene.targets.front().position)) {}

  static rigid_planning::PlannerOptions unbudgeted() {
    rigid_planning::PlannerOptions o;
    o.time_budget_s = 0.0;
    return o;
  }
  bool hasPlanner() const override { return true; }
  bool hasTissue() const override { return true; }
  PlanResult plan(const Point3& target) override {
    ++calls_;
    const rigid_planning::RigidPlan p = planner_.plan(Point2(target.x(), target.y()));
    PlanResult r;
    r.ok = static_cast<bool>(p);
    r.refused = !p && p.code != rigid_planning::PlanCode::kSimulationFailed;
    r.message = p.message;
    r.release = Point3(p.release.x(), p.release.y(), 0.0);
    r.predicted_error_m = p.predicted_error_m;
    r.verified_error_m = p.verified_error_m;
    r.plan_s = p.seconds;
    verified_.push_back(p.verified_error_m);
    return r;
  }
  MoveResult moveHeight(double height_m, double /*velocity_m_s*/) override {
    ++calls_;
    height_ = height_m;
    return done(height_m, 0.01);
  }
  MoveResult moveDepth(double depth_m, double velocity_m_s, double from_m, bool) override {
    ++calls_;
    const double direction = depth_m >= from_m ? 1.0 : -1.0;
    for (double x = from_m; direction * (depth_m - x) > 0.0;) {
      x = direction > 0.0 ? std::min(depth_m, x + 5e-5) : std::max(depth_m, x - 5e-5);
      if (!sim_->advance(0.005, height_, x)) {
        return MoveResult{};
      }
    }
    depth_ = depth_m;
    return done(depth_m, velocity_m_s);
  }
  std::optional<Point3> tip() override { return Point3(depth_, height_, 0.0); }
  std::optional<int> implantSeed(std::string& why_not) override {
    ++calls_;
    return sim_->implantSeed(&why_not);
  }
  std::optional<Point3> seedAtRest(int id) override {
    const Point2 p = sim_->seedPosition(sim_->seeds().at(static_cast<std::size_t>(id)));
    return Point3(p.x(), p.y(), 0.0);
  }
  void resetTissue() override { sim_->reset(); }
  std::optional<Fault> fault() override {
    if (fault_at_call_ > 0 && calls_ >= fault_at_call_) {
      return Fault{"/tissue_sim", 1.5, "no answer to getPid"};
    }
    return std::nullopt;
  }
  std::string safeStop(double retract_depth_m, double velocity_m_s) override {
    safe_stops_++;
    moveDepth(retract_depth_m, velocity_m_s, depth_, true);
    return "needle retracted";
  }
  double now_s() const override { return 0.0; }

  int fault_at_call_ = 0;
  int safe_stops_ = 0;
  std::vector<double> verified_;

private:
  MoveResult done(double reached, double velocity) {
    MoveResult r;
    r.ok = true;
    r.reached_m = reached;
    r.duration_s = 1.0;
    r.mean_velocity_m_s = velocity;
    r.state = "SUCCEEDED";
    return r;
  }
  rigid_planning::RigidPlanner planner_;
  std::unique_ptr<tissue::TissueSimulation> sim_;
  double height_ = 0.03, depth_ = -0.005;
  int calls_ = 0;
};

scene::Scene twoTargets() {
  scene::Scene scene = scene::defaultScene("prostate_sagittal");
  scene.targets.resize(2);
  return scene;
}

TEST(RigidImplantProcedure, TheMeasuredSeedErrorIsThePlannersVerifiedError) {
  const scene::Scene scene = twoTargets();
  SimDevices devices(scene);
  const RigidImplantReport report =
      RigidImplantProcedure(scene, RigidImplantSettings{}).run(devices);
  ASSERT_EQ(report.records.size(), 2U);
  for (std::size_t i = 0; i < report.records.size(); ++i) {
    const TargetRecord& r = report.records[i];
    SCOPED_TRACE(r.name);
    EXPECT_EQ(r.status, "ok");
    EXPECT_NEAR(r.seedError_m(), devices.verified_.at(i), kSameSeed_m);
    EXPECT_EQ(r.outcome, r.seedError_m() <= scene.needle.placement_tolerance_m
                             ? TargetOutcome::kPlaced
                             : TargetOutcome::kMissed);
  }
  EXPECT_FALSE(report.fault);
  EXPECT_EQ(report.success(), report.count(TargetOutcome::kPlaced) == 2);
}

TEST(RigidImplantProcedure, ARefusedTargetHasAReasonAndNoErrorFigures) {
  scene::Scene scene = twoTargets();
  scene.targets.resize(1);
  scene.targets.front().name = "beyond_reach";
  scene.targets.front().position = Point2(scene.needle.max_depth_m + 1e-3, 0.03);
  SimDevices devices(scene);
  const RigidImplantReport report =
      RigidImplantProcedure(scene, RigidImplantSettings{}).run(devices);
  ASSERT_EQ(report.records.size(), 1U);
  EXPECT_EQ(report.records[0].outcome, TargetOutcome::kRefused);
  EXPECT_NE(report.records[0].reason.find("max depth"), std::string::npos)
      << report.records[0].reason;
  EXPECT_FALSE(std::isfinite(report.records[0].seedError_m()));
  EXPECT_FALSE(report.success());
  EXPECT_NE(report.summaryJson().find("\"refused\": 1"), std::string::npos);
  EXPECT_EQ(report.summaryJson().find("1e+09"), std::string::npos);
}

TEST(RigidImplantProcedure, AFaultStopsTheRobotAndTheReportCountsOnlyTargetsTried) {
  const scene::Scene scene = twoTargets();
  SimDevices devices(scene);
  devices.fault_at_call_ = 6;  // target 1: plan, height, insert, implant, retract; target 2: plan
  const RigidImplantReport report =
      RigidImplantProcedure(scene, RigidImplantSettings{}).run(devices);
  ASSERT_TRUE(report.fault);
  EXPECT_EQ(report.fault->node, "/tissue_sim");
  EXPECT_EQ(devices.safe_stops_, 1);
  EXPECT_EQ(report.safe_stop, "needle retracted");
  ASSERT_EQ(report.records.size(), 2U);  // the second target was tried, not finished
  EXPECT_EQ(report.records[1].outcome, TargetOutcome::kError);
  EXPECT_NE(report.records[1].status.find("/tissue_sim died"), std::string::npos)
      << report.records[1].status;
  EXPECT_FALSE(report.success());
  const std::string json = report.summaryJson();
  EXPECT_NE(json.find("\"targets_tried\": 2"), std::string::npos) << json;
  EXPECT_NE(json.find("\"node\": \"/tissue_sim\""), std::string::npos) << json;
}

TEST(RigidImplantProcedure, WritesTheFullReportWithAPlot) {
  const scene::Scene scene = twoTargets();
  SimDevices devices(scene);
  RigidImplantSettings settings;
  settings.max_targets = 1;
  const RigidImplantReport report = RigidImplantProcedure(scene, settings).run(devices);
  const std::string dir = ::testing::TempDir() + "/rigid_implant_report_test";
  std::filesystem::remove_all(dir);
  report.write(dir);
  for (const char* file : {"moves.csv", "summary.json", "summary.md", "seed_errors.png"}) {
    EXPECT_GT(std::filesystem::file_size(dir + "/" + file), 100U) << file;
  }
}

TEST(RigidImplantProcedure, BadSettingsAreRefused) {
  RigidImplantSettings settings;
  settings.retract_depth_m = 0.01;  // inside the tissue
  EXPECT_THROW(RigidImplantProcedure(twoTargets(), settings), std::invalid_argument);
  settings = RigidImplantSettings{};
  settings.insertion_velocity_m_s = NAN;
  EXPECT_THROW(RigidImplantProcedure(twoTargets(), settings), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::procedures

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
