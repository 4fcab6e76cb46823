// The imaging region of a B-mode frame; see imaging_region.h.
#include "needle_guidance/imaging/imaging_region.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <vector>

namespace needle_guidance::imaging {
namespace {

/// Step 1: grey levels at or below this are the scanner's black outside the image (a lossy
/// recording's ringing stays under it; speckle inside the image, even of water, rarely does in
/// every frame of a sequence).
constexpr int kBlackLevel = 4;
/// Step 1: closing of the bright pixels (speckle's dark gaps inside the image) [px].
constexpr int kCloseKernel_px = 9;
/// Step 1: blobs under this share of the largest one are text or markers, not image.
constexpr double kKeepShare = 0.05;
/// Step 2: a hull covering this share of the frame is the whole frame; one covering less than
/// kMinFraction is no image region (a black or nearly black frame): the whole frame is used.
constexpr double kWholeFrame = 0.97;
constexpr double kMinFraction = 0.1;
/// Step 2: a hull edge is a side edge when steeper than this to the rows (a fan's half angle
/// stays under 60 degrees), and vertical when its slope |dx / dy| is under kVerticalSlope.
constexpr double kSideMinSlope = 0.5;  // |dy / dx|
constexpr double kVerticalSlope = 0.03;
/// Step 2: the probe face's arc (probeFace): seeded three-column circles tried, the tolerance
/// of a column on the circle, the columns (every second one) that make a face, the least rise
/// across them that makes it an arc, and the largest radius, in hull widths, worth trying.
constexpr int kFaceTrials = 200;
constexpr double kFaceTolerance_px = 3.0;
constexpr int kFaceMinColumns = 30;
constexpr double kFaceMinSag_px = 12.0;
constexpr double kFaceMaxRadius = 3.0;

struct SideEdges {
  cv::Point2d left_a, left_b, right_a, right_b;
  bool found = false;
};

/// The longest side edge of the hull on each side of its centre.
SideEdges sideEdges(const std::vector<cv::Point>& hull, double centre_x) {
  SideEdges s;
  double best_left = 0.0, best_right = 0.0;
  for (std::size_t i = 0; i < hull.size(); ++i) {
    const cv::Point2d a = hull[i], b = hull[(i + 1) % hull.size()];
    const cv::Point2d d = b - a;
    if (std::abs(d.y) < kSideMinSlope * std::abs(d.x))
      continue;
    const double length = cv::norm(d);
    const bool left = 0.5 * (a.x + b.x) < centre_x;
    if (left && length > best_left)
      best_left = length, s.left_a = a, s.left_b = b;
    if (!left && length > best_right)
      best_right = length, s.right_a = a, s.right_b = b;
  }
  s.found = best_left > 0.0 && best_right > 0.0;
  return s;
}

/// Step 1: the kept bright pixels (CV_8U, 255).
cv::Mat brightBlobs(const cv::Mat& grey8) {
  cv::Mat bright = grey8 > kBlackLevel;
  cv::morphologyEx(bright, bright, cv::MORPH_CLOSE,
                   cv::getStructuringElement(cv::MORPH_RECT, {kCloseKernel_px, kCloseKernel_px}));
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(bright, labels, stats, centroids, 8, CV_32S);
  int largest = 0;
  for (int i = 1; i < n; ++i)
    largest = std::max(largest, stats.at<int>(i, cv::CC_STAT_AREA));
  std::vector<std::uint8_t> keep(static_cast<std::size_t>(n), 0);
  for (int i = 1; i < n; ++i)
    keep[static_cast<std::size_t>(i)] = stats.at<int>(i, cv::CC_STAT_AREA) >= kKeepShare * largest;
  cv::Mat kept(grey8.size(), CV_8U, cv::Scalar(0));
  for (int r = 0; r < labels.rows; ++r) {
    const int* l = labels.ptr<int>(r);
    std::uint8_t* k = kept.ptr<std::uint8_t>(r);
    for (int c = 0; c < labels.cols; ++c)
      k[c] = keep[static_cast<std::size_t>(l[c])] ? 255 : 0;
  }
  return kept;
}

/// The circle through three points; false when they are (nearly) in line.
bool circleThrough(cv::Point2d a, cv::Point2d b, cv::Point2d c, cv::Point2d* centre,
                   double* radius) {
  const double d = 2.0 * (a.x * (b.y - c.y) + b.x * (c.y - a.y) + c.x * (a.y - b.y));
  if (std::abs(d) < 1e-6)
    return false;
  const double a2 = a.dot(a), b2 = b.dot(b), c2 = c.dot(c);
  *centre = cv::Point2d((a2 * (b.y - c.y) + b2 * (c.y - a.y) + c2 * (a.y - b.y)) / d,
                        (a2 * (c.x - b.x) + b2 * (a.x - c.x) + c2 * (b.x - a.x)) / d);
  *radius = cv::norm(a - *centre);
  return true;
}

/// Step 2: the probe face's arc. Per column inside the hull, the first bright row; the circle
/// through three of them (kFaceTrials seeded draws) with the most columns within
/// kFaceTolerance_px of it, its centre above the image (a column dark under the face, anechoic
/// or shadowed, or one on the sector's straight edge, is no face column). The face is curved
/// when at least kFaceMinColumns columns lie on that circle and it rises more than
/// kFaceMinSag_px across them (a linear probe's face is straight: the hull's top edge).
bool probeFace(const cv::Mat& kept, const cv::Rect& box, ImagingRegion* region) {
  std::vector<cv::Point2d> top;
  for (int c = box.x; c < box.x + box.width; c += 2) {
    for (int r = box.y; r < box.y + box.height; ++r) {
      if (kept.at<std::uint8_t>(r, c)) {
        top.emplace_back(c, r);
        break;
      }
    }
  }
  if (top.size() < 3)
    return false;
  cv::RNG rng(0x5EC7);  // fixed: the same frame gives the same region
  int best_count = 0;
  cv::Point2d best_centre;
  double best_radius = 0.0;
  const int n = static_cast<int>(top.size());
  for (int trial = 0; trial < kFaceTrials; ++trial) {
    cv::Point2d centre;
    double radius = 0.0;
    if (!circleThrough(top[std::size_t(rng.uniform(0, n))], top[std::size_t(rng.uniform(0, n))],
                       top[std::size_t(rng.uniform(0, n))], &centre, &radius) ||
        centre.y > box.y || radius > kFaceMaxRadius * box.width)
      continue;
    int count = 0;
    for (const cv::Point2d& p : top)
      count += std::abs(cv::norm(p - centre) - radius) < kFaceTolerance_px ? 1 : 0;
    if (count > best_count)
      best_count = count, best_centre = centre, best_radius = radius;
  }
  if (best_count < kFaceMinColumns)
    return false;
  double lo = 1e9, hi = -1e9;
  for (const cv::Point2d& p : top) {
    if (std::abs(cv::norm(p - best_centre) - best_radius) < kFaceTolerance_px)
      lo = std::min(lo, p.x), hi = std::max(hi, p.x);
  }
  const double half = 0.5 * (hi - lo);
  const double sag =
      best_radius - std::sqrt(std::max(0.0, best_radius * best_radius - half * half));
  if (sag < kFaceMinSag_px)
    return false;
  region->apex_px = best_centre;
  region->top_radius_px = best_radius - kFaceTolerance_px;
  return true;
}

/// Step 2: a fan (the hull's side edges slanted) or a probe face that is an arc.
bool sectorOf(const std::vector<cv::Point>& hull, const cv::Mat& kept, ImagingRegion* region) {
  const cv::Rect box = cv::boundingRect(hull);
  const bool face = probeFace(kept, box, region);
  const SideEdges s = sideEdges(hull, box.x + 0.5 * box.width);
  auto slope = [](cv::Point2d a, cv::Point2d b) { return std::abs((b.x - a.x) / (b.y - a.y)); };
  const bool slanted = s.found && slope(s.left_a, s.left_b) >= kVerticalSlope &&
                       slope(s.right_a, s.right_b) >= kVerticalSlope;
  return face || slanted;
}

}  // namespace

std::string toString(ImagingRegion::Shape shape) {
  switch (shape) {
    case ImagingRegion::Shape::kRectangle:
      return "rectangle";
    case ImagingRegion::Shape::kSector:
      return "sector";
    case ImagingRegion::Shape::kFrame:
      break;
  }
  return "frame";
}

float ImagingRegion::insetAt(cv::Point2d p) const {
  const int c = cvRound(p.x), r = cvRound(p.y);
  if (inset.empty() || c < 0 || r < 0 || c >= inset.cols || r >= inset.rows)
    return 0.0F;
  return inset.at<float>(r, c);
}

ImagingRegion findImagingRegion(const cv::Mat& grey8) {
  ImagingRegion region;
  if (grey8.empty() || grey8.type() != CV_8UC1)
    return region;
  const double frame_area = static_cast<double>(grey8.total());
  const cv::Mat kept = brightBlobs(grey8);
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(kept, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
  std::vector<cv::Point> all, hull;
  for (const auto& c : contours)
    all.insert(all.end(), c.begin(), c.end());
  if (all.size() >= 3)
    cv::convexHull(all, hull);
  const double hull_area = hull.size() >= 3 ? cv::contourArea(hull) : 0.0;
  region.mask = cv::Mat(grey8.size(), CV_8U, cv::Scalar(0));
  if (hull_area >= kWholeFrame * frame_area || hull_area < kMinFraction * frame_area) {
    region.mask.setTo(255);
  } else {
    cv::fillConvexPoly(region.mask, hull, cv::Scalar(255));
    region.shape = ImagingRegion::Shape::kRectangle;
    if (sectorOf(hull, kept, &region))
      region.shape = ImagingRegion::Shape::kSector;
    if (region.top_radius_px > 0.0) {  // above the probe face's arc is outside
      cv::Mat face(grey8.size(), CV_8U, cv::Scalar(0));
      cv::circle(face, cv::Point(cvRound(region.apex_px.x), cvRound(region.apex_px.y)),
                 std::max(0, cvRound(region.top_radius_px)), cv::Scalar(255), cv::FILLED);
      region.mask.setTo(0, face);
    }
  }
  // Distance to the boundary, the frame's border counting as one (a zero margin of 1 px).
  cv::Mat padded, dist;
  cv::copyMakeBorder(region.mask, padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::distanceTransform(padded, dist, cv::DIST_L2, cv::DIST_MASK_PRECISE);
  region.inset = dist(cv::Rect(1, 1, grey8.cols, grey8.rows)).clone();
  region.fraction = cv::countNonZero(region.mask) / frame_area;
  region.box = cv::boundingRect(region.mask);
  return region;
}

}  // namespace needle_guidance::imaging
