// Image geometry, synthetic reference image and the piecewise-affine warp (dissertation 2.3.7).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/image_warp.h"

namespace needle_guidance::tissue {
namespace {

constexpr double kRoundTripTol_m = 1e-12;
constexpr double kRoundTripTol_px = 1e-9;
constexpr std::uint32_t kSeed = 7;
constexpr std::uint32_t kOtherSeed = 8;
constexpr double kPixelSize_m = 2e-4;  // the prostate scene's 0.2 mm
// OpenCV's per-triangle warpAffine interpolates in 1/32 pixel fixed point.
constexpr double kOpenCvIdentityTol_grey = 1.0;
// Whole-image cv::warpAffine vs the exact piecewise-affine warp: OpenCV's 1/32 pixel fixed
// point costs up to ~gradient / 64, i.e. a few grey levels on speckle (measured: max 4, mean 0.42).
constexpr double kAffineMaxTol_grey = 6.0;
constexpr double kAffineMeanTol_grey = 0.6;
// Two double-precision bilinear evaluations can only round differently near k + 0.5.
constexpr double kRoundingTol_grey = 1.0;
constexpr int kAffineMargin_px = 2;          // compare pixels at least this far inside the mesh
constexpr double kCapsuleMargin_m = 1.5e-3;  // keep the bright capsule out of the region means
constexpr double kProstateToFatMaxRatio = 0.7;

scene::Scene prostateScene() {
  return scene::defaultScene("prostate_sagittal");
}

geometry::TriangleMesh sceneMesh(const scene::Scene& scene) {
  const std::vector<geometry::MeshRegion> regions = scene.meshRegions();
  geometry::MeshingOptions options;
  options.max_edge_m = scene.mesh.max_edge_m;
  options.min_edge_m = scene.mesh.min_edge_m;
  options.grading_length_m = scene.mesh.grading_length_m;
  options.min_angle_deg = scene.mesh.min_angle_deg;
  if (scene.mesh.refine_targets) {
    for (const auto& t : scene.targets) {
      options.refine_points.push_back(t.position);
    }
  }
  return geometry::meshDomain(scene.workspacePolygon(), scene.background_material, regions,
                              options);
}

// Two triangles covering a 1 cm square with corner at the origin.
geometry::TriangleMesh unitSquareMesh() {
  geometry::TriangleMesh mesh;
  mesh.nodes = {{0.0, 0.0}, {0.01, 0.0}, {0.01, 0.01}, {0.0, 0.01}};
  mesh.triangles = {{0, 1, 2}, {0, 2, 3}};
  mesh.triangle_region = {0, 0};
  mesh.region_names = {"background"};
  return mesh;
}

// u of a uniform affine map p -> p0 + A (p - p0) + t of all nodes [m].
Eigen::VectorXd affineDisplacement(const geometry::TriangleMesh& mesh, const Eigen::Matrix2d& A,
                                   const Point2& p0, const Point2& t_m) {
  Eigen::VectorXd u(2 * mesh.nodeCount());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    const Point2& p = mesh.nodes[i];
    u.segment<2>(2 * i) = p0 + A * (p - p0) + t_m - p;
  }
  return u;
}

double maxAbsDiff(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask = cv::Mat()) {
  cv::Mat diff;
  cv::absdiff(a, b, diff);
  double max_diff = 0.0;
  cv::minMaxLoc(diff, nullptr, &max_diff, nullptr, nullptr, mask);
  return max_diff;
}

// The default prostate mesh (1,259 triangles), meshed once for all tests.
const geometry::TriangleMesh& prostateMesh() {
  static const geometry::TriangleMesh mesh = sceneMesh(prostateScene());
  return mesh;
}

class ImageWarpTest : public ::testing::Test {
protected:
  ImageWarpTest()
      : scene_(prostateScene()),
        mesh_(&prostateMesh()),
        g_(forWorkspace(scene_, kPixelSize_m)),
        reference_(syntheticUltrasound(scene_, g_, kSeed)) {}

