#include "needle_guidance/report/bench_args.h"

#include <cstdlib>
#include <iostream>
#include <stdexcept>

namespace needle_guidance::report {

std::optional<BenchArgs> parseBenchArgs(int argc, char** argv, const std::string& tool,
                                        const std::string& more_usage) {
  BenchArgs args;
  bool ok = true;
  for (int i = 1; i < argc && ok; ++i) {
    const std::string arg = argv[i];
    if (arg == "--out" && i + 1 < argc) {
      args.out_dir = argv[++i];
    } else if (arg == "--scene" && i + 1 < argc) {
      args.scene = argv[++i];
      args.scenes.push_back(args.scene);
    } else if (arg == "--trials" && i + 1 < argc) {
      try {
        args.trials = std::stoi(argv[++i]);
      } catch (const std::exception&) {
        args.trials = -1;
      }
      ok = args.trials > 0;
    } else if (arg == "--quick") {
      args.quick = true;
    } else if (arg == "--help" || arg == "-h") {
      std::cout << "usage: " << tool << " --out DIR [--quick] [--scene SPEC]... [--trials N > 0]\n"
                << more_usage << "Writes DIR/summary.json, its CSVs and plot.json (scripts/bench "
                << tool.substr(tool.find('_') + 1) << " runs it and draws the plots).\n";
      std::exit(0);
    } else {
      ok = false;
    }
  }
  if (!ok || args.out_dir.empty()) {
    std::cerr << "usage: " << tool << " --out DIR [--quick] [--scene SPEC]... [--trials N > 0]\n"
              << more_usage;
    return std::nullopt;
  }
  return args;
}

bool helpRequested(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--help" || arg == "-h")
      return true;
  }
  return false;
}

}  // namespace needle_guidance::report
