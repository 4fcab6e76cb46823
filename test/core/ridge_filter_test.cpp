// The Hessian ridge filter shared by the tip detector and the acquisition (ridge_filter.h): a
// bright line is a ridge along its direction, a blob of the same contrast scores less, a dark
// line and a flat image score nothing, and bad input is refused.
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <stdexcept>

#include "../../src/imaging/ridge_filter.h"

namespace det = needle_guidance::imaging::detail;

namespace {

constexpr double kSigma_px = 2.0;
constexpr double kAngleTolerance_rad = 5.0 * CV_PI / 180.0;  ///< line direction (3 x 3 Sobel)

/// A 3 px wide line at `angle_rad` through the centre of a 200 x 200 image of level 50, 100
/// grey levels brighter (darker when `dark`).
cv::Mat lineImage(double angle_rad, bool dark = false) {
  cv::Mat img(200, 200, CV_32F, cv::Scalar(50.0F));
  const cv::Point2d c(100, 100), d(std::cos(angle_rad), std::sin(angle_rad));
  cv::line(img, c - 90.0 * d, c + 90.0 * d, cv::Scalar(dark ? 0.0 : 150.0), 3, cv::LINE_AA);
  return img;
}

}  // namespace

TEST(RidgeFilter, BrightLineIsARidgeAlongItsDirection) {
  for (const double angle : {0.0, 0.4, -1.1, 1.5}) {
    const det::HessianRidge h =
        det::hessianRidge(lineImage(angle), kSigma_px, 1.0, cv::BORDER_REPLICATE);
    double peak = 0.0;
    cv::Point at;
    cv::minMaxLoc(h.strength, nullptr, &peak, nullptr, &at);
    EXPECT_GT(peak, 0.0) << angle;
    // The strongest response lies on the line, and the direction there is the line's.
    const cv::Point2d d(std::cos(angle), std::sin(angle)), n(-d.y, d.x);
    EXPECT_LT(std::abs((cv::Point2d(at) - cv::Point2d(100, 100)).dot(n)), 2.0) << angle;
    double da = std::abs(h.direction(100, 100) - angle);
    da = std::min(da, CV_PI - da);
    EXPECT_LT(da, kAngleTolerance_rad) << angle;
    EXPECT_LT(h.lambda_across.at<float>(100, 100), 0.0F) << angle;
  }
}

TEST(RidgeFilter, BlobScoresLessThanALineOfTheSameContrastAndDarkLinesNothing) {
  cv::Mat blob(200, 200, CV_32F, cv::Scalar(50.0F));
  cv::circle(blob, cv::Point(100, 100), 2, cv::Scalar(150.0), cv::FILLED, cv::LINE_AA);
  const det::HessianRidge line = det::hessianRidge(lineImage(0.3), kSigma_px, 1.0, 4);
  const det::HessianRidge spot = det::hessianRidge(blob, kSigma_px, 1.0, 4);
  double line_peak = 0.0, spot_peak = 0.0;
  cv::minMaxLoc(line.strength, nullptr, &line_peak);
  cv::minMaxLoc(spot.strength, nullptr, &spot_peak);
  EXPECT_LT(spot_peak, 0.5 * line_peak);
  const det::HessianRidge dark = det::hessianRidge(lineImage(0.3, true), kSigma_px, 1.0, 4);
  EXPECT_EQ(dark.strength.at<float>(100, 100), 0.0F);
  const det::HessianRidge flat =
      det::hessianRidge(cv::Mat(50, 50, CV_32F, cv::Scalar(7.0F)), kSigma_px, 1.0, 4);
  EXPECT_EQ(cv::countNonZero(flat.strength), 0);
}

TEST(RidgeFilter, BadInputIsRefused) {
  const cv::Mat bytes(20, 20, CV_8U, cv::Scalar(1));
  EXPECT_THROW(det::hessianRidge(bytes, kSigma_px, 1.0, 4), std::invalid_argument);
  const cv::Mat img(20, 20, CV_32F, cv::Scalar(1.0F));
  EXPECT_THROW(det::hessianRidge(img, 0.0, 1.0, 4), std::invalid_argument);
  EXPECT_THROW(det::hessianRidge(img, std::nan(""), 1.0, 4), std::invalid_argument);
  EXPECT_THROW(det::hessianRidge(img, kSigma_px, -1.0, 4), std::invalid_argument);
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
