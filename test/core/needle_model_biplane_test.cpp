// Tests for biplane tip triangulation (biplane_3d.h): exact fusion, the covariance against the
// closed form, the estimate's consistency over seeded noisy views, the gate's false-alarm rate,
// and the hard case: views that disagree are gated, not fused.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "needle_guidance/needle_model/biplane_3d.h"

namespace needle_guidance::needle_model {
namespace {

constexpr double kExactTol_m = 1e-12;
constexpr double kVarianceTol_m2 = 1e-18;
constexpr int kSamples = 20000;

ViewDetection view(ViewAxis axis, const Vector3& p, double sigma_x, double sigma_other) {
  ViewDetection v;
  v.axis = axis;
  v.p_m = Eigen::Vector2d(p.x(), axis == ViewAxis::kAlongZ ? p.y() : p.z());
  v.covariance_m2 = Eigen::Vector2d(sigma_x * sigma_x, sigma_other * sigma_other).asDiagonal();
  return v;
}

TEST(Biplane3d, ConsistentViewsFuseExactlyWithTheClosedFormCovariance) {
  const Vector3 p(0.031, -0.012, 0.007);
  const double sa = 2e-4, sb = 3e-4, so = 1e-4;
  const auto r =
      triangulateBiplane(view(ViewAxis::kAlongZ, p, sa, so), view(ViewAxis::kAlongY, p, sb, so));
  ASSERT_TRUE(r) << r.status().toString();
  EXPECT_NEAR((r.value().p_SceneTip - p).norm(), 0.0, kExactTol_m);
  // x is seen twice: 1 / (1/sa^2 + 1/sb^2); y and z once.
  EXPECT_NEAR(r.value().covariance_m2(0, 0), 1.0 / (1.0 / (sa * sa) + 1.0 / (sb * sb)),
              kVarianceTol_m2);
  EXPECT_NEAR(r.value().covariance_m2(1, 1), so * so, kVarianceTol_m2);
  EXPECT_NEAR(r.value().covariance_m2(2, 2), so * so, kVarianceTol_m2);
  EXPECT_NEAR(r.value().chi_square, 0.0, 1e-12);
}

TEST(Biplane3d, NoisyViewsAreConsistentWithTheirCovarianceAndRarelyGated) {
  std::mt19937_64 rng(42);
  std::normal_distribution<double> n(0.0, 1.0);
  const Vector3 p(0.05, 0.01, -0.02);
  const double sx = 3e-4, so = 2e-4;
  double nees = 0.0;
  int gated = 0;
  for (int i = 0; i < kSamples; ++i) {
    ViewDetection a = view(ViewAxis::kAlongZ, p, sx, so);
    ViewDetection b = view(ViewAxis::kAlongY, p, sx, so);
    a.p_m += Eigen::Vector2d(sx * n(rng), so * n(rng));
    b.p_m += Eigen::Vector2d(sx * n(rng), so * n(rng));
    const auto r = triangulateBiplane(a, b);
    if (!r) {
      ++gated;
      continue;
    }
    const Vector3 e = r.value().p_SceneTip - p;
    nees += e.dot(r.value().covariance_m2.inverse() * e);
  }
  // Normalised estimation error squared: chi-square with 3 degrees of freedom, mean 3; its
  // sample mean's standard error is sqrt(6 / N) = 0.017, so 0.1 is six of them.
  EXPECT_NEAR(nees / (kSamples - gated), 3.0, 0.1);
  // The gate's false alarms: 0.1 % expected (20 of 20,000); 0.3 % is far in the tail.
  EXPECT_LT(gated, kSamples * 3 / 1000);
}

TEST(Biplane3d, DisagreeingViewsAreGatedNotFused) {
  const Vector3 p(0.05, 0.01, -0.02);
  ViewDetection a = view(ViewAxis::kAlongZ, p, 2e-4, 2e-4);
  ViewDetection b = view(ViewAxis::kAlongY, p, 2e-4, 2e-4);
  b.p_m.x() += 3e-3;  // 3 mm apart along the shared axis: ~10.6 sigma of the difference
  const auto r = triangulateBiplane(a, b);
  ASSERT_FALSE(r);
  EXPECT_EQ(r.status().code(), BiplaneCode::kDisagree);
  EXPECT_NE(r.status().toString().find("not fused"), std::string::npos);
}

TEST(Biplane3d, BadInputIsRefused) {
  const Vector3 p(0.05, 0.01, -0.02);
  const ViewDetection a = view(ViewAxis::kAlongZ, p, 2e-4, 2e-4);
  EXPECT_EQ(triangulateBiplane(a, a).status().code(), BiplaneCode::kBadInput);
  ViewDetection b = view(ViewAxis::kAlongY, p, 2e-4, 2e-4);
  b.covariance_m2(1, 1) = -1.0;
  EXPECT_EQ(triangulateBiplane(a, b).status().code(), BiplaneCode::kBadInput);
  b = view(ViewAxis::kAlongY, p, 2e-4, 2e-4);
  b.p_m.y() = std::nan("");
  EXPECT_EQ(triangulateBiplane(a, b).status().code(), BiplaneCode::kBadInput);
}

TEST(BiplaneObserver3d, CleanViewsRecoverPositionAndTangentAndKeepThePredictedBevel) {
  BiplaneImaging3 imaging;
  imaging.sigma_position_m = 1e-5;
  imaging.sigma_heading_rad = 1e-4;
  imaging.dropout = 0.0;
  imaging.outlier = 0.0;
  BiplaneObserver3 observer(imaging, 5);
  const TipPose3 truth =
      makeTipPose(Vector3(0.04, 0.01, -0.005), Vector3(1.0, 0.2, -0.1), Vector3::UnitY());
  const TipPose3 predicted = rotateBevel(truth, 0.3);  // the views cannot see the roll
  constexpr double kPositionTol_m = 1e-4;              // 10 sigma of one view's noise
  constexpr double kTangentTol_rad = 2e-3;             // 20 sigma of the heading noise
  for (int i = 0; i < 50; ++i) {
    const auto seen = observer.observe(truth, predicted);
    ASSERT_TRUE(seen) << seen.status().toString();
    EXPECT_LT((seen.value().p_SceneTip - truth.p_SceneTip).norm(), kPositionTol_m);
    EXPECT_LT(std::acos(std::min(1.0, seen.value().tangent().dot(truth.tangent()))),
              kTangentTol_rad);
    EXPECT_GT(seen.value().bevel().dot(predicted.bevel()), 0.999);
  }
}

TEST(BiplaneObserver3d, DroppedViewsAndFalseDetectionsAreNotFused) {
  const TipPose3 truth = makeTipPose(Vector3(0.04, 0.01, 0.0), Vector3::UnitX(), Vector3::UnitY());
  BiplaneImaging3 imaging;
  imaging.dropout = 1.0;
  BiplaneObserver3 blind(imaging, 5);
  EXPECT_EQ(blind.observe(truth, truth).status().code(), BiplaneCode::kNoDetection);
  // Every view a false tip 20 mm off in a random direction: the shared x disagrees by more than
  // the gate's 3.3 sigma (0.93 mm at 0.2 mm per view) unless both offsets nearly share their x.
  imaging.dropout = 0.0;
  imaging.outlier = 1.0;
  imaging.outlier_offset_m = 0.02;
  BiplaneObserver3 fooled(imaging, 5);
  int gated = 0;
  constexpr int kCalls = 200;
  for (int i = 0; i < kCalls; ++i) {
    gated += fooled.observe(truth, truth).status().code() == BiplaneCode::kDisagree ? 1 : 0;
  }
  EXPECT_GE(gated, kCalls * 9 / 10);
  imaging.outlier = 1.5;
  EXPECT_THROW(BiplaneObserver3(imaging, 5), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::needle_model

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
