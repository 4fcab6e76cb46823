// Image statistics that say how much a B-mode frame looks like a scanner's: speckle
// level, its signal-to-noise and grain, the needle's contrast and how bright the brightest
// other structure is against it. bench tracking_real compares the recorded in-vitro frames with
// the imager's classic and realistic renderers on them. Plain C++ and OpenCV.
#pragma once

#include <opencv2/core.hpp>

namespace needle_guidance::imaging {

/// Statistics of one CV_8UC1 frame (grey levels 0..255, lengths in pixels).
struct BModeStatistics {
  int tissue_patches = 0;           ///< 32 x 32 tissue patches the speckle figures come from
  double tissue_mean_grey = 0.0;    ///< median over the patches of their mean
  double speckle_snr = 0.0;         ///< median over the patches of mean / standard deviation
  double speckle_lateral_px = 0.0;  ///< autocorrelation half width at half maximum along x
  double speckle_axial_px = 0.0;    ///< the same along y (the beam)
  double needle_grey = 0.0;         ///< 90th percentile of the grey levels on the needle mask
  double needle_contrast = 0.0;     ///< needle_grey / tissue_mean_grey
  /// 99.5th percentile of the grey levels away from the needle (more than 10 px from its mask)
  /// over needle_grey: > 1 when an interface or a wall is brighter than the needle.
  double brightest_other_over_needle = 0.0;
  double dark_fraction = 0.0;  ///< fraction of pixels below 10 grey levels (no echo)
};

/// Statistics of `grey` (CV_8UC1) with the needle's pixels non-zero in `needle_mask` (CV_8UC1,
/// same size; empty = no needle: the needle figures stay 0). Tissue patches are 32 x 32 tiles
/// at least 10 px from the needle, with a mean of at least 30 grey levels and no pixel above 200
/// (speckle, not the dark background or a specular structure). Throws std::invalid_argument
/// for a frame that is not CV_8UC1 or a mask of another size or type.
BModeStatistics bmodeStatistics(const cv::Mat& grey, const cv::Mat& needle_mask);

}  // namespace needle_guidance::imaging
