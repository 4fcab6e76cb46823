// Number formatting for messages (errors, logs, diagnostics), shared by every module.
#pragma once

#include <sstream>
#include <string>

namespace needle_guidance {

/// `value` with at most `significant` significant digits in the stream's default notation
/// (e.g. 0.0025, 1e-07, 42), for a message that names a value.
inline std::string formatNumber(double value, int significant = 6) {
  std::ostringstream out;
  out.precision(significant);
  out << value;
  return out.str();
}

}  // namespace needle_guidance
