// A registration as a caller asks for it (the registration node's ~register service, a tool):
// options by name, range-checked against the defaults, and either the two segmented slices or
// a seeded synthetic probe case with known truth (3.3). One call checks, runs registerSlices and,
// on a synthetic case, measures the point error against the truth and the baselines.
#pragma once

#include <cmath>
#include <cstdint>
#include <string>

#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/segmentation.h"
#include "needle_guidance/status.h"

namespace needle_guidance::registration {

struct RegistrationRequest {
  std::string optimizer;             ///< "" (the default) | fast | steepest_descent
  double alpha = -1.0;               ///< Q = Dice - alpha E; < 0: the default
  int target_nodes = 0;              ///< mesh size; 0: the default, else in [30, 20000]
  std::uint64_t synthetic_seed = 0;  ///< > 0: register a seeded synthetic case instead
  std::string probe_type;            ///< synthetic only: "" (balloon) | balloon | rigid
  SliceSegmentation probe_out;       ///< the slices, when not synthetic
  ProbeInSegmentation probe_in;
};

struct RegistrationAnswer {
  RegistrationResult result;
  SliceSegmentation probe_out;  ///< what was registered (the synthetic case's slices, if any)
  ProbeInSegmentation probe_in;
  /// Synthetic cases with a mapping only: mean point error against the truth of the
  /// registration, the rigid centre-of-mass baseline and no registration at all [m]; NaN else.
  double point_error_m = NAN;
  double rigid_point_error_m = NAN;
  double unregistered_point_error_m = NAN;
};

/// Refused (StatusCode::kRefused, the message naming the field and the value) for an unknown
/// optimizer or probe type, a non-finite alpha, target_nodes out of range, or a geometry
/// registerSlices refuses by exception; the data problems it reports come back in
/// result.status.
Result<RegistrationAnswer> runRegistration(const RegistrationRequest& request,
                                           const RegistrationOptions& defaults);

}  // namespace needle_guidance::registration
