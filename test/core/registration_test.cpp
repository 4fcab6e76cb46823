// Tests of deformable registration with tissue-parameter estimation (dissertation 3.2-3.3):
// polygon Dice, the synthetic case generator, both optimisers against the targets, the
// baselines, and the hard cases (refusals with a status, never NaN or a throw).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>

#include "needle_guidance/registration/baselines.h"
#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/dice.h"
#include "needle_guidance/registration/probe_case.h"
#include "needle_guidance/registration/registration_request.h"

namespace needle_guidance::registration {
namespace {

constexpr std::uint64_t kSeed = 3;
constexpr double kDiceExactTol = 1e-12;           // exact polygon arithmetic [fraction]
constexpr double kTargetDice = 0.975;             // issue target (fraction)
constexpr double kTargetPointError_m = 0.001;     // issue target [m]
constexpr double kTargetSeconds = 1.0;            // issue target per slice [s]
constexpr double kRoundTripTol_m = 1e-9;          // T^-1(T(x)) = x [m]
constexpr double kZeroDisplacementTol_m = 1e-12;  // identical slices [m]
constexpr double kMm = 1e-3;

Polygon square(double x0, double y0, double side) {
  return Polygon({{x0, y0}, {x0 + side, y0}, {x0 + side, y0 + side}, {x0, y0 + side}});
}

const ProbeCase& balloonCase() {
  static const ProbeCase pc = generateProbeCase(ProbeType::kBalloon, kSeed);
  return pc;
}
const ProbeCase& rigidCase() {
  static const ProbeCase pc = generateProbeCase(ProbeType::kRigid, kSeed);
  return pc;
}

void expectNoMapping(const RegistrationResult& r) {
  EXPECT_FALSE(hasMapping(r.status));
  EXPECT_FALSE(r.message.empty());
  EXPECT_EQ(r.mapping, nullptr);
  EXPECT_FALSE(r.forward(Point2::Zero()).has_value());
  EXPECT_TRUE(std::isfinite(r.dice));
}

// ---- Dice on polygons -------------------------------------------------------------------------

TEST(RegistrationDice, OverlapOfSquaresIsExact) {
  const Loops a = toLoops(square(0, 0, 2)), b = toLoops(square(1, 1, 2));
  EXPECT_NEAR(intersectionArea(a, b), 1.0, kDiceExactTol);
  EXPECT_NEAR(diceSimilarity(a, b), 2.0 * 1.0 / 8.0, kDiceExactTol);
  EXPECT_NEAR(diceSimilarity(a, toLoops(square(5, 5, 1))), 0.0, kDiceExactTol);
}

TEST(RegistrationDice, IdenticalAndSubdividedOutlinesGiveOne) {
  const Loops a = toLoops(square(0, 0, 1));
  EXPECT_NEAR(diceSimilarity(a, a), 1.0, kDiceExactTol);
  // The same square with extra collinear vertices (as a mesh boundary has).
  const Loops b{{{0, 0}, {0.5, 0}, {1, 0}, {1, 0.3}, {1, 1}, {0, 1}}};
  EXPECT_NEAR(diceSimilarity(a, b), 1.0, kDiceExactTol);
}

TEST(RegistrationDice, HoleLoopIsSubtracted) {
  Loops ring = toLoops(square(0, 0, 4));
  std::vector<Point2> hole = toLoops(square(1, 1, 2))[0];
  std::reverse(hole.begin(), hole.end());  // clockwise = hole
  ring.push_back(hole);
  EXPECT_NEAR(loopsArea(ring), 12.0, kDiceExactTol);
  EXPECT_NEAR(intersectionArea(ring, toLoops(square(0, 0, 4))), 12.0, kDiceExactTol);
}

// ---- Case generator ---------------------------------------------------------------------------

TEST(RegistrationCases, DeterministicWithKnownTruthOnAFinerMesh) {
  const ProbeCase a = generateProbeCase(ProbeType::kBalloon, 7);
  const ProbeCase b = generateProbeCase(ProbeType::kBalloon, 7);
  ASSERT_EQ(a.test_points_in.size(), b.test_points_in.size());
  for (std::size_t i = 0; i < a.test_points_in.size(); ++i)
    EXPECT_EQ(a.test_points_in[i], b.test_points_in[i]);
  EXPECT_EQ(a.probe_in.prostate.outer.vertices(), b.probe_in.prostate.outer.vertices());
  EXPECT_TRUE(checkSegmentation(a.probe_out, a.probe_in).ok);
  EXPECT_GE(a.truth.forward_mesh_nodes,
            3 * RegistrationOptions{}.target_nodes);  // not the registration mesh
  EXPECT_GE(a.truth.cg_modulus_Pa, 40e3);
  EXPECT_LE(a.truth.cg_modulus_Pa, 90e3);
  // The probe moves the gland: test points are displaced by more than the target error.
  EXPECT_GT(meanPointError(TranslationMapping(Point2::Zero()), a), kTargetPointError_m);
}

// ---- FEM registration -------------------------------------------------------------------------

void checkFastRegistration(const ProbeCase& pc) {
  const RegistrationResult r = registerSlices(pc.probe_out, pc.probe_in);
  std::cout << toString(pc.type) << ": " << r.message << ", " << r.seconds << " s\n";
  ASSERT_TRUE(hasMapping(r.status)) << r.message;
  EXPECT_GE(r.dice, kTargetDice);
  EXPECT_GT(r.dice, r.initial_dice);
  const double error = meanPointError(*r.mapping, pc);
  EXPECT_LE(error, kTargetPointError_m);
  EXPECT_LE(r.seconds, kTargetSeconds);
  EXPECT_NEAR(r.modulus_Pa[kSurrounding], 30e3, 0.0);  // the reference class is fixed
  EXPECT_NEAR(static_cast<double>(r.mesh.nodes.size()), 500.0, 100.0);
  // Better than the rigid centre-of-mass baseline (3.3.5).
  const BaselineResult rigid = rigidCentreOfMass(pc.probe_out, pc.probe_in);
  EXPECT_GT(r.dice, rigid.dice);
  EXPECT_LT(error, meanPointError(*rigid.mapping, pc));
  // T^-1(T(x)) = x inside the gland; outside the model: nullopt, not NaN.
  for (const Point2& p : pc.test_points_out) {
    const auto y = r.forward(p);
    ASSERT_TRUE(y.has_value());
    const auto x = r.inverse(*y);
    ASSERT_TRUE(x.has_value());
    EXPECT_NEAR((*x - p).norm(), 0.0, kRoundTripTol_m);
  }
  EXPECT_FALSE(r.forward(Point2(1.0, 1.0)).has_value());
  const Point2 lumen =
      0.5 * (pc.probe_out.rectum.outer.minCorner() + pc.probe_out.rectum.outer.maxCorner());
  EXPECT_FALSE(r.forward(lumen).has_value());  // the rectum lumen is not tissue
  // Warped MRSI grid (3.3.3): 7 mm grid over the probe-in prostate, mapped by T^-1.
  ASSERT_GT(r.mrsi_grid.rows * r.mrsi_grid.cols, 4);
  EXPECT_NEAR((r.mrsi_grid.probe_in[1] - r.mrsi_grid.probe_in[0]).norm(), 0.007, 1e-12);
  for (std::size_t g = 0; g < r.mrsi_grid.probe_in.size(); ++g) {
    if (r.mrsi_grid.inside_prostate[g]) {
      EXPECT_TRUE(r.mrsi_grid.probe_out[g].has_value());
    }
  }
  for (const auto& rec : r.trace)
    EXPECT_TRUE(std::isfinite(rec.q));
}

TEST(RegistrationFem, FastOptimizerMeetsTargetsOnBalloonCase) {
  checkFastRegistration(balloonCase());
}
TEST(RegistrationFem, FastOptimizerMeetsTargetsOnRigidCase) {
  checkFastRegistration(rigidCase());
}

TEST(RegistrationFem, SteepestDescentWithArmijoIncreasesQ) {
  const ProbeCase& pc = rigidCase();
  RegistrationOptions options;
  options.optimizer = Optimizer::kSteepestDescent;
  options.max_iterations = 25;
  const RegistrationResult r = registerSlices(pc.probe_out, pc.probe_in, options);
  std::cout << "steepest descent: " << r.message << ", " << r.seconds << " s\n";
  ASSERT_TRUE(hasMapping(r.status)) << r.message;
  ASSERT_GE(r.trace.size(), 2u);
  for (std::size_t i = 1; i < r.trace.size(); ++i)
    EXPECT_GT(r.trace[i].q, r.trace[i - 1].q);  // Armijo: every step improves Q
  EXPECT_GE(r.dice, kTargetDice);
  EXPECT_LE(meanPointError(*r.mapping, pc), kTargetPointError_m);
}

TEST(RegistrationFem, OnlyStiffnessRatiosAreIdentifiable) {
  // All boundary conditions are displacements: doubling every modulus (and the force scale)
  // changes nothing but the absolute moduli.
  const ProbeCase& pc = rigidCase();
  RegistrationOptions a, b;
  b.initial_modulus_Pa = {60e3, 120e3, 60e3};
  const RegistrationResult ra = registerSlices(pc.probe_out, pc.probe_in, a);
  const RegistrationResult rb = registerSlices(pc.probe_out, pc.probe_in, b);
  ASSERT_TRUE(hasMapping(ra.status) && hasMapping(rb.status));
  EXPECT_NEAR(ra.dice, rb.dice, 1e-6);
  EXPECT_NEAR(rb.modulus_Pa[kCentralGland] / rb.modulus_Pa[kSurrounding],
              ra.modulus_Pa[kCentralGland] / ra.modulus_Pa[kSurrounding],
              1e-3 * ra.modulus_Pa[kCentralGland] / 30e3);
}

// ---- Baselines --------------------------------------------------------------------------------

TEST(RegistrationBaselines, RigidAndIntensityBaselinesAreWorseOnPointError) {
  const ProbeCase& pc = balloonCase();
  const RegistrationResult fem = registerSlices(pc.probe_out, pc.probe_in);
  ASSERT_TRUE(hasMapping(fem.status));
  const double fem_error = meanPointError(*fem.mapping, pc);
  const BaselineResult rigid = rigidCentreOfMass(pc.probe_out, pc.probe_in);
  ASSERT_TRUE(hasMapping(rigid.status));
  const SyntheticImagePair images = renderProbeImages(pc);
  const BaselineResult demons =
      intensityRegistration(images, prostateLoops(pc.probe_out), pc.probe_in.prostate.outer);
  ASSERT_TRUE(hasMapping(demons.status)) << demons.message;
  const double rigid_error = meanPointError(*rigid.mapping, pc),
               demons_error = meanPointError(*demons.mapping, pc);
  std::cout << "point error [mm]: fem " << fem_error * 1e3 << ", rigid " << rigid_error * 1e3
            << ", demons " << demons_error * 1e3 << "; Dice [%]: fem " << fem.dice * 100
            << ", rigid " << rigid.dice * 100 << ", demons " << demons.dice * 100 << "\n";
  EXPECT_LT(fem_error, rigid_error);
  EXPECT_LT(fem_error, demons_error);
  EXPECT_LT(demons_error,
            meanPointError(TranslationMapping(Point2::Zero()), pc));  // demons does register
  if (intensityMethodAvailable(IntensityMethod::kDisOpticalFlow)) {
    const BaselineResult dis =
        intensityRegistration(images, prostateLoops(pc.probe_out), pc.probe_in.prostate.outer,
                              IntensityMethod::kDisOpticalFlow);
    ASSERT_TRUE(hasMapping(dis.status)) << dis.message;
    std::cout << "point error [mm]: DIS optical flow " << meanPointError(*dis.mapping, pc) * 1e3
              << "\n";
    EXPECT_LT(fem_error, meanPointError(*dis.mapping, pc));
  } else {
    EXPECT_EQ(intensityRegistration(images, prostateLoops(pc.probe_out), pc.probe_in.prostate.outer,
                                    IntensityMethod::kDisOpticalFlow)
                  .status,
              RegistrationStatus::kUnavailable);
  }
}

// ---- Hard cases -------------------------------------------------------------------------------

TEST(RegistrationHardCases, ProbeThatDoesNotEncloseTheRectumIsRefused) {
  const ProbeCase& pc = balloonCase();
  ProbeInSegmentation moved = pc.probe_in;
  std::vector<Point2> v = moved.probe.outer.vertices();
  for (Point2& p : v)
    p += Point2(0.0, -0.03);  // 30 mm posterior: misses the rectum
  moved.probe = Polygon(v);
  const RegistrationResult r = registerSlices(pc.probe_out, moved);
  EXPECT_EQ(r.status, RegistrationStatus::kProbeDoesNotEncloseRectum) << r.message;
  expectNoMapping(r);
  // Partly outside (rectum wall 3 mm outside the probe): refused too.
  v = pc.probe_in.probe.outer.vertices();
  const double drop_m =
      pc.probe_in.probe.outer.maxCorner().y() - pc.probe_out.rectum.outer.maxCorner().y() + 0.003;
  for (Point2& p : v)
    p.y() -= drop_m;  // the probe's top 3 mm below the rectum's top
  moved.probe = Polygon(v);
  const RegistrationResult partly = registerSlices(pc.probe_out, moved);
  EXPECT_EQ(partly.status, RegistrationStatus::kProbeDoesNotEncloseRectum) << partly.message;
}

TEST(RegistrationHardCases, SegmentationWithHoleOrSelfIntersectionIsRefused) {
  const ProbeCase& pc = balloonCase();
  SliceSegmentation with_hole = pc.probe_out;
  with_hole.cg.holes.push_back(square(-0.002, 0.004, 0.002));  // an inner ring in the CG
  RegistrationResult r = registerSlices(with_hole, pc.probe_in);
  EXPECT_EQ(r.status, RegistrationStatus::kInvalidSegmentation);
  EXPECT_NE(r.message.find("cg"), std::string::npos) << r.message;
  expectNoMapping(r);

  ProbeInSegmentation bow_tie = pc.probe_in;  // self-intersecting probe-in prostate
  bow_tie.prostate = Polygon({{-0.01, -0.01}, {0.01, 0.01}, {0.01, -0.01}, {-0.01, 0.01}});
  r = registerSlices(pc.probe_out, bow_tie);
  EXPECT_EQ(r.status, RegistrationStatus::kInvalidSegmentation);
  EXPECT_NE(r.message.find("not simple"), std::string::npos) << r.message;
  expectNoMapping(r);
  EXPECT_EQ(rigidCentreOfMass(pc.probe_out, bow_tie).status,
            RegistrationStatus::kInvalidSegmentation);

  SliceSegmentation overlapping = pc.probe_out;  // PZ overlapping the CG
  overlapping.pz = Polygon(overlapping.cg.outer);
  r = registerSlices(overlapping, pc.probe_in);
  EXPECT_EQ(r.status, RegistrationStatus::kInvalidSegmentation) << r.message;
}

TEST(RegistrationHardCases, IdenticalSlicesTerminateImmediatelyWithZeroDisplacement) {
  const ProbeCase& pc = rigidCase();
  ProbeInSegmentation same;
  same.prostate = Polygon(prostateLoops(pc.probe_out).at(0));
  same.probe = pc.probe_out.rectum.outer;  // "probe" = the rectum itself: no displacement
  for (Optimizer optimizer : {Optimizer::kFast, Optimizer::kSteepestDescent}) {
    RegistrationOptions options;
    options.optimizer = optimizer;
    const RegistrationResult r = registerSlices(pc.probe_out, same, options);
    EXPECT_EQ(r.status, RegistrationStatus::kAlreadyAligned) << r.message;
    EXPECT_EQ(r.iterations, 0);
    EXPECT_NEAR(r.dice, 1.0, 1e-9);
    double max_u = 0.0;
    for (const Point2& u : r.displacement_m)
      max_u = std::max(max_u, u.norm());
    EXPECT_LE(max_u, kZeroDisplacementTol_m);
    EXPECT_EQ(r.modulus_Pa, options.initial_modulus_Pa);
  }
}

TEST(RegistrationHardCases, StiffnessBoundsAreReportedAndClampedExactly) {
  // A gland 5,000 times stiffer than its surroundings: the estimate runs into Y_max = 600 kPa.
  ProbeCaseOptions case_options;
  case_options.surrounding_modulus_range_Pa = {10e3, 10e3};
  case_options.cg_modulus_range_Pa = {50e6, 50e6};
  case_options.pz_modulus_range_Pa = {50e6, 50e6};
  const ProbeCase pc = generateProbeCase(ProbeType::kBalloon, kSeed, case_options);
  const RegistrationResult r = registerSlices(pc.probe_out, pc.probe_in);
  std::cout << "bounded: " << r.message << "\n";
  EXPECT_EQ(r.status, RegistrationStatus::kConvergedAtBound) << r.message;
  EXPECT_TRUE(r.modulus_at_bound[kCentralGland]);
  EXPECT_EQ(r.modulus_Pa[kCentralGland], 600e3);  // exactly the bound
  for (int c = 0; c < kSoftClassCount; ++c) {
    EXPECT_GE(r.modulus_Pa[static_cast<std::size_t>(c)], 1e3);
    EXPECT_LE(r.modulus_Pa[static_cast<std::size_t>(c)], 600e3);
  }
  EXPECT_TRUE(std::isfinite(r.dice));
}

TEST(RegistrationHardCases, InvalidOptionsThrow) {
  const ProbeCase& pc = rigidCase();
  RegistrationOptions options;
  options.target_nodes = 5;
  EXPECT_THROW(registerSlices(pc.probe_out, pc.probe_in, options), std::invalid_argument);
}

TEST(RegistrationRequests, BadFieldsAreRefusedByName) {
  const auto refused = [](RegistrationRequest r) {
    r.synthetic_seed = kSeed;
    const Result<RegistrationAnswer> a = runRegistration(r, RegistrationOptions());
    EXPECT_FALSE(a);
    EXPECT_EQ(a.status().code(), StatusCode::kRefused);
    return a.status().message();
  };
  RegistrationRequest r;
  r.optimizer = "newton";
  EXPECT_NE(refused(r).find("optimizer 'newton'"), std::string::npos);
  r = {};
  r.alpha = NAN;
  EXPECT_NE(refused(r).find("alpha is not finite"), std::string::npos);
  r = {};
  r.target_nodes = 10;
  EXPECT_NE(refused(r).find("target_nodes 10"), std::string::npos);
  r = {};
  r.probe_type = "cone";
  EXPECT_NE(refused(r).find("probe_type 'cone'"), std::string::npos);
  // Empty slices are a data problem: answered with a refusal status and no mapping.
  const Result<RegistrationAnswer> empty = runRegistration({}, RegistrationOptions());
  ASSERT_TRUE(empty) << empty.status().message();
  expectNoMapping(empty.value().result);
  EXPECT_TRUE(std::isnan(empty.value().point_error_m));
}

TEST(RegistrationRequests, SyntheticCaseIsMeasuredAgainstItsTruthAndTheBaselines) {
  RegistrationRequest r;
  r.synthetic_seed = kSeed;
  r.probe_type = "balloon";
  const Result<RegistrationAnswer> a = runRegistration(r, RegistrationOptions());
  ASSERT_TRUE(a) << a.status().message();
  ASSERT_TRUE(hasMapping(a.value().result.status)) << a.value().result.message;
  EXPECT_LT(a.value().point_error_m, kTargetPointError_m);
  EXPECT_LT(a.value().point_error_m, a.value().rigid_point_error_m);
  EXPECT_LT(a.value().rigid_point_error_m, a.value().unregistered_point_error_m);
}

}  // namespace
}  // namespace needle_guidance::registration

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
