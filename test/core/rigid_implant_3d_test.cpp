// RigidImplantProcedure in 3-D tissue with in-process devices: the 3-D offset planner, and a
// tissue that follows the robot in its own samples (not the planner's steps) on the same mesh.
// Every reachable seed is placed and lands where the planner's verification put it; the
// target inside the bone is refused as unreachable and the run succeeds; the lateral axis
// moved to the plan's z.
#include <gtest/gtest.h>

#include <cmath>

#include "needle_guidance/procedures/rigid_implant.h"
#include "needle_guidance/tissue_3d/offset_planner_3d.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace needle_guidance::procedures {
namespace {

using tissue_3d::NeedleInsertion3;
using tissue_3d::TissueScene3d;

constexpr double kRobotSample_m = 3.7e-4;  // the live loop's samples, unrelated to needle.step
constexpr double kSameSeed_m = 1e-6;       // located events: the sampling does not enter
constexpr double kTolerance_m = 1e-4;      // the 3-D planner's placement tolerance

class Sim3Devices : public RigidImplantDevices {
public:
  explicit Sim3Devices(const TissueScene3d& scene)
      : scene_(scene),
        model_(tissue_3d::meshTissue3d(scene, {}), scene.materialTable()),
        planner_(scene, model_) {
    resetTissue();
  }
  bool hasPlanner() const override { return true; }
  bool hasTissue() const override { return true; }
  PlanResult plan(const Point3& target) override {
    const tissue_3d::PlanResult3 p = planner_.plan({"t", target});
    PlanResult r;
    r.ok = p.placed;
    r.refused = !p.placed;
    r.unreachable = p.unreachable;
    r.message = p.placed ? "ok" : p.refusal;
    r.release = Point3(p.tip_x_m, p.lateral_m.x(), p.lateral_m.y());
    r.verified_error_m = p.verified_error_m >= 0.0 ? p.verified_error_m : NAN;
    verified_.push_back(p.verified_error_m);
    return r;
  }
  MoveResult moveHeight(double height_m, double velocity_m_s) override {
    lateral_.x() = height_m;
    return follow(depth_, velocity_m_s);
  }
  MoveResult moveLateral(double lateral_m, double velocity_m_s) override {
    lateral_.y() = lateral_m;
    lateral_moves_++;
    return follow(depth_, velocity_m_s);
  }
  MoveResult moveDepth(double depth_m, double velocity_m_s, double from_m, bool) override {
    const double direction = depth_m >= from_m ? 1.0 : -1.0;
    for (double x = from_m; direction * (depth_m - x) > 0.0;) {
      x = direction > 0.0 ? std::min(depth_m, x + kRobotSample_m)
                          : std::max(depth_m, x - kRobotSample_m);
      if (!needle_->moveTo(lateral_, x)) {
        return MoveResult{};
      }
    }
    depth_ = depth_m;
    return follow(depth_m, velocity_m_s);
  }
  std::optional<Point3> tip() override { return Point3(depth_, lateral_.x(), lateral_.y()); }
  std::optional<int> implantSeed(std::string& why_not) override {
    return needle_->implantSeed(&why_not);
  }
  std::optional<Point3> seedAtRest(int id) override { return needle_->seedWorld(id); }
  void resetTissue() override {
    needle_ = std::make_unique<NeedleInsertion3>(model_, scene_.needle, scene_.block_min_m.x(),
                                                 scene_.workspace.max_tip_x_m);
  }
  std::optional<Fault> fault() override { return std::nullopt; }
  std::string safeStop(double, double) override { return "none needed"; }
  double now_s() const override { return 0.0; }

  std::vector<double> verified_;
  int lateral_moves_ = 0;

private:
  MoveResult follow(double reached, double velocity) {
    MoveResult r;
    r.ok = needle_->moveTo(lateral_, depth_);
    r.reached_m = reached;
    r.duration_s = 1.0;
    r.mean_velocity_m_s = velocity;
    r.state = r.ok ? "SUCCEEDED" : "ABORTED";
    return r;
  }
  const TissueScene3d& scene_;
  tissue_3d::TissueModel3 model_;
  tissue_3d::OffsetPlanner3 planner_;
  std::unique_ptr<NeedleInsertion3> needle_;
  Eigen::Vector2d lateral_ = Eigen::Vector2d::Zero();
  double depth_ = -0.005;
};

TEST(RigidImplantProcedure3d, ReachableSeedsPlacedWhereVerifiedAndBoneTargetUnreachable) {
  const TissueScene3d scene =
      tissue_3d::loadTissueScene3d(std::string(NG_SOURCE_DIR) + "/test/data/tissue_3d_small.yaml");
  std::vector<ImplantTarget> targets;
  for (const auto& t : scene.targets) {
    targets.push_back({t.name, t.position_m});
  }
  RigidImplantSettings settings;
  settings.lateral_stage = true;
  settings.placement_tolerance_m = kTolerance_m;
  Sim3Devices devices(scene);
  const RigidImplantReport report =
      RigidImplantProcedure(scene.name, targets, scene.block_min_m.x(), settings).run(devices);
  ASSERT_EQ(report.records.size(), 3U);
  for (std::size_t i = 0; i < report.records.size(); ++i) {
    const TargetRecord& r = report.records[i];
    SCOPED_TRACE(r.name);
    if (r.name == "in_bone") {
      EXPECT_EQ(r.outcome, TargetOutcome::kRefused);
      EXPECT_TRUE(r.plan.unreachable);
      EXPECT_NE(r.reason.find("inside fixed region 'bone'"), std::string::npos) << r.reason;
      EXPECT_FALSE(std::isfinite(r.seedError_m()));
      continue;
    }
    EXPECT_EQ(r.status, "ok");
    EXPECT_EQ(r.outcome, TargetOutcome::kPlaced);
    EXPECT_LE(r.seedError_m(), kTolerance_m);
    EXPECT_NEAR(r.seedError_m(), devices.verified_.at(i), kSameSeed_m);
  }
  EXPECT_EQ(devices.lateral_moves_, 2);
  EXPECT_EQ(report.unreachableCount(), 1);
  EXPECT_TRUE(report.success());
  const std::string json = report.summaryJson();
  EXPECT_NE(json.find("\"refused_unreachable\": 1"), std::string::npos) << json;
  EXPECT_NE(json.find("\"lateral_stage\": true"), std::string::npos) << json;
}

}  // namespace
}  // namespace needle_guidance::procedures

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
