// What the running process has used so far, for the benchmarks' memory figures (CPU time:
// needle_guidance/cpu_time.h).
#pragma once

#include <sys/resource.h>

namespace needle_guidance::report {

/// Peak resident memory of the process so far [MB] (ru_maxrss is in KiB on Linux).
inline double peakMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

}  // namespace needle_guidance::report