  scene::Scene scene_;
  const geometry::TriangleMesh* mesh_;  // not owned
  ImageGeometry g_;
  cv::Mat reference_;
};

TEST(ImageGeometryTest, WorkspaceGeometryAndRoundTrip) {
  const scene::Scene scene = prostateScene();
  const ImageGeometry g = forWorkspace(scene, kPixelSize_m);
  EXPECT_EQ(g.cols, 300);
  EXPECT_EQ(g.rows, 300);
  // Row 0 is the top (max y): the workspace's top-left corner is the outer corner of pixel (0, 0).
  const cv::Point2d top_left = g.toPixel({scene.workspace_min.x(), scene.workspace_max.y()});
  EXPECT_NEAR(top_left.x, -0.5, kRoundTripTol_px);
  EXPECT_NEAR(top_left.y, -0.5, kRoundTripTol_px);
  const cv::Point2d bottom_right = g.toPixel({scene.workspace_max.x(), scene.workspace_min.y()});
  EXPECT_NEAR(bottom_right.x, g.cols - 0.5, kRoundTripTol_px);
  EXPECT_NEAR(bottom_right.y, g.rows - 0.5, kRoundTripTol_px);
  EXPECT_GT(g.toScene({0.0, 0.0}).y(), g.toScene({0.0, 10.0}).y());  // +y up

  std::mt19937 rng(kSeed);
  std::uniform_real_distribution<double> coordinate_m(-0.01, 0.07);
  for (int i = 0; i < 1000; ++i) {
    const Point2 p(coordinate_m(rng), coordinate_m(rng));
    EXPECT_NEAR((g.toScene(g.toPixel(p)) - p).norm(), 0.0, kRoundTripTol_m);
    const cv::Point2d q = g.toPixel(p);
    const cv::Point2d q_back = g.toPixel(g.toScene(q));
    EXPECT_NEAR(std::hypot(q_back.x - q.x, q_back.y - q.y), 0.0, kRoundTripTol_px);
  }
  EXPECT_THROW(forWorkspace(scene, 0.0), std::invalid_argument);
  EXPECT_THROW(forWorkspace(scene, std::numeric_limits<double>::quiet_NaN()),
               std::invalid_argument);
  // A size that is not a whole number of pixels rounds up.
  EXPECT_EQ(forWorkspace(scene, 7e-4).cols, 86);  // 60 / 0.7 = 85.7
}

TEST(SyntheticUltrasoundTest, DeterministicForASeed) {
  const scene::Scene scene = prostateScene();
  const ImageGeometry g = forWorkspace(scene, kPixelSize_m);
  const cv::Mat a = syntheticUltrasound(scene, g, kSeed);
  const cv::Mat b = syntheticUltrasound(scene, g, kSeed);
  const cv::Mat c = syntheticUltrasound(scene, g, kOtherSeed);
  ASSERT_EQ(a.type(), CV_8UC1);
  ASSERT_EQ(a.size(), g.size());
  EXPECT_EQ(cv::countNonZero(a != b), 0);
  EXPECT_GT(cv::countNonZero(a != c), a.rows * a.cols / 2);
}

TEST(SyntheticUltrasoundTest, ProstateIsDarkerThanFat) {
  const scene::Scene scene = prostateScene();
  const ImageGeometry g = forWorkspace(scene, kPixelSize_m);
  const cv::Mat image = syntheticUltrasound(scene, g, kSeed);
  const geometry::Polygon& prostate = scene.regions.at(0).polygon;
  double prostate_sum = 0.0, fat_sum = 0.0;
  int prostate_n = 0, fat_n = 0;
  for (int r = 0; r < g.rows; ++r) {
    for (int c = 0; c < g.cols; ++c) {
      const Point2 p = g.toScene(cv::Point2d(c, r));
      if (prostate.distanceToBoundary(p) < kCapsuleMargin_m) {
        continue;
      }
      if (prostate.contains(p)) {
        prostate_sum += image.at<uchar>(r, c);
        ++prostate_n;
      } else {
        fat_sum += image.at<uchar>(r, c);
        ++fat_n;
      }
    }
  }
  ASSERT_GT(prostate_n, 1000);
  ASSERT_GT(fat_n, 1000);
  const double prostate_mean = prostate_sum / prostate_n, fat_mean = fat_sum / fat_n;
  EXPECT_LT(prostate_mean, kProstateToFatMaxRatio * fat_mean)
      << "prostate " << prostate_mean << ", fat " << fat_mean;
}

TEST(ReferenceImageTest, LoadsAndResizesOrThrowsNamingThePath) {
  scene::Scene scene = prostateScene();
  const ImageGeometry g = forWorkspace(scene, kPixelSize_m);
  // No file: the synthetic image.
  EXPECT_EQ(
      cv::countNonZero(referenceImage(scene, g, kSeed) != syntheticUltrasound(scene, g, kSeed)), 0);

  const std::string missing = "/nonexistent_dir/us_reference.png";
  scene.imaging.reference_image = missing;
  try {
    referenceImage(scene, g, kSeed);
    FAIL() << "a missing reference image was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find(missing), std::string::npos) << e.what();
  }

  // A file of another size is resized to g.
  const std::string path = ::testing::TempDir() + "image_warp_test_reference.png";
  cv::Mat small(150, 120, CV_8UC1, cv::Scalar(90));
  ASSERT_TRUE(cv::imwrite(path, small));
  scene.imaging.reference_image = path;
  const cv::Mat loaded = referenceImage(scene, g, kSeed);
  EXPECT_EQ(loaded.type(), CV_8UC1);
  EXPECT_EQ(loaded.size(), g.size());
  EXPECT_EQ(cv::countNonZero(loaded != 90), 0);
}

TEST_F(ImageWarpTest, ZeroDisplacementReproducesTheReferenceExactly) {
  const Eigen::VectorXd u = Eigen::VectorXd::Zero(2 * mesh_->nodeCount());
  const cv::Mat warped = warpImage(reference_, g_, *mesh_, u);
  ASSERT_EQ(warped.type(), CV_8UC1);
  ASSERT_EQ(warped.size(), g_.size());
  // The mesh covers the workspace, hence every pixel centre.
  EXPECT_EQ(cv::countNonZero(warped != reference_), 0);

  const cv::Mat warped_cv = warpImage(reference_, g_, *mesh_, u, WarpMethod::kOpenCvAffine);
  EXPECT_LE(maxAbsDiff(warped_cv, reference_), kOpenCvIdentityTol_grey);
}

TEST_F(ImageWarpTest, WholePixelTranslationShiftsTheImage) {
  constexpr int kShiftCols_px = 5;  // +x: to the right
  constexpr int kShiftUp_px = 4;    // +y: up, towards row 0
  const Eigen::VectorXd u =
      affineDisplacement(*mesh_, Eigen::Matrix2d::Identity(), Point2::Zero(),
                         Point2(kShiftCols_px * kPixelSize_m, kShiftUp_px * kPixelSize_m));
  for (WarpMethod method : {WarpMethod::kBarycentricScan, WarpMethod::kOpenCvAffine}) {
    const cv::Mat warped = warpImage(reference_, g_, *mesh_, u, method);
    const cv::Rect dst(kShiftCols_px, 0, g_.cols - kShiftCols_px, g_.rows - kShiftUp_px);
    const cv::Rect src(0, kShiftUp_px, g_.cols - kShiftCols_px, g_.rows - kShiftUp_px);
    const double tol_grey = method == WarpMethod::kBarycentricScan ? 0.0 : kOpenCvIdentityTol_grey;
    EXPECT_LE(maxAbsDiff(warped(dst), reference_(src)), tol_grey) << int(method);
    if (method == WarpMethod::kBarycentricScan) {
      // The strips the mesh moved away from are black.
      EXPECT_EQ(cv::countNonZero(warped(cv::Rect(0, 0, kShiftCols_px, g_.rows))), 0);
      EXPECT_EQ(cv::countNonZero(warped(cv::Rect(0, g_.rows - kShiftUp_px, g_.cols, kShiftUp_px))),
                0);
    }
  }
}

TEST_F(ImageWarpTest, UniformAffineStretchMatchesWarpAffine) {
  Eigen::Matrix2d A;
  A << 1.08, 0.05, -0.03, 0.93;  // stretch in x, squeeze in y, shear [scene frame]
  const Point2 p0(0.03, 0.03);
  const Point2 t_m(0.5e-3, -0.3e-3);
  const Eigen::VectorXd u = affineDisplacement(*mesh_, A, p0, t_m);
  const cv::Mat warped = warpImage(reference_, g_, *mesh_, u);

  // The same map in pixel coordinates: y flips, so q' = q0 + F A F (q - q0) + F t / s.
  const cv::Point2d q0 = g_.toPixel(p0);
  cv::Matx22d A_px(A(0, 0), -A(0, 1), -A(1, 0), A(1, 1));
  const cv::Vec2d t_px(t_m.x() / kPixelSize_m, -t_m.y() / kPixelSize_m);
  const cv::Vec2d q0_vec(q0.x, q0.y);
  const cv::Vec2d offset = q0_vec - A_px * q0_vec + t_px;
  const cv::Matx23d forward(A_px(0, 0), A_px(0, 1), offset[0], A_px(1, 0), A_px(1, 1), offset[1]);
  cv::Mat expected;
  cv::warpAffine(reference_, expected, cv::Mat(forward), g_.size(), cv::INTER_LINEAR,
                 cv::BORDER_CONSTANT, cv::Scalar(0));

  // Compare where the source position lies at least kAffineMargin_px inside the reference.
  cv::Matx23d inverse;
  cv::invertAffineTransform(forward, inverse);
  cv::Mat mask(g_.size(), CV_8U, cv::Scalar(0));
  for (int r = 0; r < g_.rows; ++r) {
    for (int c = 0; c < g_.cols; ++c) {
      const cv::Vec3d q(c, r, 1.0);
      const cv::Vec2d s = inverse * q;
      if (s[0] >= kAffineMargin_px && s[0] <= g_.cols - 1 - kAffineMargin_px &&
          s[1] >= kAffineMargin_px && s[1] <= g_.rows - 1 - kAffineMargin_px) {
        mask.at<uchar>(r, c) = 255;
      }
    }
  }
  ASSERT_GT(cv::countNonZero(mask), g_.rows * g_.cols / 2);
  cv::Mat diff;
  cv::absdiff(warped, expected, diff);
  EXPECT_LE(maxAbsDiff(warped, expected, mask), kAffineMaxTol_grey);
  EXPECT_LE(cv::mean(diff, mask)[0], kAffineMeanTol_grey);
  // Against a double-precision bilinear sample at the inverse-mapped position (no fixed point):
  // only the rounding of a value near k + 0.5 can differ.
  cv::Mat exact(g_.size(), CV_8U, cv::Scalar(0));
  for (int r = 0; r < g_.rows; ++r) {
    for (int c = 0; c < g_.cols; ++c) {
      const cv::Vec2d s = inverse * cv::Vec3d(c, r, 1.0);
      const int x0 = std::clamp(static_cast<int>(std::floor(s[0])), 0, g_.cols - 2);
      const int y0 = std::clamp(static_cast<int>(std::floor(s[1])), 0, g_.rows - 2);
      const double fx = s[0] - x0, fy = s[1] - y0;
      auto at = [&](int y, int x) { return static_cast<double>(reference_.at<uchar>(y, x)); };
      const double v = (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) +
                       fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1));
      exact.at<uchar>(r, c) = cv::saturate_cast<uchar>(v);
    }
  }
  EXPECT_LE(maxAbsDiff(warped, exact, mask), kRoundingTol_grey);
  // Outside the deformed mesh the warp is black.
  cv::Mat outside(g_.size(), CV_8U, cv::Scalar(0));
  for (int r = 0; r < g_.rows; ++r) {
    for (int c = 0; c < g_.cols; ++c) {
      const cv::Vec2d s = inverse * cv::Vec3d(c, r, 1.0);
      if (s[0] < -1.0 || s[0] > g_.cols || s[1] < -1.0 || s[1] > g_.rows) {
        outside.at<uchar>(r, c) = 255;
      }
    }
  }
  ASSERT_GT(cv::countNonZero(outside), 0);
  cv::Mat warped_outside;
  warped.copyTo(warped_outside, outside);
  EXPECT_EQ(cv::countNonZero(warped_outside), 0);
}

