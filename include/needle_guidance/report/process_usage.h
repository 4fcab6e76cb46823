// What the running process has used so far, for the benchmarks' speed and memory figures.
#pragma once

#include <sys/resource.h>

namespace needle_guidance::report {

/// Peak resident memory of the process so far [MB] (ru_maxrss is in KiB on Linux).
inline double peakMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_maxrss) / 1024.0;
}

/// User + system CPU time of the process so far, all threads [s].
inline double cpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return static_cast<double>(usage.ru_utime.tv_sec + usage.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

}  // namespace needle_guidance::report
