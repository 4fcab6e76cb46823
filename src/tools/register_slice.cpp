// register_slice: demo of deformable probe-in / probe-out registration (dissertation ch. 3) on
// the seeded synthetic cases, with the rigid and intensity baselines.
//   register_slice [--cases N] [--seed S] [--optimizer fast|sd|both] [--nodes N] [--alpha A]
//                  [--force-set bladder|gland|none] [--baselines] [--grid]
#include <cstdlib>
#include <iomanip>
#include <iostream>
#include <string>
#include <vector>

#include "needle_guidance/registration/baselines.h"
#include "needle_guidance/registration/deformable_registration.h"
#include "needle_guidance/registration/probe_case.h"
#include "needle_guidance/report/bench_args.h"

using namespace needle_guidance::registration;  // NOLINT(google-build-using-namespace): tool

namespace {

void usage(std::ostream& out = std::cerr) {
  out << "usage: register_slice [--cases N] [--seed S] [--optimizer fast|sd|both] [--nodes "
         "N] [--alpha A]\n"
         "                      [--force-set bladder|gland|none] [--baselines] [--grid]\n";
}

}  // namespace

int main(int argc, char** argv) {
  if (needle_guidance::report::helpRequested(argc, argv)) {
    usage(std::cout);
    return 0;
  }
  int cases = 5;
  std::uint64_t seed = 1;
  std::string optimizer = "fast";
  RegistrationOptions options;
  bool baselines = false, grid = false;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        usage();
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--cases")
      cases = std::stoi(value());
    else if (arg == "--seed")
      seed = std::stoull(value());
    else if (arg == "--optimizer")
      optimizer = value();
    else if (arg == "--nodes")
      options.target_nodes = std::stoi(value());
    else if (arg == "--alpha")
      options.alpha = std::stod(value());
    else if (arg == "--reg")
      options.fast_force_regularisation_m2 = std::stod(value());
    else if (arg == "--force-set") {
      const std::string v = value();
      options.force_set = v == "gland"  ? ForceSet::kGlandBoundary
                          : v == "none" ? ForceSet::kNone
                                        : ForceSet::kBladderBoundary;
    } else if (arg == "--baselines")
      baselines = true;
    else if (arg == "--grid")
      grid = true;
    else {
      usage();
      return 2;
    }
  }
  std::vector<std::pair<std::string, Optimizer>> optimizers;
  if (optimizer == "fast" || optimizer == "both")
    optimizers.emplace_back("fast", Optimizer::kFast);
  if (optimizer == "sd" || optimizer == "both")
    optimizers.emplace_back("sd", Optimizer::kSteepestDescent);
  std::cout << std::fixed << std::setprecision(3);
  std::cout << "probe    seed method      status              dice%   init%  err_mm  undeformed_mm "
               " E%     cg_kPa  pz_kPa  iters  s\n";
  for (ProbeType type : {ProbeType::kBalloon, ProbeType::kRigid}) {
    for (int k = 0; k < cases; ++k) {
      const ProbeCase pc = generateProbeCase(type, seed + static_cast<std::uint64_t>(k));
      const double undeformed = meanPointError(TranslationMapping(Point2::Zero()), pc) * 1e3;
      for (const auto& [name, opt] : optimizers) {
        options.optimizer = opt;
        const RegistrationResult r = registerSlices(pc.probe_out, pc.probe_in, options);
        const double err = r.mapping ? meanPointError(*r.mapping, pc) * 1e3 : -1.0;
        std::cout << std::setw(8) << std::left << toString(type) << " " << std::setw(4) << pc.seed
                  << " fem-" << std::setw(7) << name << " " << std::setw(19) << toString(r.status)
                  << " " << r.dice * 100 << " " << r.initial_dice * 100 << " " << err << " "
                  << undeformed << " " << r.energy_share * 100 << " "
                  << r.modulus_Pa[kCentralGland] * 1e-3 << " "
                  << r.modulus_Pa[kPeripheralZone] * 1e-3 << " " << r.iterations << " " << r.seconds
                  << "\n";
        if (grid && r.mapping) {
          for (std::size_t g = 0; g < r.mrsi_grid.probe_in.size(); ++g) {
            if (!r.mrsi_grid.inside_prostate[g])
              continue;
            const auto& q = r.mrsi_grid.probe_out[g];
            std::cout << "  grid " << r.mrsi_grid.probe_in[g].transpose() * 1e3 << " -> "
                      << (q ? std::to_string(q->x() * 1e3) + " " + std::to_string(q->y() * 1e3)
                            : std::string("outside"))
                      << "\n";
          }
        }
      }
      if (!baselines)
        continue;
      const BaselineResult rigid = rigidCentreOfMass(pc.probe_out, pc.probe_in);
      std::cout << std::setw(8) << std::left << toString(type) << " " << std::setw(4) << pc.seed
                << " rigid-com   " << std::setw(19) << toString(rigid.status) << " "
                << rigid.dice * 100 << " -      "
                << (rigid.mapping ? meanPointError(*rigid.mapping, pc) * 1e3 : -1.0) << " "
                << undeformed << " -  -  -  -  " << rigid.seconds << "\n";
      for (TextureMode tm : {TextureMode::kIndependent, TextureMode::kTissueTracking}) {
        const SyntheticImagePair images = renderProbeImages(pc, 0.0005, 0.03, 1, tm);
        for (IntensityMethod m : {IntensityMethod::kDemons, IntensityMethod::kDisOpticalFlow,
                                  IntensityMethod::kFarneback}) {
          if (!intensityMethodAvailable(m))
            continue;
          const BaselineResult ir = intensityRegistration(images, prostateLoops(pc.probe_out),
                                                          pc.probe_in.prostate.outer, m);
          std::cout << std::setw(8) << std::left << toString(type) << " " << std::setw(4) << pc.seed
                    << " " << (tm == TextureMode::kIndependent ? "I-" : "T-") << std::setw(9)
                    << toString(m) << " " << std::setw(19) << toString(ir.status) << " "
                    << ir.dice * 100 << " -      "
                    << (ir.mapping ? meanPointError(*ir.mapping, pc) * 1e3 : -1.0) << " "
                    << undeformed << " -  -  -  -  " << ir.seconds << "\n";
        }
      }
    }
  }
  return 0;
}
