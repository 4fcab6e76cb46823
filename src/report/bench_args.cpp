#include "needle_guidance/report/bench_args.h"

#include <iostream>
#include <stdexcept>

namespace needle_guidance::report {

std::optional<BenchArgs> parseBenchArgs(int argc, char** argv, const std::string& tool) {
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
    } else {
      ok = false;
    }
  }
  if (!ok || args.out_dir.empty()) {
    std::cerr << "usage: " << tool << " --out DIR [--quick] [--scene SPEC]... [--trials N > 0]\n";
    return std::nullopt;
  }
  return args;
}

}  // namespace needle_guidance::report
