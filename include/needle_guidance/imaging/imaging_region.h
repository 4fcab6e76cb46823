// The imaging region of a B-mode frame: where the probe's beams reach. A scanner draws its image
// inside a sector (convex or phased probe: two straight edges meeting at an apex above the
// image, the probe face an arc at the top, the deepest samples an arc at the bottom) or a
// rectangle (linear probe) and leaves the rest of the frame black, or writes text there.
// findImagingRegion works the region out from the frame (or, better, from the maximum of a
// sequence's frames: a shadow or an anechoic area dark in one frame is rarely dark in all):
//   1  the pixels brighter than kBlackLevel, closed, small blobs (text, markers) dropped;
//   2  their convex hull; a sector when the hull's side edges are slanted or the top of the
//      image is an arc (the probe face: a circle fitted to each column's first bright row),
//      else a rectangle; above the probe face's arc is outside (the hull spans it);
//   3  the region's mask and each pixel's distance to its boundary (the frame's border counts).
// Plain C++ and OpenCV; no ROS.
#pragma once

#include <opencv2/core.hpp>
#include <string>

namespace needle_guidance::imaging {

struct ImagingRegion {
  enum class Shape : int {
    kFrame,      ///< the whole frame is image (nothing black around it)
    kRectangle,  ///< a linear probe's rectangle inside a black frame
    kSector      ///< a convex or phased probe's fan
  };
  Shape shape = Shape::kFrame;
  cv::Mat mask;   ///< CV_8UC1, 255 inside the region (empty: the whole frame)
  cv::Mat inset;  ///< CV_32FC1, distance to the region's boundary or the frame's border [px]
  cv::Point2d apex_px{0.0, 0.0};  ///< centre of the probe face's arc, when curved [px]
  double top_radius_px = 0.0;     ///< radius of the probe face's arc (0: a straight face) [px]
  double fraction = 1.0;          ///< share of the frame inside the region
  cv::Rect box;                   ///< the region's bounding box [px]
  /// Distance of p from the region's boundary [px]; 0 outside it or the frame. For kFrame, the
  /// distance from the frame's border.
  float insetAt(cv::Point2d p) const;
  /// Whether the region is more than the whole frame's rectangle (a black margin around it).
  bool bounded() const { return shape != Shape::kFrame; }
};

std::string toString(ImagingRegion::Shape shape);

/// The region of a CV_8UC1 frame (or a sequence's maximum frame). Never throws; an empty or
/// non-8-bit image gives the whole frame of its size (kFrame).
ImagingRegion findImagingRegion(const cv::Mat& grey8);

}  // namespace needle_guidance::imaging
