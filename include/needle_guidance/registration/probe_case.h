// Seeded synthetic probe-out / probe-in slice pairs with known truth, standing in for the
// dissertation's 10 patient cases (3.3.1: 5 balloon-probe, 5 rigid-probe).
//
// Probe-out slice (x: patient left-right, y: anterior, origin at the prostate centre): a
// 100 x 117 mm field of view (traction-free outline) with the prostate (40-vertex perturbed
// ellipse, 38-46 x 28-34 mm; CG anterior, PZ wrapping it posteriorly and laterally), the rectum
// 1.5-3 mm posterior to it (balloon cases: circle of 15-18 mm diameter; rigid cases: a collapsed
// 16-19 x 8-10 mm ellipse, so that the 29 x 16.5 mm probe encloses it), the bladder anterior (a
// cavity: not meshed, its wall loaded by the hidden pressure), two pubic bones anterior and the
// sacrum posterior (fixed). The probe-in slice is made by a forward FEM on a FINER mesh
// (~2,000 nodes vs the registration's 500) with hidden per-region moduli (CG 40-90 kPa, PZ
// 20-50 kPa, surrounding 10-40 kPa) and a hidden bladder pressure (+-0.5-2 kPa normal to the
// bladder wall), the rectum wall displaced onto the probe outline along rays from the rectum
// centre (3.3.2). Balloon probe: 48 mm circle pushing the rectum's anterior wall 8-12 mm; rigid
// probe: 29 x 16.5 mm half-ellipse, anterior face flat, push 3-4.5 mm (3.3.1). Smooth
// segmentation noise (0.3 mm RMS by default) is added to the probe-in prostate and probe
// outlines (resampled at 1 mm). Homologous test points inside the gland are mapped by the
// forward FEM.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "needle_guidance/registration/point_mapping.h"
#include "needle_guidance/registration/segmentation.h"

namespace needle_guidance::registration {

enum class ProbeType { kBalloon, kRigid };
/// "balloon" or "rigid".
const char* toString(ProbeType type);

struct ProbeCaseOptions {
  double noise_rms_m = 0.0003;    ///< RMS normal displacement of the probe-in outlines [m]
  int truth_target_nodes = 2000;  ///< forward-model mesh size
  int test_points = 8;            ///< homologous test points inside the gland
  /// Hidden moduli are drawn uniformly from these ranges [Pa] (lo, hi).
  std::array<double, 2> cg_modulus_range_Pa{40e3, 90e3};
  std::array<double, 2> pz_modulus_range_Pa{20e3, 50e3};
  std::array<double, 2> surrounding_modulus_range_Pa{10e3, 40e3};
  /// |bladder pressure| range [Pa]; the sign (filling or emptying) is random.
  std::array<double, 2> bladder_pressure_range_Pa{500.0, 2000.0};
};

/// The hidden truth of a case.
struct ProbeCaseTruth {
  double cg_modulus_Pa = 0.0;
  double pz_modulus_Pa = 0.0;
  double surrounding_modulus_Pa = 0.0;
  double bladder_pressure_Pa = 0.0;  ///< > 0 pushes the bladder wall outward (filling)
  double probe_push_m = 0.0;         ///< anterior displacement of the rectum wall's top [m]
  int forward_mesh_nodes = 0;
  /// The forward FEM's map (fine mesh): T_true and T_true^-1.
  std::shared_ptr<const PointMapping> mapping;
  /// Exact (noise-free) probe-in outlines, e.g. to render images: deformed CG, PZ, bladder.
  Polygon probe_in_cg, probe_in_pz, probe_in_bladder, probe_in_prostate, probe_outline;
};

struct ProbeCase {
  ProbeType type = ProbeType::kBalloon;
  std::uint64_t seed = 0;
  SliceSegmentation probe_out;          ///< exact probe-out segmentation
  ProbeInSegmentation probe_in;         ///< noisy probe-in segmentation (input of the registration)
  std::vector<Point2> test_points_out;  ///< probe-out positions [m]; [0] = posterior CG border at
                                        ///< the midline (3.3.4)
  std::vector<Point2> test_points_in;   ///< their true probe-in positions [m]
  ProbeCaseTruth truth;
};

/// Generates case `seed` of the given probe type (deterministic for a given seed and
/// options). Throws std::runtime_error only if the generator itself fails (a bug).
ProbeCase generateProbeCase(ProbeType type, std::uint64_t seed,
                            const ProbeCaseOptions& options = {});

/// Mean distance [m] between mapping.forward(test_points_out[i]) and test_points_in[i]; points
/// the mapping cannot map count as the distance of the unmapped point (and are counted in
/// *unmapped when given).
double meanPointError(const PointMapping& mapping, const ProbeCase& probe_case,
                      int* unmapped = nullptr);

}  // namespace needle_guidance::registration
