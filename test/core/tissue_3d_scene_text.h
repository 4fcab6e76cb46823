// Scene text shared by the 3-D tissue tests: the block, the needle, the lateral stage and the
// mesh sizes of a 60 mm test block.
#pragma once

#include <string>

namespace needle_guidance::tissue_3d {

/// The scene line and the block of a test scene: 60 × 50 × 50 mm of 20 kPa tissue, fixed at its
/// far face (x = 60 mm).
inline std::string testBlock(const std::string& name) {
  return "scene: {name: " + name + R"(, kind: tissue_3d}
block:
  min_mm: [0, -25, -25]
  max_mm: [60, 25, 25]
  material: {young_modulus_kPa: 20, poisson_ratio: 0.45}
  fixed_faces: x_max
)";
}

/// The `needle`, `workspace` and `mesh` keys of the test block's scenes. `needle_keys` adds
/// lines to the needle map (each "  key: value\n"); `fine_mm` is the mesh size at the targets.
inline std::string testNeedleStageMesh(const std::string& needle_keys = "",
                                       const std::string& fine_mm = "4") {
  return "needle:\n" + needle_keys + R"(  cutting_force_N: 0.5
  static_friction_N_per_cm: 0.3
  kinetic_friction_N_per_cm: 0.2
  insertion_velocity_mm_s: 5
  step_s: 0.1
workspace:
  stage: {y_min_mm: -20, y_max_mm: 20, z_min_mm: -20, z_max_mm: 20}
  max_tip_x_mm: 56
mesh: {size_mm: 12, fine_size_mm: )" +
         fine_mm + R"(, fine_radius_mm: 4}
)";
}

}  // namespace needle_guidance::tissue_3d
