// A node (or device) a procedure depends on stopped answering: what every procedure's report
// names when a fault ends it.
#pragma once

#include <string>

namespace needle_guidance::procedures {

struct Fault {
  std::string node;   ///< e.g. /tissue_sim
  double at_s = 0.0;  ///< seconds since the procedure started
  std::string reason;
  double detected_unix_s = 0.0;  ///< wall clock when it was first seen [s since 1970]
  /// "node /tissue_sim died (not registered with the master)".
  std::string toString() const { return "node " + node + " died (" + reason + ")"; }
};

}  // namespace needle_guidance::procedures
