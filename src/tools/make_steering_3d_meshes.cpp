// Generates the closed triangle meshes (OFF, mm) of the shipped 3-D steering scenes
// (config/scenes/steering_3d/): tissue blocks, a pubic arch and urethra (prostate-like), hepatic
// vessels as tubes (liver-like), and the held-out prostate variant the bench reports apart.
// Usage: make_steering_3d_meshes OUT_DIR
#include <cmath>
#include <filesystem>
#include <iostream>
#include <vector>

#include "needle_guidance/math.h"
#include "needle_guidance/needle_model/mesh_3d.h"
#include "needle_guidance/report/bench_args.h"

namespace ns = needle_guidance::needle_model;
using ns::Vector3;

namespace {

using needle_guidance::kPi;
constexpr double kMm = 1e-3;
constexpr int kSides = 16;

/// An arch in the plane x = x0: centerline y = base + rise cos(phi), z = half_width sin(phi).
std::vector<Vector3> archCenterline(double x0, double base, double rise, double half_width,
                                    double max_phi) {
  std::vector<Vector3> points;
  const int n = 24;
  for (int i = 0; i <= n; ++i) {
    const double phi = -max_phi + 2.0 * max_phi * i / n;
    points.emplace_back(x0, base + rise * std::cos(phi), half_width * std::sin(phi));
  }
  for (Vector3& p : points) {
    p *= kMm;
  }
  return points;
}

std::vector<Vector3> line(const Vector3& a_mm, const Vector3& b_mm, int pieces) {
  std::vector<Vector3> points;
  for (int i = 0; i <= pieces; ++i) {
    points.push_back((a_mm + (b_mm - a_mm) * (double(i) / pieces)) * kMm);
  }
  return points;
}

std::vector<Vector3> curve(const std::vector<Vector3>& control_mm, int pieces_per_span) {
  // Catmull-Rom through the control points.
  std::vector<Vector3> points;
  const std::size_t n = control_mm.size();
  for (std::size_t i = 0; i + 1 < n; ++i) {
    const Vector3 p0 = control_mm[i == 0 ? 0 : i - 1], p1 = control_mm[i], p2 = control_mm[i + 1],
                  p3 = control_mm[i + 2 < n ? i + 2 : n - 1];
    for (int k = 0; k < pieces_per_span; ++k) {
      const double t = double(k) / pieces_per_span;
      const Vector3 p =
          0.5 * ((2.0 * p1) + (-p0 + p2) * t + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * t * t +
                 (-p0 + 3.0 * p1 - 3.0 * p2 + p3) * t * t * t);
      points.push_back(p * kMm);
    }
  }
  points.push_back(control_mm.back() * kMm);
  return points;
}

void write(const std::filesystem::path& dir, const std::string& name, const ns::Mesh3& mesh) {
  const std::string path = (dir / name).string();
  ns::writeMesh3(path, mesh, kMm);
  ns::readMesh3(path, kMm);  // refuse to ship a mesh the loader would refuse
  std::cout << path << ": " << mesh.vertices.size() << " vertices, " << mesh.triangles.size()
            << " triangles\n";
}

}  // namespace

int main(int argc, char** argv) {
  if (needle_guidance::report::helpRequested(argc, argv)) {
    std::cout << "usage: make_steering_3d_meshes OUT_DIR\n";
    return 0;
  }
  if (argc != 2) {
    std::cerr << "usage: make_steering_3d_meshes OUT_DIR\n";
    return 2;
  }
  const std::filesystem::path dir(argv[1]);
  std::filesystem::create_directories(dir);
  try {
    // Prostate-like: perineum at x = 0, bladder side at x = 90 mm.
    write(dir, "prostate_tissue.off",
          ns::boxMesh(Vector3(0, -45, -45) * kMm, Vector3(90, 45, 45) * kMm));
    write(dir, "pubic_arch.off",
          ns::tubeMesh(archCenterline(30.0, -20.0, 36.0, 36.0, 70.0 * kPi / 180.0), 5.0 * kMm,
                       kSides));
    write(dir, "urethra.off", ns::tubeMesh(line({5, -4, 0}, {90, 0, 0}, 8), 3.0 * kMm, kSides));
    // Held-out prostate variant (never tuned on): arch deeper and wider, urethra tilted.
    write(dir, "heldout_pubic_arch.off",
          ns::tubeMesh(archCenterline(34.0, -18.0, 33.0, 40.0, 65.0 * kPi / 180.0), 5.5 * kMm,
                       kSides));
    write(dir, "heldout_urethra.off",
          ns::tubeMesh(line({5, -5, 2}, {90, 1, -2}, 8), 3.5 * kMm, kSides));
    // Liver-like: a 13 x 12 x 12 cm block with hepatic vessels as tubes.
    write(dir, "liver_tissue.off",
          ns::boxMesh(Vector3(0, -60, -60) * kMm, Vector3(130, 60, 60) * kMm));
    write(dir, "vessel_portal.off",
          ns::tubeMesh(line({45, -70, -6}, {45, 70, 6}, 10), 4.5 * kMm, kSides));
    write(dir, "vessel_hepatic.off",
          ns::tubeMesh(curve({{20, 35, -50}, {40, 12, -10}, {60, 8, 12}, {80, 30, 55}}, 8),
                       3.0 * kMm, kSides));
    write(dir, "vessel_branch.off",
          ns::tubeMesh(line({72, -12, -70}, {76, 14, 70}, 10), 3.5 * kMm, kSides));
    write(dir, "vessel_deep.off",
          ns::tubeMesh(curve({{100, -60, 30}, {104, -10, 10}, {108, 40, -25}, {110, 70, -40}}, 8),
                       4.0 * kMm, kSides));
  } catch (const std::exception& e) {
    std::cerr << "make_steering_3d_meshes: " << e.what() << "\n";
    return 1;
  }
  return 0;
}