TEST_F(ImageWarpTest, BadDisplacementThrowsNamingTheDof) {
  const geometry::TriangleMesh square = unitSquareMesh();
  const ImageGeometry g{Point2(0.0, 0.01), 1e-3, 10, 10};
  const cv::Mat reference(10, 10, CV_8UC1, cv::Scalar(100));
  EXPECT_THROW(warpImage(reference, g, square, Eigen::VectorXd::Zero(7)), std::invalid_argument);
  EXPECT_THROW(warpImage(reference, g, square, Eigen::VectorXd::Zero(9)), std::invalid_argument);
  Eigen::VectorXd u = Eigen::VectorXd::Zero(8);
  u[5] = std::numeric_limits<double>::quiet_NaN();
  try {
    warpImage(reference, g, square, u);
    FAIL() << "a NaN displacement was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("u[5] (node 2, y)"), std::string::npos) << e.what();
  }
  u[5] = std::numeric_limits<double>::infinity();
  EXPECT_THROW(warpImage(reference, g, square, u), std::invalid_argument);
  u[5] = 0.0;
  EXPECT_THROW(warpImage(cv::Mat(9, 10, CV_8UC1), g, square, u), std::invalid_argument);
  EXPECT_THROW(warpImage(cv::Mat(10, 10, CV_8UC3), g, square, u), std::invalid_argument);
  // The valid call covers the whole 10 x 10 image.
  EXPECT_EQ(cv::countNonZero(warpImage(reference, g, square, u) != 100), 0);
}

