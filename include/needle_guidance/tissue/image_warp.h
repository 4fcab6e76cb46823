// Images of the tissue slice: pixel <-> scene geometry, a synthetic B-mode reference image and
// the piecewise-affine warp of the reference image by the FEM displacement (dissertation
// 2.3.7: the reference image is texture-mapped with the reference node coordinates of mesh G as
// texture coordinates and drawn at the deformed node coordinates of mesh G').
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <opencv2/core.hpp>
#include <string>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/scene/scene.h"

namespace needle_guidance::tissue {

using geometry::Point2;

/// Pixel grid of an image of the slice in frame `scene` (+x insertion depth, +y height).
/// Row 0 is the TOP of the image (largest y); column 0 is the smallest x. Continuous pixel
/// coordinates follow OpenCV: (col, row) = (0, 0) is the CENTRE of the top-left pixel, so the
/// image covers col, row in [-0.5, cols - 0.5] x [-0.5, rows - 0.5].
struct ImageGeometry {
  /// Scene position of the top-left image CORNER (x min, y max) [m].
  Point2 origin_m = Point2::Zero();
  double pixel_size_m = 0.0;  ///< square pixel edge [m], > 0
  int rows = 0;               ///< image height [px], > 0
  int cols = 0;               ///< image width [px], > 0

  /// Continuous pixel coordinates (x = col, y = row) of a scene point.
  /// @param[in] p_scene point in frame scene [m]
  cv::Point2d toPixel(const Point2& p_scene) const;
  /// Scene point of continuous pixel coordinates (x = col, y = row); inverse of toPixel.
  /// @param[in] p_px pixel coordinates [px]
  /// @return point in frame scene [m]
  Point2 toScene(const cv::Point2d& p_px) const;
  /// OpenCV size (cols, rows).
  cv::Size size() const { return {cols, rows}; }
  /// Throws std::invalid_argument naming `where` and the value if pixel_size_m is not positive
  /// and finite, rows or cols is not positive, or origin_m is not finite.
  void validate(const char* where) const;
};

/// The image geometry whose top-left corner is (workspace_min.x, workspace_max.y) and whose
/// pixels cover the workspace rectangle: cols = ceil(width / pixel_size_m), rows likewise
/// (exact when the size is a whole number of pixels, as for the embedded scenes; otherwise the
/// last column / bottom row reach past the workspace by less than one pixel).
/// @param[in] scene workspace_min / workspace_max [m]
/// @param[in] pixel_size_m pixel edge [m], > 0 and finite
/// Throws std::invalid_argument for a bad pixel size or an empty workspace.
ImageGeometry forWorkspace(const scene::Scene& scene, double pixel_size_m);

/// Mean echogenicity (fraction of full scale, before speckle) that syntheticUltrasound gives a
/// material, by case-insensitive name: "fat" 0.45, "prostate" 0.22, "muscle" 0.30, "bone" 0.85,
/// anything else 0.35. (A rigid region is drawn as bone whatever its material.)
double meanEchogenicity(const std::string& material_name);

/// A B-mode-like 8-bit single-channel reference image made from the scene's regions: each
/// pixel's region (background_material outside all regions, black outside the workspace) sets
/// the mean echogenicity (meanEchogenicity), every region outline gets a bright capsule line
/// (echogenicity 0.75, 0.4 mm wide), and a fully developed speckle pattern multiplies it: the
/// magnitude of a complex Gaussian field smoothed by an anisotropic Gaussian (grain sigma
/// 0.4 mm along x, 0.15 mm along y: the axial direction of a probe on the y = 0 face), i.e.
/// Rayleigh distributed with unit mean. Deterministic for a seed (std::mt19937, own
/// Box-Muller). Per-frame noise, blur and frame drops (scene.imaging) are NOT applied here:
/// they belong to each simulated frame, not to the tissue texture.
/// @param[in] scene regions, background_material, materials
/// @param[in] g pixel grid (validated; throws std::invalid_argument)
/// @param[in] seed speckle seed
/// @return CV_8UC1 image of size g.size()
cv::Mat syntheticUltrasound(const scene::Scene& scene, const ImageGeometry& g, std::uint32_t seed);

/// Fully developed speckle: the magnitude of a complex Gaussian field (std::mt19937, own
/// Box-Muller: the same on every platform) smoothed by a Gaussian of sigma_x_px / sigma_y_px,
/// i.e. Rayleigh distributed, scaled to unit mean (CV_32FC1 of `size`). Multiply an
/// echogenicity map by it.
cv::Mat rayleighSpeckle(cv::Size size, double sigma_x_px, double sigma_y_px, std::uint32_t seed);

/// The reference (undeformed) image of the slice: scene.imaging.reference_image read as 8-bit
/// greyscale and resized to g (it is taken to span the image geometry exactly) when the scene
/// names one, else syntheticUltrasound(scene, g, seed).
/// Throws std::invalid_argument naming the path if the file cannot be read as an image.
cv::Mat referenceImage(const scene::Scene& scene, const ImageGeometry& g, std::uint32_t seed);

/// How warpImage draws the triangles. Both are piecewise-affine with bilinear sampling of the
/// reference (border pixels replicated) and leave uncovered pixels 0.
enum class WarpMethod {
  /// Per deformed triangle: scan its pixel bounding box, keep pixel centres whose barycentric
  /// coordinates are all >= -1e-9 (no gaps along shared edges), map them with the same
  /// barycentric weights into the reference triangle and sample. Exact (identity and
  /// whole-pixel translations reproduce the reference bit for bit); the default and the fastest.
  kBarycentricScan,
  /// Per triangle: cv::getAffineTransform + cv::warpAffine on the triangle's bounding
  /// rectangle, copied through a cv::fillConvexPoly mask. Kept for comparison; OpenCV's 1/32
  /// pixel fixed-point interpolation and the mask's pixel rule make it differ by a grey level
  /// here and there, and edge pixels just outside the mesh may be drawn.
  kOpenCvAffine,
};

/// Piecewise-affine warp of the reference image by a nodal displacement (dissertation 2.3.7):
/// each triangle of the reference mesh G is drawn at its deformed position (nodes + u), its
/// pixels textured from the reference triangle by the affine map between the two (the linear
/// FEM interpolation inside a triangle, 2.2.2). Pixels no deformed triangle covers are 0. Where
/// deformed triangles overlap (an inverted mesh) the later triangle wins.
/// @param[in] reference CV_8UC1 image of size g.size() (the undeformed slice)
/// @param[in] g pixel grid of both images
/// @param[in] reference_mesh mesh G in frame scene [m]
/// @param[in] u displacement, u[2i] = x and u[2i+1] = y of node i [m]
/// @param[in] method drawing method (see WarpMethod)
/// @return CV_8UC1 image of size g.size()
/// Throws std::invalid_argument for a reference of the wrong size or type, a bad g, u of the
/// wrong size or a non-finite u (naming the DOF), or a triangle with an invalid node index.
cv::Mat warpImage(const cv::Mat& reference, const ImageGeometry& g,
                  const geometry::TriangleMesh& reference_mesh, const Eigen::VectorXd& u,
                  WarpMethod method = WarpMethod::kBarycentricScan);

}  // namespace needle_guidance::tissue
