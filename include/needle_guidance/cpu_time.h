// CPU time for the suite's speed figures: unlike wall time, it does not grow when other
// processes load the machine. A plan or a frame runs on one thread, so most figures use the
// calling thread's clock; work that may spread over threads uses the process clock.
#pragma once

#include <ctime>

namespace needle_guidance {

namespace detail {
inline double clockSeconds(clockid_t clock) {
  timespec ts{};
  clock_gettime(clock, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}
}  // namespace detail

/// CPU time of the calling thread so far [s].
inline double threadCpuSeconds() {
  return detail::clockSeconds(CLOCK_THREAD_CPUTIME_ID);
}

/// CPU time of the whole process so far, all threads [s].
inline double processCpuSeconds() {
  return detail::clockSeconds(CLOCK_PROCESS_CPUTIME_ID);
}

/// CPU seconds since construction, of the calling thread (default) or of the process.
class CpuStopwatch {
public:
  enum class Scope { kThread, kProcess };
  explicit CpuStopwatch(Scope scope = Scope::kThread) : scope_(scope), start_s_(now()) {}
  double seconds() const { return now() - start_s_; }

private:
  double now() const { return scope_ == Scope::kThread ? threadCpuSeconds() : processCpuSeconds(); }
  Scope scope_;
  double start_s_;
};

}  // namespace needle_guidance
