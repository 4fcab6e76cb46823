// Scene text shared by the 3-D tissue tests: the needle, the lateral stage and the mesh sizes of
// a 60 mm test block.
#pragma once

#include <string>

namespace needle_guidance::tissue_3d {

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
