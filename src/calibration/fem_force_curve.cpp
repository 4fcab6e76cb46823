#include "needle_guidance/calibration/fem_force_curve.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

#include "needle_guidance/format.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/tissue/tissue_simulation.h"

namespace needle_guidance::calibration {
namespace {

std::string exact(double value) {
  return formatNumber(value, 17);
}

}  // namespace

std::string calibrationSceneYaml(const CalibrationBlock& block,
                                 const tissue::NeedleParams& needle) {
  const double l = block.length_m;
  // The needle may go to the far face less two fine elements; the mesh is refined along that
  // whole path, so it does not depend on how deep a particular run goes.
  const double max_depth_m = l - 2.0 * block.min_edge_m;
  const double h = block.height_m;
  std::ostringstream y;
  y << "scene: {name: calibration_block, description: homogeneous block for force calibration}\n"
    << "workspace: {min_m: [0, 0], max_m: [" << exact(l) << ", " << exact(h)
    << "], background_material: tissue, thickness_m: " << exact(block.thickness_m) << "}\n"
    << "models: {tissue: quasi_static, corotational: false, steering: false}\n"
    << "materials:\n  - {name: tissue, young_modulus_Pa: " << exact(block.young_modulus_Pa)
    << ", poisson_ratio: " << exact(block.poisson_ratio) << "}\n"
    << "boundary:\n"
    << "  - {name: entry, condition: free, from_m: [0, 0], to_m: [0, " << exact(h) << "]}\n"
    << "  - {name: bottom, condition: fixed, from_m: [0, 0], to_m: [" << exact(l) << ", 0]}\n"
    << "  - {name: far, condition: fixed, from_m: [" << exact(l) << ", 0], to_m: [" << exact(l)
    << ", " << exact(h) << "]}\n"
    << "  - {name: top, condition: fixed, from_m: [0, " << exact(h) << "], to_m: [" << exact(l)
    << ", " << exact(h) << "]}\n"
    << "needle:\n  min_height_m: " << exact(0.5 * h) << "\n  max_height_m: " << exact(0.5 * h)
    << "\n  max_depth_m: " << exact(max_depth_m)
    << "\n  insertion_velocity_m_s: " << exact(block.insertion_velocity_m_s)
    << "\n  cutting_force_N: " << exact(needle.cutting_force_N)
    << "\n  cut_length_m: " << exact(needle.cut_length_m)
    << "\n  static_friction_N_per_m: " << exact(needle.static_friction_N_per_m)
    << "\n  kinetic_friction_N_per_m: " << exact(needle.kinetic_friction_N_per_m)
    << "\n  stick_velocity_m_s: " << exact(needle.stick_velocity_m_s)
    << "\n  diameter_m: " << exact(2.0 * needle.tip_radius_m) << "\n"
    << "targets:\n  - {name: path_end, position_m: [" << exact(max_depth_m) << ", "
    << exact(0.5 * h) << "]}\n"
    << "mesh: {max_edge_m: " << exact(block.max_edge_m)
    << ", min_edge_m: " << exact(block.min_edge_m) << ", grading_length_m: " << exact(0.1 * h)
    << ", min_angle_deg: 25, refine_targets: true}\n";
  return y.str();
}

std::vector<double> femInsertionForce(const CalibrationBlock& block,
                                      const tissue::NeedleParams& needle,
                                      const std::vector<double>& depths_m) {
  if (depths_m.empty()) {
    return {};
  }
  const double max_depth = depths_m.back();
  for (std::size_t i = 0; i < depths_m.size(); ++i) {
    if (!(depths_m[i] > 0.0) || (i > 0 && !(depths_m[i] > depths_m[i - 1]))) {
      throw std::invalid_argument(
          "femInsertionForce: depths must be positive and ascending "
          "(depth " +
          formatNumber(depths_m[i]) + " m at index " + std::to_string(i) + ")");
    }
  }
  if (!(max_depth < block.length_m - 2.0 * block.min_edge_m)) {
    throw std::invalid_argument("femInsertionForce: deepest depth " + formatNumber(max_depth) +
                                " m does not fit the block of length " +
                                formatNumber(block.length_m) + " m");
  }
  const scene::Scene scene =
      scene::parseScene(calibrationSceneYaml(block, needle), "<calibration block>");
  tissue::TissueSimOptions options = tissue::optionsFromScene(scene);
  options.depth_grid.step_m = block.depth_step_m;
  tissue::TissueSimulation sim(scene, options);
  const double y = 0.5 * block.height_m;
  const double dt = block.depth_step_m / block.insertion_velocity_m_s;

  // The needle's force at every grid point up to the deepest depth, then linear interpolation.
  std::vector<double> grid_depth{0.0};
  std::vector<double> grid_force{0.0};
  for (long k = 0; sim.gridDepth(k) <= max_depth + block.depth_step_m; ++k) {
    const tissue::StepStatus status = sim.advance(dt, y, sim.gridDepth(k));
    if (!status) {
      throw std::runtime_error("femInsertionForce: the simulation refused depth " +
                               formatNumber(sim.gridDepth(k)) + " m: " + status.message);
    }
    const tissue::InsertionStepInfo& info = sim.lastStep();
    grid_depth.push_back(sim.gridDepth(k));
    grid_force.push_back(info.tip_force_N + info.friction_force_N);
  }
  std::vector<double> force(depths_m.size());
  std::size_t j = 1;
  for (std::size_t i = 0; i < depths_m.size(); ++i) {
    while (j + 1 < grid_depth.size() && grid_depth[j] < depths_m[i]) {
      ++j;
    }
    const double w = (depths_m[i] - grid_depth[j - 1]) / (grid_depth[j] - grid_depth[j - 1]);
    force[i] = (1.0 - w) * grid_force[j - 1] + w * grid_force[j];
  }
  return force;
}

}  // namespace needle_guidance::calibration
