// A registration request checked and run (see registration_request.h).
#include "needle_guidance/registration/registration_request.h"

#include <exception>

#include "needle_guidance/registration/baselines.h"
#include "needle_guidance/registration/probe_case.h"

namespace needle_guidance::registration {
namespace {

GeneralStatus refuse(std::string why) {
  return {StatusCode::kRefused, std::move(why)};
}

}  // namespace

Result<RegistrationAnswer> runRegistration(const RegistrationRequest& request,
                                           const RegistrationOptions& defaults) {
  RegistrationOptions options = defaults;
  if (request.optimizer == "steepest_descent") {
    options.optimizer = Optimizer::kSteepestDescent;
  } else if (!request.optimizer.empty() && request.optimizer != "fast") {
    return refuse("optimizer '" + request.optimizer + "' is not fast or steepest_descent");
  }
  if (!std::isfinite(request.alpha)) {
    return refuse("alpha is not finite");
  }
  if (request.alpha >= 0.0) {
    options.alpha = request.alpha;
  }
  if (request.target_nodes != 0) {
    if (request.target_nodes < 30 || request.target_nodes > 20000) {
      return refuse("target_nodes " + std::to_string(request.target_nodes) +
                    " is outside [30, 20000]");
    }
    options.target_nodes = request.target_nodes;
  }
  RegistrationAnswer answer;
  std::optional<ProbeCase> synthetic;
  if (request.synthetic_seed > 0) {
    ProbeType type = ProbeType::kBalloon;
    if (request.probe_type == "rigid") {
      type = ProbeType::kRigid;
    } else if (!request.probe_type.empty() && request.probe_type != "balloon") {
      return refuse("probe_type '" + request.probe_type + "' is not balloon or rigid");
    }
    synthetic = generateProbeCase(type, request.synthetic_seed);
    answer.probe_out = synthetic->probe_out;
    answer.probe_in = synthetic->probe_in;
  } else {
    answer.probe_out = request.probe_out;
    answer.probe_in = request.probe_in;
  }
  try {
    answer.result = registerSlices(answer.probe_out, answer.probe_in, options);
  } catch (const std::exception& e) {
    return refuse(e.what());
  }
  if (synthetic && hasMapping(answer.result.status) && answer.result.mapping) {
    answer.point_error_m = meanPointError(*answer.result.mapping, *synthetic);
    const BaselineResult rigid = rigidCentreOfMass(answer.probe_out, answer.probe_in);
    if (rigid.mapping) {
      answer.rigid_point_error_m = meanPointError(*rigid.mapping, *synthetic);
    }
    answer.unregistered_point_error_m =
        meanPointError(TranslationMapping(geometry::Point2::Zero()), *synthetic);
  }
  return answer;
}

}  // namespace needle_guidance::registration
