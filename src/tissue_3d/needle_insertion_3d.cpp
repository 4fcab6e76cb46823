// 3-D needle insertion: the embedded-track needle of fem::EmbeddedNeedle on a tetrahedral mesh
// (needle_insertion_3d.h).
#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance::tissue_3d {
namespace {

fem::EmbeddedNeedleParams paramsOf(const Needle3& needle, double event_warp_tolerance_m) {
  fem::EmbeddedNeedleParams p;
  p.cutting_force_N = needle.cutting_force_N;
  p.static_friction_N_per_m = needle.static_friction_N_per_m;
  p.kinetic_friction_N_per_m = needle.kinetic_friction_N_per_m;
  p.stick_velocity_m_s = needle.stick_velocity_m_s;
  p.insertion_velocity_m_s = needle.insertion_velocity_m_s;
  p.track_spacing_m = needle.track_spacing_m;
  p.follow_tissue = needle.follow_tissue;
  p.tip_radius_m = 0.5 * needle.diameter_m;
  p.section_load = needle.section_load;
  p.event_warp_tolerance_m = event_warp_tolerance_m;
  return p;
}

}  // namespace

NeedleInsertion3::NeedleInsertion3(TissueModel3& model, const Needle3& needle, double entry_x_m,
                                   double max_tip_x_m, double event_warp_tolerance_m)
    : fem::EmbeddedNeedle<3>(model.embedding(), paramsOf(needle, event_warp_tolerance_m), entry_x_m,
                             max_tip_x_m) {}

}  // namespace needle_guidance::tissue_3d
