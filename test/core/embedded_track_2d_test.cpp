// The 2-D embedded-track insertion (fem::EmbeddedNeedle<2> through TissueSimulation): the
// mesh never changes, the seed lands at the tip's tissue point, events do not depend on the
// step, bad commands and a needle meeting bone are refused with the state unchanged, and a copy
// continues bit for bit.
#include <gtest/gtest.h>

#include <algorithm>
#include <string>

#include "needle_guidance/fem/embedded_needle.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace needle_guidance::tissue {
namespace {

constexpr double kRounding_m = 1e-9;      // the same state, rounding apart
constexpr double kConvergedTol_m = 5e-6;  // the bench's step-halving target
constexpr double kOnNeedleTol_m = 1e-9;   // constrained tissue points sit on the needle
constexpr double kTipForceTol_N = 1e-6;   // the cut holds the tip force at f_b

/// Inserts from where the needle is to depth on the depth grid at height h (every stride-th grid
/// point), implants, retracts and returns the seed.
Point2 implant(TissueSimulation& sim, double h, double depth, long stride = 1) {
  for (long k = std::max(sim.gridPosition(), 0L) + stride; sim.gridDepth(k) <= depth + 1e-12;
       k += stride) {
    EXPECT_TRUE(sim.step(0.01, h, sim.gridDepth(k)));
  }
  const std::optional<int> id = sim.implantSeed();
  EXPECT_TRUE(id.has_value());
  EXPECT_TRUE(sim.step(0.5, h, -0.001));
  return sim.seedPosition(sim.seeds().at(static_cast<std::size_t>(*id)));
}

TEST(EmbeddedTrack2d, IsTheDefaultOfAQuasiStaticLinearScene) {
  scene::Scene scene = scene::defaultScene("prostate_sagittal");
  EXPECT_EQ(optionsFromScene(scene).needle_model, NeedleModel::kEmbeddedTrack);
  scene.models.corotational = true;
  EXPECT_EQ(optionsFromScene(scene).needle_model, NeedleModel::kNodeMoving);
  TissueSimOptions bad = optionsFromScene(scene::defaultScene("prostate_sagittal"));
  bad.integrator = IntegratorKind::kNewmark;
  EXPECT_THROW(TissueSimulation(scene::defaultScene("prostate_sagittal"), bad),
               std::invalid_argument);
}

TEST(EmbeddedTrack2d, CutsAtTheCuttingForceAndKeepsTheShaftOnTheNeedle) {
  const scene::Scene scene = scene::defaultScene("prostate_sagittal");
  TissueSimulation sim(scene);
  const double h = 0.030;
  for (long k = 0; sim.gridDepth(k) <= 0.030 + 1e-12; ++k) {
    ASSERT_TRUE(sim.advance(0.01, h, sim.gridDepth(k)));
  }
  ASSERT_TRUE(sim.needleInTissue());
  EXPECT_NEAR(sim.lastStep().tip_force_N, scene.needle.cutting_force_N, kTipForceTol_N);
  const std::optional<Point2> tip = sim.tipReference();
  ASSERT_TRUE(tip.has_value());
  EXPECT_NEAR(tip->y(), h, kOnNeedleTol_m) << "the cut track is the reference line y = h";
  EXPECT_LT(tip->x(), sim.tipX()) << "the tissue ahead of the tip is compressed";
  // One shaft point per track spacing of cut, each held on the needle axis.
  EXPECT_GE(sim.shaftCount(), 20);
  for (const Point2& p : sim.shaftReference()) {
    EXPECT_NEAR(sim.trackNeedle().worldOf(p).y(), h, kOnNeedleTol_m);
  }
  EXPECT_EQ(sim.mesh().nodes, sim.initialMesh().nodes) << "the embedded track never moves a node";
}

TEST(EmbeddedTrack2d, TheSeedDoesNotDependOnTheStepAndRestsAtTheTipsTissuePoint) {
  const scene::Scene scene = scene::defaultScene("prostate_sagittal");
  TissueSimulation fine(scene), coarse(scene);
  const double h = 0.027, depth = 0.036;
  const Point2 a = implant(fine, h, depth);
  const Point2 b = implant(coarse, h, depth, 20);  // 2 mm steps
  EXPECT_LT((a - b).norm(), kConvergedTol_m);
  // After full retraction the linear tissue is at rest: the seed is the tip's tissue point.
  EXPECT_NEAR(a.y(), h, kRounding_m);
  EXPECT_NEAR((a - fine.seeds().front().p_ref).norm(), 0.0, kRounding_m);
}

TEST(EmbeddedTrack2d, BadCommandsAreRefusedAndLeaveTheStateUnchanged) {
  const scene::Scene scene = scene::defaultScene("prostate_sagittal");
  TissueSimulation sim(scene);
  const double h = 0.030;
  ASSERT_TRUE(sim.advance(0.01, h, 0.020));
  const Point2 tip = *sim.tipReference();
  const double tip_x = sim.tipX();
  const int shaft = sim.shaftCount();
  EXPECT_FALSE(sim.step(0.01, h + 0.001, 0.021)) << "height change in tissue";
  EXPECT_FALSE(sim.step(0.01, h, std::nan(""))) << "non-finite";
  EXPECT_FALSE(sim.step(0.0, h, 0.021)) << "dt <= 0";
  const StepStatus beyond = sim.step(0.01, h, scene.workspace_max.x() + 0.001);
  EXPECT_FALSE(beyond);
  EXPECT_NE(beyond.toString().find("beyond the tissue"), std::string::npos) << beyond.toString();
  EXPECT_EQ(*sim.tipReference(), tip);
  EXPECT_EQ(sim.shaftCount(), shaft);
  EXPECT_EQ(sim.tipX(), tip_x);
}

TEST(EmbeddedTrack2d, ANeedleMeetingBoneIsRefusedWithItsPositionAndTheStateUnchanged) {
  scene::Scene scene = scene::defaultScene("prostate_sagittal");
  scene.regions.push_back(
      {"bone_block", scene.materials.front().name,
       geometry::Polygon({{0.050, 0.025}, {0.054, 0.025}, {0.054, 0.035}, {0.050, 0.035}}), true});
  scene.targets.clear();
  TissueSimulation sim(scene);
  const double h = 0.030;
  ASSERT_TRUE(sim.advance(0.01, h, 0.045));
  const Point2 tip = *sim.tipReference();
  const double tip_x = sim.tipX();
  const StepStatus status = sim.step(0.01, h, 0.057);
  EXPECT_FALSE(status);
  EXPECT_NE(status.toString().find("rigid tissue"), std::string::npos) << status.toString();
  EXPECT_EQ(*sim.tipReference(), tip);
  EXPECT_EQ(sim.tipX(), tip_x);
}

TEST(EmbeddedTrack2d, ACopyContinuesBitForBitAndResetStartsAfresh) {
  const scene::Scene scene = scene::defaultScene("prostate_sagittal");
  TissueSimulation sim(scene);
  const double h = 0.029;
  ASSERT_TRUE(sim.advance(0.01, h, 0.015));
  TissueSimulation copy(sim);
  const Point2 from_copy = implant(copy, h, 0.034);
  const Point2 from_original = implant(sim, h, 0.034);
  EXPECT_EQ(from_copy, from_original);
  sim.reset();
  EXPECT_TRUE(sim.seeds().empty());
  EXPECT_FALSE(sim.needleInTissue());
  TissueSimulation fresh(scene);
  EXPECT_EQ(implant(sim, h, 0.034), implant(fresh, h, 0.034));
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