TEST_F(ImageWarpTest, TrianglesOffTheImageAreClippedAndInvertedOnesDrawn) {
  const geometry::TriangleMesh square = unitSquareMesh();
  const ImageGeometry g{Point2(0.0, 0.01), 1e-3, 10, 10};
  const cv::Mat reference(10, 10, CV_8UC1, cv::Scalar(100));
  for (WarpMethod method : {WarpMethod::kBarycentricScan, WarpMethod::kOpenCvAffine}) {
    // Far away (1 km): nothing is drawn, nothing overflows.
    const Eigen::VectorXd far =
        affineDisplacement(square, Eigen::Matrix2d::Identity(), Point2::Zero(), Point2(1e3, -1e3));
    EXPECT_EQ(cv::countNonZero(warpImage(reference, g, square, far, method)), 0) << int(method);
    // Mirrored in x (both triangles inverted) about the square's centre: still covers it.
    const Eigen::VectorXd mirror = affineDisplacement(
        square, Eigen::Vector2d(-1.0, 1.0).asDiagonal(), Point2(0.005, 0.005), Point2::Zero());
    EXPECT_EQ(cv::countNonZero(warpImage(reference, g, square, mirror, method) != 100), 0)
        << int(method);
  }
}

TEST_F(ImageWarpTest, NeedleLikePushMovesThePictureAndWritesIt) {
  // A needle-like push: tissue near the insertion height y = 3 cm is dragged in +x, decaying
  // towards the fixed faces, with some compression in y.
  const double w_m = 0.006, amp_x_m = 3e-3, amp_y_m = 1e-3, side_m = 0.06;
  Eigen::VectorXd u(2 * mesh_->nodeCount());
  for (std::size_t i = 0; i < mesh_->nodeCount(); ++i) {
    const Point2& p = mesh_->nodes[i];
    const double fall_off = std::exp(-std::pow((p.y() - 0.03) / w_m, 2) / 2.0);
    const double sx = std::sin(M_PI * p.x() / side_m), sy = std::sin(M_PI * p.y() / side_m);
    u[2 * i] = amp_x_m * fall_off * sx;
    u[2 * i + 1] = -amp_y_m * sx * std::sin(2.0 * M_PI * p.y() / side_m) * sy;
  }
  // Speed is measured by `scripts/bench tissue`, not asserted here.
  const cv::Mat warped = warpImage(reference_, g_, *mesh_, u);
  // The deformation moved pixels.
  EXPECT_GT(cv::countNonZero(warped != reference_), g_.rows * g_.cols / 20);

  // reference | warped | warped with the deformed mesh, for a human to look at.
  cv::Mat warped_bgr, lines;
  cv::cvtColor(warped, warped_bgr, cv::COLOR_GRAY2BGR);
  lines = warped_bgr.clone();
  for (const auto& tri : mesh_->triangles) {
    std::vector<cv::Point> polygon;
    for (int n : tri) {
      const cv::Point2d q = g_.toPixel(mesh_->nodes[n] + Point2(u[2 * n], u[2 * n + 1]));
      polygon.emplace_back(static_cast<int>(std::lround(q.x * 16)),
                           static_cast<int>(std::lround(q.y * 16)));
    }
    cv::polylines(lines, polygon, true, cv::Scalar(0, 200, 255), 1, cv::LINE_AA, 4);
  }
  cv::Mat overlay, reference_bgr, panel;
  cv::addWeighted(warped_bgr, 0.4, lines, 0.6, 0.0, overlay);
  cv::cvtColor(reference_, reference_bgr, cv::COLOR_GRAY2BGR);
  cv::hconcat(std::vector<cv::Mat>{reference_bgr, warped_bgr, overlay}, panel);
  const std::string path = ::testing::TempDir() + "image_warp_deformed.png";
  ASSERT_TRUE(cv::imwrite(path, panel));
  std::cout << "wrote " << path << "\n";
}

}  // namespace
}  // namespace needle_guidance::tissue

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
