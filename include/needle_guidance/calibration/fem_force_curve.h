// The axial needle force against depth that the project's 2-D needle–tissue model predicts for a
// straight insertion into a homogeneous tissue block (dissertation 2.3.3–2.3.6). The one place the
// calibration touches the tissue simulation: it drives TissueSimulation along the depth grid and
// reads the needle's force on the tissue per step (tip cutting force plus shaft friction).
#pragma once

#include <string>
#include <vector>

#include "needle_guidance/tissue/needle_insertion.h"

namespace needle_guidance::calibration {

/// The tissue block the calibration inserts into: a rectangle entered through its free face
/// x = 0 at mid-height, its other three faces fixed (a sample held in a container).
struct CalibrationBlock {
  double length_m = 0.12;                ///< along the needle [m]
  double height_m = 0.06;                ///< across the needle [m]
  double thickness_m = 0.01;             ///< slice thickness h carrying the needle's forces [m]
  double young_modulus_Pa = 20e3;        ///< tissue stiffness (sets the pre-puncture phase) [Pa]
  double poisson_ratio = 0.49;           ///< nearly incompressible soft tissue
  double max_edge_m = 6e-3;              ///< element size away from the needle path [m]
  double min_edge_m = 1e-3;              ///< element size along the needle path [m]
  double insertion_velocity_m_s = 5e-3;  ///< needle speed (sets the stick-slip time step) [m/s]
  double depth_step_m = 1e-4;            ///< depth grid of the simulation [m]
};

/// Scene YAML of the block with the needle parameters, for TissueSimulation and for users who
/// want to run the calibration insertion themselves (check_scene, tissue_sim). The mesh is fine
/// along the whole needle path, whatever depth a run goes to.
std::string calibrationSceneYaml(const CalibrationBlock& block, const tissue::NeedleParams& needle);

/// Axial force on the needle [N] (needle on tissue along +x: tip force plus shaft friction) at
/// each depth of `depths_m` (ascending, > 0, within the block), inserting at the block's speed.
/// Throws std::invalid_argument for bad parameters and std::runtime_error when a step is refused.
std::vector<double> femInsertionForce(const CalibrationBlock& block,
                                      const tissue::NeedleParams& needle,
                                      const std::vector<double>& depths_m);

}  // namespace needle_guidance::calibration
