// The answer of tissue_sim's ~implant_seed service, shared by its 2-D and 3-D modes.
#pragma once

#include <ros/console.h>

#include <optional>
#include <string>

#include "needle_guidance/ImplantSeed.h"

namespace needle_guidance::ros_conversions {

/// Fills `res`: refused with the reason when the tissue could not follow the needle to the
/// robot's last state (`why_not_followed` non-empty) or the simulation would not release a seed;
/// otherwise the new seed's id. Refusals are logged. `implant(&why_not)` releases the seed.
/// Returns the seed's id when one was implanted; the caller then fills its position.
template <typename Implant>
std::optional<int> answerImplantSeed(const std::string& why_not_followed, Implant implant,
                                     ImplantSeed::Response& res) {
  std::optional<int> id;
  if (!why_not_followed.empty()) {
    res.message = "seed not implanted: the tissue could not follow the needle: " + why_not_followed;
  } else {
    std::string why_not;
    id = implant(&why_not);
    res.message =
        id ? "seed " + std::to_string(*id) + " implanted" : "seed not implanted: " + why_not;
  }
  res.success = id.has_value();
  if (id) {
    res.seed_id = *id;
  } else {
    ROS_WARN_STREAM_NAMED("tissue_sim", res.message);
  }
  return id;
}

}  // namespace needle_guidance::ros_conversions
