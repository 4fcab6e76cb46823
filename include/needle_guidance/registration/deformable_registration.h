// Deformable registration with tissue-parameter estimation (dissertation 3.2), applied to
// endorectal probe-in / probe-out prostate slices (3.3.2-3.3.3).
//
// Model (3.2.2): a conforming triangle mesh of the probe-out slice (CG, PZ, surrounding tissue;
// rectum lumen and bladder cavity not meshed; bones fixed), plane-strain linear elasticity
// (tissue::FemModel, nu = 0.49, averaged-volumetric triangles against locking), the outer
// boundary traction-free. Dirichlet conditions H (3.3.2): every rectum-wall node is moved along
// the ray from the rectum centre to where that ray meets the probe outline of the probe-in
// slice. Unknowns p (3.2.4): Young's modulus per soft class (CG, PZ, surrounding; bounded
// [1, 600] kPa) and the external force at every node of the force set L (2 components each).
// Objective (3.2.4): maximise Q = S - alpha E, S = Dice of the probe-in prostate and the
// deformed probe-out prostate (exact polygon overlap), E = share of the strain energy due to
// the external forces, from two solves (without and with forces).
//
// Scale: when every boundary condition is a displacement, scaling all moduli and all forces
// by the same factor leaves the displacement and Q unchanged, so only stiffness ratios are
// identifiable. The modulus of the reference class (default: surrounding tissue, 30 kPa) is
// therefore held fixed and the other moduli are estimated relative to it.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"
#include "needle_guidance/registration/dice.h"
#include "needle_guidance/registration/point_mapping.h"
#include "needle_guidance/registration/segmentation.h"

namespace needle_guidance::registration {

/// Outcome of a registration (or a baseline). Data problems are reported here, never thrown.
enum class RegistrationStatus {
  kConverged,                  ///< optimiser stopped on its tolerance
  kConvergedAtBound,           ///< converged with at least one modulus clamped at 1 or 600 kPa
  kAlreadyAligned,             ///< Dice = 1 at the initial parameters: nothing to optimise
  kMaxIterations,              ///< iteration limit reached (result is the best iterate)
  kInvalidSegmentation,        ///< inner ring, self-intersection, overlap, outside domain...
  kProbeDoesNotEncloseRectum,  ///< the probe outline cannot define the rectum displacements
  kMeshingFailed,              ///< CGAL meshing refused the geometry
  kSolveFailed,                ///< FEM factorisation failed or produced non-finite values
  kUnavailable,                ///< method not compiled in (see intensity baselines)
};

/// Short name of a status, e.g. "converged_at_bound".
const char* toString(RegistrationStatus status);
/// True for kConverged, kConvergedAtBound, kAlreadyAligned and kMaxIterations (a mapping is
/// available); false for the refusals.
bool hasMapping(RegistrationStatus status);

/// Soft tissue classes with their own Young's modulus (m = 3, 3.3.2).
enum SoftClass : int { kSurrounding = 0, kCentralGland = 1, kPeripheralZone = 2 };
constexpr int kSoftClassCount = 3;
/// "surrounding", "cg", "pz".
const char* softClassName(int soft_class);

/// Which nodes carry unknown external forces (set L, 3.2.4).
enum class ForceSet {
  kBladderBoundary,  ///< nodes on the bladder wall (none if no bladder is segmented); default
  kGlandBoundary,    ///< nodes on the prostate boundary (the dissertation's choice, 3.3.2)
  kNone,             ///< stiffness only
};

enum class Optimizer {
  kSteepestDescent,  ///< 3.2.4: steepest ascent of Q with Armijo's rule, finite-difference gradient
  kFast,             ///< projected Levenberg-Marquardt on a boundary-distance residual (see .cpp)
};

struct RegistrationOptions {
  int target_nodes = 500;       ///< mesh size (3.3.2: n = 500); achieved within ~15 %
  double poisson_ratio = 0.49;  ///< 3.2.2
  /// Initial moduli per SoftClass [Pa] (3.3.2: CG 60 kPa, all surrounding tissues 30 kPa).
  std::array<double, kSoftClassCount> initial_modulus_Pa{30e3, 60e3, 30e3};
  int reference_class = kSurrounding;  ///< its modulus stays at the initial value (scale, see top)
  double min_modulus_Pa = 1e3;         ///< Y_min (3.2.4)
  double max_modulus_Pa = 600e3;       ///< Y_max (3.2.4)
  ForceSet force_set = ForceSet::kBladderBoundary;
  double alpha = 0.005;  ///< weight of E in Q = S - alpha E (3.3.5); S, E as fractions
  Optimizer optimizer = Optimizer::kFast;
  int max_iterations = 200;          ///< optimiser iterations
  double gradient_tolerance = 1e-3;  ///< steepest descent: stop when |grad Q| < epsilon (3.2.4)
  double step_size = 0.5;            ///< steepest descent: lambda, in scaled variables (see .cpp)
  double fd_step = 1e-3;             ///< finite-difference step in scaled variables
  /// kFast: weight of the force ridge term (scaled forces) relative to the boundary residual [m^2].
  double fast_force_regularisation_m2 = 1e-5;
  double fast_tolerance = 1e-5;  ///< kFast: stop when the relative cost decrease < this
  /// Refuse when a rectum-wall point lies farther than this outside the probe outline [m].
  double max_rectum_outside_probe_m = 0.001;
  double mrsi_spacing_m = 0.007;  ///< 3.3.3
};

/// One optimiser iteration.
struct IterationRecord {
  int iteration = 0;
  double q = 0.0;             ///< objective Q = S - alpha E
  double dice = 0.0;          ///< S
  double energy_share = 0.0;  ///< E
  std::array<double, kSoftClassCount> modulus_Pa{};
  double seconds = 0.0;  ///< since the start of registerSlices
};

struct RegistrationResult {
  RegistrationStatus status = RegistrationStatus::kInvalidSegmentation;
  std::string message;  ///< human-readable reason / summary

