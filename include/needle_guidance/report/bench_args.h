// Command line of the benchmark tools (bench_NAME --out DIR [--quick] [--scene SPEC]
// [--trials N]).
#pragma once

#include <optional>
#include <string>
#include <vector>

namespace needle_guidance::report {

struct BenchArgs {
  std::string out_dir;                      ///< where summary.json, CSV and plot.json go
  bool quick = false;                       ///< a smaller sweep for a fast look
  std::string scene = "prostate_sagittal";  ///< scene file or embedded name (the last --scene)
  std::vector<std::string> scenes;          ///< every --scene in order (a tool may run them all)
  int trials = 0;  ///< --trials N: trials per cell for tools that run seeded trials (0 = theirs)
};

/// Parses the arguments; on a bad or missing one prints the usage of `tool` to stderr and
/// returns nullopt (the tool then exits with status 2). --help or -h prints the usage to stdout
/// and exits the process with status 0. `more_usage` (lines, each ending in a newline) follows
/// the usage line: a tool's own forms and flags.
std::optional<BenchArgs> parseBenchArgs(int argc, char** argv, const std::string& tool,
                                        const std::string& more_usage = {});

/// Whether any argument is --help or -h (a command-line tool then prints its usage to stdout
/// and exits with status 0).
bool helpRequested(int argc, char** argv);

}  // namespace needle_guidance::report
