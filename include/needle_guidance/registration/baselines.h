// Baselines for probe-in / probe-out registration on the same data (dissertation 3.3.4-3.3.5):
// rigid centre-of-mass translation of the prostate (the dissertation's comparison, after
// Bharatha et al. [26]) and an intensity-based deformable registration on synthetic images.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include <opencv2/core.hpp>

#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/probe_case.h"

namespace needle_guidance::registration {

/// Result of a baseline: the same point-mapping interface as the FEM registration.
struct BaselineResult {
  RegistrationStatus status = RegistrationStatus::kInvalidSegmentation;
  std::string message;
  std::shared_ptr<const PointMapping> mapping;  ///< null for refusals
  double dice = 0.0;     ///< probe-in prostate vs the probe-out prostate mapped by T
  double seconds = 0.0;  ///< wall time [s] (image rendering excluded for the intensity method)
};

/// Rigid registration by centre-of-mass translation of the prostate total gland (3.3.4):
/// T(x) = x + (c_in - c_out), c = area centroid. Refuses (kInvalidSegmentation) the same
/// segmentation defects as registerSlices.
BaselineResult rigidCentreOfMass(const SliceSegmentation& probe_out,
                                 const ProbeInSegmentation& probe_in);

/// A pair of synthetic grey-level images of a case, same pixel grid: pixel (row r, col c) has
/// centre origin + ((c + 0.5) * pixel, (R - r - 0.5) * pixel) (row 0 at the top = anterior).
struct SyntheticImagePair {
  cv::Mat probe_out;               ///< CV_32F, fixed image F
  cv::Mat probe_in;                ///< CV_32F, moving image M
  Point2 origin = Point2::Zero();  ///< lower-left corner of the grid [m]
  double pixel_m = 0.0005;
};

/// How the texture of the two synthetic images relates.
enum class TextureMode {
  kIndependent,     ///< each image has its own random texture: only the anatomy's region
                    ///< boundaries carry correspondence (different coils / sequences, 3.3.1)
  kTissueTracking,  ///< one texture that moves with the tissue (optimistic for intensity methods)
};

/// Renders T2-like images of a case from its exact anatomy: region grey levels (CG, PZ,
/// surrounding, bladder bright, bone, rectum lumen / probe dark) -- the probe-in image is the
/// probe-out anatomy pulled back through the true mapping -- plus a smooth texture (see
/// TextureMode) and independent Gaussian pixel noise (noise_sd, grey levels in [0, 1]).
/// Deterministic for a given seed.
SyntheticImagePair renderProbeImages(const ProbeCase& probe_case, double pixel_m = 0.0005,
                                     double noise_sd = 0.03, std::uint64_t seed = 1,
                                     TextureMode texture = TextureMode::kIndependent);

enum class IntensityMethod {
  kDemons,          ///< multi-resolution Thirion demons with Gaussian regularisation (imgproc only)
  kDisOpticalFlow,  ///< cv::DISOpticalFlow (needs opencv_video, see intensityMethodAvailable)
  kFarneback,       ///< cv::calcOpticalFlowFarneback (needs opencv_video)
};
const char* toString(IntensityMethod method);
/// False for the optical-flow methods when the core was built without NG_HAVE_OPENCV_VIDEO.
bool intensityMethodAvailable(IntensityMethod method);

/// Intensity-based deformable registration of the image pair: a dense displacement field v on
/// the probe-in grid with probe_in(x) ~ probe_out(x + v(x)), so T^-1(y) = y + v(y) (bilinear)
/// and T is its fixed-point inverse. Points outside the image map to nullopt. Dice is that of
/// `probe_out_prostate` mapped by T against `probe_in_prostate`. Returns kUnavailable for a
/// method not compiled in.
BaselineResult intensityRegistration(const SyntheticImagePair& images,
                                     const Loops& probe_out_prostate,
                                     const Polygon& probe_in_prostate,
                                     IntensityMethod method = IntensityMethod::kDemons);

}  // namespace needle_guidance::registration