  // Estimated parameters p* (3.2.4).
  std::array<double, kSoftClassCount> modulus_Pa{};      ///< per SoftClass [Pa]
  std::array<bool, kSoftClassCount> modulus_at_bound{};  ///< clamped exactly at a bound
  std::vector<int> force_nodes;                          ///< set L (mesh node indices)
  std::vector<Point2> forces_N;  ///< per node of L [N per metre of slice thickness]

  // Quality.
  double dice = 0.0;          ///< S at p* (deformed probe-out prostate vs probe-in prostate)
  double initial_dice = 0.0;  ///< S of the undeformed probe-out prostate
  double energy_share = 0.0;  ///< E at p* (fraction)
  double q = 0.0;             ///< Q at p*
  int iterations = 0;
  int objective_evaluations = 0;  ///< FEM-based evaluations of Q (incl. finite differences)
  std::vector<IterationRecord> trace;
  double seconds = 0.0;          ///< wall time of registerSlices [s]
  double meshing_seconds = 0.0;  ///< of which meshing and assembly [s]

  // Model and deformation.
  geometry::TriangleMesh mesh;                 ///< probe-out mesh (regions: see region_names) [m]
  std::vector<Point2> displacement_m;          ///< per mesh node [m]
  std::vector<int> rectum_nodes;               ///< Dirichlet nodes H (3.3.2)
  std::vector<int> fixed_nodes;                ///< bone nodes
  std::shared_ptr<const MeshMapping> mapping;  ///< T and T^-1; null for refusals
  WarpedGrid mrsi_grid;                        ///< 3.3.3 (empty for refusals)

  /// T (probe-out -> probe-in) [m]; nullopt outside the mesh or without a mapping.
  std::optional<Point2> forward(const Point2& probe_out_m) const;
  /// T^-1 (probe-in -> probe-out) [m]; nullopt outside the deformed mesh or without a mapping.
  std::optional<Point2> inverse(const Point2& probe_in_m) const;
};

/// Registers the probe-out slice to the probe-in slice (3.2-3.3). Never throws for data
/// problems: invalid segmentations, a probe that does not enclose the rectum, meshing or solver
/// failures are reported in `status` and `message` with no mapping. Throws
/// std::invalid_argument only for invalid options (e.g. target_nodes < 30, bounds not
/// 0 < min <= initial <= max, alpha < 0).
RegistrationResult registerSlices(const SliceSegmentation& probe_out,
                                  const ProbeInSegmentation& probe_in,
                                  const RegistrationOptions& options = {});

/// The probe-out prostate (CG union PZ) as loops, e.g. for Dice of a baseline.
Loops prostateLoops(const SliceSegmentation& probe_out);

/// The homologous rectum-wall displacement of 3.3.2 for one wall point: the point where the ray
/// from `rectum_centre` through `wall_point` leaves the probe outline (nearest crossing beyond
/// the centre); nullopt if the ray does not cross the outline.
std::optional<Point2> projectOntoProbe(const Point2& rectum_centre, const Point2& wall_point,
                                       const Polygon& probe);

}  // namespace needle_guidance::registration
