// Tetrahedral meshing of a tissue_3d scene with CGAL Mesh_3 (a labelled implicit domain: the
// block and its region surfaces), graded finer within a radius of the needle lines and the
// targets; element quality check with repair of near-zero-volume elements.
#pragma once

#include <ostream>
#include <string>
#include <vector>

#include "needle_guidance/fem/linear_elasticity.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"

namespace needle_guidance::tissue_3d {

/// A tetrahedral tissue mesh: element_material 0 = block, 1 + r = region r (materialTable()).
struct TetMesh3 : fem::SimplexMesh<3> {
  std::vector<char> node_fixed;  ///< on a fixed block face or in a fixed region
  int fixedCount() const;
};

/// What the mesher and the quality check did.
struct TetMeshReport {
  double cpu_s = 0.0;
  int dropped_elements = 0;        ///< near-zero-volume elements removed (repair)
  double dropped_volume_m3 = 0.0;  ///< their total volume
  double min_quality = 0.0;        ///< min over kept elements of 6 sqrt(2) V / l_rms^3 (1: regular)
  std::string note;                ///< what was repaired, for the user ("" if nothing)
};

/// Meshes the scene. lines: lateral (y, z) positions of needle lines that need the fine size
/// (in addition to the lines through the targets). size_scale multiplies both sizes (the bench
/// sweeps it for the element count). Throws std::invalid_argument if the mesh has fewer than
/// 4 fixed nodes (nothing holds the tissue) or an element is inverted.
TetMesh3 meshTissue3d(const TissueScene3d& scene, const std::vector<Eigen::Vector2d>& lines,
                      double size_scale = 1.0, TetMeshReport* report = nullptr);

/// The size_scale of meshTissue3d that gives about n tetrahedra (element count ~ scale^-3,
/// one correction from a trial mesh at the first guess). tets_at_scale_1: the element count at
/// scale 1 when known (<= 0: meshed here).
double sizeScaleForTets(const TissueScene3d& scene, double n, int tets_at_scale_1 = 0);

/// Mean-ratio quality 6 sqrt(2) V / l_rms^3 of a tetrahedron: 1 regular, 0 flat; negative
/// if inverted.
double tetQuality(const fem::Corners<3>& c);

/// The quality rule every tissue mesh passes: an inverted element (volume < 0) is refused
/// (std::invalid_argument naming it); elements with quality below min_quality (near-zero
/// volume: slivers, flat or collapsed tetrahedra) are dropped and nodes no element uses are
/// removed; the report says how many and their volume.
void repairTetMesh(TetMesh3& mesh, double min_quality, TetMeshReport& report);

/// check_scene for a tissue_3d file: loads and validates it, prints a summary to `out` and,
/// with mesh, meshes it and prints the element count, quality and any repair. Returns 0; a bad
/// scene throws (scene::SceneError or std::invalid_argument) with the reason.
int checkTissueScene3d(const std::string& path, bool mesh, std::ostream& out);

/// Quality below which an element counts as of near-zero volume.
constexpr double kMinTetQuality = 1e-3;

}  // namespace needle_guidance::tissue_3d
