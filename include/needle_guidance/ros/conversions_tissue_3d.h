// Markers of the 3-D tissue simulation (tissue_3d/): deformed region surfaces, the needle, the
// seeds, the targets and the block outline, in frame scene.
#pragma once

#include <visualization_msgs/MarkerArray.h>

#include <string>
#include <vector>

#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance::ros_conversions {

/// A region surface embedded in the tissue mesh: each vertex's tetrahedron and weights
/// (element -1: the vertex lies outside the mesh and is drawn where it is).
struct EmbeddedSurface3 {
  std::string name;
  bool fixed = false;
  std::vector<tissue_3d::EmbeddedPoint> vertices;
  std::vector<std::array<int, 3>> triangles;
};

/// Locates every vertex of every region surface of `scene` in `model`'s mesh (once).
std::vector<EmbeddedSurface3> embedSurfaces(const tissue_3d::TissueScene3d& scene,
                                            const tissue_3d::TissueModel3& model);

/// The markers: region surfaces deformed by `displacement` (Dim * node order, from
/// NeedleInsertion3::displacementField; empty = undeformed), TRIANGLE_LIST, one colour per
/// region (fixed regions grey); the needle from its hub to the tip (LINE_STRIP, DELETE when it
/// is out of the block); seeds (yellow) and targets (green) as SPHERE_LISTs; the block outline.
visualization_msgs::MarkerArray tissue3dToMarkers(const tissue_3d::TissueScene3d& scene,
                                                  const tissue_3d::TissueModel3& model,
                                                  const std::vector<EmbeddedSurface3>& surfaces,
                                                  const Eigen::VectorXd& displacement,
                                                  const tissue_3d::NeedleInsertion3& needle,
                                                  const std::string& frame_id);

}  // namespace needle_guidance::ros_conversions
