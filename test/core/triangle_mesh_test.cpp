// Tests for geometry::meshDomain, TriangleMesh and PointLocator (dissertation 2.3.2).
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <limits>
#include <random>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/geometry/triangle_mesh.h"

namespace needle_guidance::geometry {
namespace {

constexpr double kAreaRelTol = 1e-12;
constexpr double kAngleSlackDeg = 1e-6;
constexpr double kSizeRelSlack = 1e-9;
constexpr double kOnLineTol_m = 1e-12;
constexpr double kBarycentricTol = 1e-12;

Polygon rectangle(double x0, double y0, double x1, double y1) {
  return Polygon({{x0, y0}, {x1, y0}, {x1, y1}, {x0, y1}});
}

Polygon regularPolygon(const Point2& center, double radius_m, int n, double phase_rad = 0.0) {
  std::vector<Point2> vertices;
  for (int k = 0; k < n; ++k) {
    const double angle_rad = phase_rad + 2.0 * M_PI * k / n;
    vertices.push_back(center + radius_m * Point2(std::cos(angle_rad), std::sin(angle_rad)));
  }
  return Polygon(vertices);
}

double distanceToSegment(const Point2& p, const Segment& s) {
  const Point2 ab = s.b - s.a;
  const double t = std::clamp((p - s.a).dot(ab) / ab.squaredNorm(), 0.0, 1.0);
  return (s.a + t * ab - p).norm();
}

Point2 centroidOf(const TriangleMesh& mesh, std::size_t t) {
  const auto& tri = mesh.triangles[t];
  return (mesh.nodes[static_cast<std::size_t>(tri[0])] +
          mesh.nodes[static_cast<std::size_t>(tri[1])] +
          mesh.nodes[static_cast<std::size_t>(tri[2])]) /
         3.0;
}

std::array<double, 3> edgeLengths(const TriangleMesh& mesh, std::size_t t) {
  const auto& tri = mesh.triangles[t];
  const Point2& a = mesh.nodes[static_cast<std::size_t>(tri[0])];
  const Point2& b = mesh.nodes[static_cast<std::size_t>(tri[1])];
  const Point2& c = mesh.nodes[static_cast<std::size_t>(tri[2])];
  return {(c - b).norm(), (a - c).norm(), (b - a).norm()};
}

double minAngleDeg(const TriangleMesh& mesh, std::size_t t) {
  const auto l = edgeLengths(mesh, t);
  double smallest = 180.0;
  for (std::size_t k = 0; k < 3; ++k) {
    const double opposite = l[k];
    const double side1 = l[(k + 1) % 3];
    const double side2 = l[(k + 2) % 3];
    const double cosine =
        (side1 * side1 + side2 * side2 - opposite * opposite) / (2.0 * side1 * side2);
    smallest = std::min(smallest, std::acos(std::clamp(cosine, -1.0, 1.0)) * 180.0 / M_PI);
  }
  return smallest;
}

/// Size field as specified in MeshingOptions.
double expectedSize(const MeshingOptions& options, const Point2& p) {
  double distance_m = std::numeric_limits<double>::infinity();
  for (const Point2& q : options.refine_points) {
    distance_m = std::min(distance_m, (p - q).norm());
  }
  for (const Segment& s : options.refine_lines) {
    distance_m = std::min(distance_m, distanceToSegment(p, s));
  }
  return options.min_edge_m + (options.max_edge_m - options.min_edge_m) *
                                  std::clamp(distance_m / options.grading_length_m, 0.0, 1.0);
}

std::set<std::pair<int, int>> meshEdges(const TriangleMesh& mesh) {
  std::set<std::pair<int, int>> edges;
  for (const auto& tri : mesh.triangles) {
    for (int k = 0; k < 3; ++k) {
      const int a = tri[static_cast<std::size_t>(k)];
      const int b = tri[static_cast<std::size_t>((k + 1) % 3)];
      edges.insert({std::min(a, b), std::max(a, b)});
    }
  }
  return edges;
}

/// A 10 cm x 10 cm domain with a hexagonal "prostate" and a round "rectum" below it.
struct Scene {
  Polygon domain = rectangle(-0.05, -0.05, 0.05, 0.05);
  std::vector<MeshRegion> regions{
      {"prostate", regularPolygon({0.0, 0.0}, 0.02, 6)},
      {"rectum", regularPolygon({0.0, -0.035}, 0.008, 24)},
  };
};

MeshingOptions gradedOptions() {
  MeshingOptions options;
  options.max_edge_m = 0.005;
  options.min_edge_m = 0.001;
  options.grading_length_m = 0.01;
  options.min_angle_deg = 25.0;
  options.refine_points = {{0.01, 0.005}};
  // A needle path from outside the domain (clipped at x = -0.05) to the target.
  options.refine_lines = {{{-0.06, 0.03}, {0.01, 0.005}}};
  return options;
}

void expectValidMesh(const TriangleMesh& mesh, const Polygon& domain) {
  ASSERT_GT(mesh.triangleCount(), 0u);
  ASSERT_EQ(mesh.triangle_region.size(), mesh.triangleCount());
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    ASSERT_GT(mesh.triangleArea(t), 0.0) << "triangle " << t;
  }
  EXPECT_NEAR(mesh.totalArea(), domain.area(), kAreaRelTol * domain.area());
  // Deduplicated nodes, all used.
  std::vector<std::pair<double, double>> sorted;
  for (const Point2& p : mesh.nodes) {
    sorted.emplace_back(p.x(), p.y());
  }
  std::sort(sorted.begin(), sorted.end());
  EXPECT_EQ(std::adjacent_find(sorted.begin(), sorted.end()), sorted.end());
  std::vector<bool> used(mesh.nodeCount(), false);
  for (const auto& tri : mesh.triangles) {
    for (int k : tri) {
      used.at(static_cast<std::size_t>(k)) = true;
    }
  }
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0);
}

void expectRegionTags(const TriangleMesh& mesh, const std::vector<MeshRegion>& regions) {
  ASSERT_EQ(mesh.region_names.size(), regions.size() + 1);
  std::vector<double> region_area(regions.size() + 1, 0.0);
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const Point2 c = centroidOf(mesh, t);
    const int tag = mesh.triangle_region[t];
    ASSERT_GE(tag, 0);
    ASSERT_LE(tag, static_cast<int>(regions.size()));
    for (std::size_t i = 0; i < regions.size(); ++i) {
      EXPECT_EQ(regions[i].polygon.contains(c), tag == static_cast<int>(i + 1))
          << "triangle " << t << " region " << regions[i].name;
    }
    region_area[static_cast<std::size_t>(tag)] += mesh.triangleArea(t);
  }
  for (std::size_t i = 0; i < regions.size(); ++i) {
    EXPECT_EQ(mesh.region_names[i + 1], regions[i].name);
    const double expected = regions[i].polygon.area();
    EXPECT_NEAR(region_area[i + 1], expected, kAreaRelTol * expected) << regions[i].name;
  }
}

TEST(TriangleMeshTest, MeshCoversDomainWithPositiveTriangles) {
  const Scene scene;
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, gradedOptions());
  expectValidMesh(mesh, scene.domain);
  EXPECT_EQ(mesh.region_names.front(), "tissue");
}

TEST(TriangleMeshTest, RegionTagsAndAreas) {
  const Scene scene;
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, gradedOptions());
  expectRegionTags(mesh, scene.regions);
  double background_m2 = 0.0;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    if (mesh.triangle_region[t] == 0) {
      background_m2 += mesh.triangleArea(t);
    }
  }
  const double expected =
      scene.domain.area() - scene.regions[0].polygon.area() - scene.regions[1].polygon.area();
  EXPECT_NEAR(background_m2, expected, kAreaRelTol * scene.domain.area());
}

TEST(TriangleMeshTest, QualityBoundHoldsWithoutSmallInputAngles) {
  // Input angles are all >= 60 deg here (square, hexagon, 24-gon), where Delaunay refinement
  // guarantees the bound for every triangle.
  const Scene scene;
  MeshingOptions options = gradedOptions();
  options.refine_lines.clear();
  for (double bound_deg : {20.0, 25.0, 30.0}) {
    options.min_angle_deg = bound_deg;
    const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, options);
    double smallest_deg = 180.0;
    for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
      smallest_deg = std::min(smallest_deg, minAngleDeg(mesh, t));
    }
    EXPECT_GE(smallest_deg, bound_deg - kAngleSlackDeg) << "bound " << bound_deg;
  }
}

TEST(TriangleMeshTest, QualityWithRefineLineCrossingRegion) {
  // The needle path meets the domain and the prostate outline at small angles; triangles there
  // may be below the bound (CGAL does not refine at small input angles). Every triangle below
  // the bound must touch the needle path.
  const Scene scene;
  const MeshingOptions options = gradedOptions();
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, options);
  std::size_t below = 0;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    if (minAngleDeg(mesh, t) >= options.min_angle_deg - kAngleSlackDeg) {
      continue;
    }
    ++below;
    bool touches_line = false;
    for (int k : mesh.triangles[t]) {
      touches_line = touches_line || distanceToSegment(mesh.nodes[static_cast<std::size_t>(k)],
                                                       options.refine_lines[0]) < kOnLineTol_m;
    }
    EXPECT_TRUE(touches_line) << "triangle " << t << " min angle " << minAngleDeg(mesh, t);
  }
  std::cout << "[ stats    ] " << below << " of " << mesh.triangleCount()
            << " triangles below the angle bound, all at the needle path\n";
}

TEST(TriangleMeshTest, SizeIsGradedTowardsFeatures) {
  const Scene scene;
  const MeshingOptions options = gradedOptions();
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, options);
  double near_sum_m = 0.0;
  double far_sum_m = 0.0;
  std::size_t near_count = 0;
  std::size_t far_count = 0;
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    const auto lengths = edgeLengths(mesh, t);
    const double longest_m = *std::max_element(lengths.begin(), lengths.end());
    const Point2 c = centroidOf(mesh, t);
    // The size criterion: the longest edge never exceeds the local size at the centroid.
    EXPECT_LE(longest_m, expectedSize(options, c) * (1.0 + kSizeRelSlack)) << "triangle " << t;
    const double feature_distance_m = std::min((c - options.refine_points[0]).norm(),
                                               distanceToSegment(c, options.refine_lines[0]));
    if ((c - options.refine_points[0]).norm() < 0.002) {
      near_sum_m += longest_m;
      ++near_count;
    } else if (feature_distance_m > options.grading_length_m) {
      far_sum_m += longest_m;
      ++far_count;
    }
  }
  ASSERT_GT(near_count, 0u);
  ASSERT_GT(far_count, 0u);
  const double near_mean_m = near_sum_m / near_count;
  const double far_mean_m = far_sum_m / far_count;
  // Near the target the size bound is at most min + (max - min) * 2 mm / 10 mm = 1.8 mm.
  EXPECT_LE(near_mean_m, 0.0018);
  EXPECT_LT(near_mean_m, 0.5 * far_mean_m);
  std::cout << "[ stats    ] mean longest edge near target " << near_mean_m * 1e3 << " mm, far "
            << far_mean_m * 1e3 << " mm\n";
}

TEST(TriangleMeshTest, RefineLineIsAChainOfMeshEdges) {
  const Scene scene;
  const MeshingOptions options = gradedOptions();
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, options);
  const Segment& line = options.refine_lines[0];
  const Point2 direction = line.b - line.a;
  std::vector<std::pair<double, int>> on_line;
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    if (distanceToSegment(mesh.nodes[i], line) < kOnLineTol_m) {
      on_line.emplace_back((mesh.nodes[i] - line.a).dot(direction), static_cast<int>(i));
    }
  }
  std::sort(on_line.begin(), on_line.end());
  ASSERT_GE(on_line.size(), 3u);
  // Starts where the path enters the domain (x = -0.05) and ends at the target.
  const Point2 entry(-0.05, 0.03 - 0.025 * (0.01 / 0.07));
  EXPECT_NEAR((mesh.nodes[static_cast<std::size_t>(on_line.front().second)] - entry).norm(), 0.0,
              kOnLineTol_m);
  EXPECT_EQ(mesh.nodes[static_cast<std::size_t>(on_line.back().second)], line.b);
  const auto edges = meshEdges(mesh);
  for (std::size_t k = 0; k + 1 < on_line.size(); ++k) {
    const int a = on_line[k].second;
    const int b = on_line[k + 1].second;
    EXPECT_TRUE(edges.count({std::min(a, b), std::max(a, b)})) << "gap after node " << a;
  }
}

TEST(TriangleMeshTest, RefinePointIsANode) {
  const Scene scene;
  const MeshingOptions options = gradedOptions();
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", scene.regions, options);
  EXPECT_NE(std::find(mesh.nodes.begin(), mesh.nodes.end(), options.refine_points[0]),
            mesh.nodes.end());
}

TEST(TriangleMeshTest, ConcaveDomainWithTouchingRegions) {
  // L-shaped domain; "a" shares an edge with the domain boundary, "b" shares an edge with "a".
  const Polygon domain({{0, 0}, {0.06, 0}, {0.06, 0.03}, {0.03, 0.03}, {0.03, 0.06}, {0, 0.06}});
  const std::vector<MeshRegion> regions{
      {"a", rectangle(0.0, 0.0, 0.02, 0.01)},
      {"b", Polygon({{0.02, 0.0}, {0.04, 0.0}, {0.04, 0.01}, {0.02, 0.01}})},
  };
  MeshingOptions options;
  options.max_edge_m = 0.004;
  options.min_edge_m = 0.004;
  const TriangleMesh mesh = meshDomain(domain, "background", regions, options);
  expectValidMesh(mesh, domain);
  expectRegionTags(mesh, regions);
  for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
    EXPECT_TRUE(domain.contains(centroidOf(mesh, t)));
  }
}

TEST(TriangleMeshTest, ClockwiseInputGivesCounterClockwiseTriangles) {
  const Polygon clockwise_domain({{0, 0}, {0, 0.05}, {0.05, 0.05}, {0.05, 0}});
  const std::vector<MeshRegion> regions{
      {"cw", Polygon({{0.01, 0.01}, {0.01, 0.03}, {0.03, 0.03}, {0.03, 0.01}})}};
  MeshingOptions options;
  options.max_edge_m = 0.005;
  options.min_edge_m = 0.005;
  const TriangleMesh mesh = meshDomain(clockwise_domain, "background", regions, options);
  expectValidMesh(mesh, clockwise_domain);
  expectRegionTags(mesh, regions);
}

TEST(TriangleMeshTest, BoundaryNodesLieOnTheDomainBoundary) {
  const Scene scene;
  MeshingOptions options;
  options.max_edge_m = 0.01;
  options.min_edge_m = 0.01;
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", {}, options);
  const std::vector<int> boundary = meshDomain(scene.domain, "tissue", {}, options).boundaryNodes();
  std::set<int> boundary_set(boundary.begin(), boundary.end());
  for (std::size_t i = 0; i < mesh.nodeCount(); ++i) {
    const bool on_boundary = scene.domain.distanceToBoundary(mesh.nodes[i]) < kOnLineTol_m;
    EXPECT_EQ(on_boundary, boundary_set.count(static_cast<int>(i)) == 1) << "node " << i;
  }
}

TEST(TriangleMeshTest, NearDegenerateInputIsSnapped) {
  // A region 1e-15 m inside the domain edge, a needle path starting 1e-15 m inside the domain
  // edge and a refinement point 1e-15 m off the region outline: without snapping these
  // would force refinement down to rounding-error scale.
  const Scene scene;
  constexpr double kTiny_m = 1e-15;
  const std::vector<MeshRegion> regions{{"a", rectangle(-0.05 + kTiny_m, -0.01, -0.03, 0.0)}};
  MeshingOptions options = gradedOptions();
  options.refine_lines = {{{-0.05 + kTiny_m, 0.02}, {0.0, 0.02}}, {{-0.07, -0.07}, {-0.06, 0.07}}};
  options.refine_points = {{-0.04, kTiny_m}, {0.2, 0.2}};
  const TriangleMesh mesh = meshDomain(scene.domain, "tissue", regions, options);
  expectValidMesh(mesh, scene.domain);
  expectRegionTags(mesh, regions);
  EXPECT_LT(mesh.triangleCount(), 20000u);
}

TEST(TriangleMeshTest, InvalidInputsThrow) {
  const Scene scene;
  const MeshingOptions options = gradedOptions();
  auto expect_throw_with = [&](const Polygon& domain, const std::vector<MeshRegion>& regions,
                               const MeshingOptions& opts, const std::string& fragment) {
    try {
      meshDomain(domain, "tissue", regions, opts);
      ADD_FAILURE() << "expected std::invalid_argument containing '" << fragment << "'";
    } catch (const std::invalid_argument& error) {
      EXPECT_NE(std::string(error.what()).find(fragment), std::string::npos) << error.what();
    }
  };
  expect_throw_with(scene.domain,
                    {{"bowtie", Polygon({{0, 0}, {0.01, 0.01}, {0.01, 0}, {0, 0.01}})}}, options,
                    "meshDomain: region 'bowtie' polygon self-intersects at edges 0 and 2");
  expect_throw_with(scene.domain, {{"outside", rectangle(0.04, 0.04, 0.06, 0.06)}}, options,
                    "region 'outside' polygon is not inside the domain");
  expect_throw_with(
      scene.domain,
      {{"one", rectangle(0.0, 0.0, 0.02, 0.02)}, {"two", rectangle(0.01, 0.01, 0.03, 0.03)}},
      options, "region 'one' polygon overlaps region 'two'");
  expect_throw_with(Polygon({{0, 0}, {0.1, 0.1}, {0.1, 0}, {0, 0.1}}), {}, options,
                    "domain polygon self-intersects");
  MeshingOptions bad = options;
  bad.min_edge_m = 0.01;
  expect_throw_with(scene.domain, scene.regions, bad,
                    "min_edge_m = 0.01 exceeds max_edge_m = 0.005");
  bad = options;
  bad.max_edge_m = 0.0;
  expect_throw_with(scene.domain, scene.regions, bad, "max_edge_m must be positive");
  bad = options;
  bad.min_edge_m = -0.001;
  expect_throw_with(scene.domain, scene.regions, bad, "min_edge_m must be positive");
  bad = options;
  bad.grading_length_m = 0.0;
  expect_throw_with(scene.domain, scene.regions, bad, "grading_length_m must be positive");
  bad = options;
  bad.min_angle_deg = 35.0;
  expect_throw_with(scene.domain, scene.regions, bad, "min_angle_deg must be in [0, 30]");
  bad = options;
  bad.refine_points.push_back({std::nan(""), 0.0});
  expect_throw_with(scene.domain, scene.regions, bad, "refine point 1 is not finite");
  expect_throw_with(Polygon(), {}, options, "domain polygon is empty");
}

TEST(TriangleMeshTest, PointLocatorMatchesBruteForce) {
  const Polygon domain({{0, 0}, {0.06, 0}, {0.06, 0.03}, {0.03, 0.03}, {0.03, 0.06}, {0, 0.06}});
  MeshingOptions options;
  options.max_edge_m = 0.004;
  options.min_edge_m = 0.001;
  options.refine_points = {{0.01, 0.01}};
  const TriangleMesh mesh =
      meshDomain(domain, "background", {{"a", rectangle(0.005, 0.005, 0.02, 0.02)}}, options);
  const PointLocator locator(mesh);
  std::mt19937 random(42);
  std::uniform_real_distribution<double> coordinate(-0.01, 0.07);
  constexpr double kBruteForceTol = 1e-9;  // away from edges random points are unambiguous
  int inside_count = 0;
  for (int i = 0; i < 20000; ++i) {
    const Point2 p(coordinate(random), coordinate(random));
    const auto location = locator.locate(p);
    std::vector<int> containing;
    for (std::size_t t = 0; t < mesh.triangleCount(); ++t) {
      const auto& tri = mesh.triangles[t];
      const auto w = barycentric(p, mesh.nodes[static_cast<std::size_t>(tri[0])],
                                 mesh.nodes[static_cast<std::size_t>(tri[1])],
                                 mesh.nodes[static_cast<std::size_t>(tri[2])]);
      if (*std::min_element(w.begin(), w.end()) >= -kBruteForceTol) {
        containing.push_back(static_cast<int>(t));
      }
    }
    EXPECT_EQ(domain.contains(p), !containing.empty()) << p.transpose();
    if (containing.empty()) {
      EXPECT_FALSE(location.has_value()) << p.transpose();
      continue;
    }
    ++inside_count;
    ASSERT_TRUE(location.has_value()) << p.transpose();
    EXPECT_NE(std::find(containing.begin(), containing.end(), location->triangle),
              containing.end());
    const auto& w = location->barycentric;
    EXPECT_NEAR(w[0] + w[1] + w[2], 1.0, kBarycentricTol);
    const auto& tri = mesh.triangles[static_cast<std::size_t>(location->triangle)];
    const Point2 reproduced = w[0] * mesh.nodes[static_cast<std::size_t>(tri[0])] +
                              w[1] * mesh.nodes[static_cast<std::size_t>(tri[1])] +
                              w[2] * mesh.nodes[static_cast<std::size_t>(tri[2])];
    EXPECT_NEAR((reproduced - p).norm(), 0.0, kBarycentricTol);
  }
  EXPECT_GT(inside_count, 5000);
  // Nodes and the notch.
  EXPECT_TRUE(locator.locate(mesh.nodes[0]).has_value());
  EXPECT_TRUE(locator.locate({0.0, 0.0}, 0.0).has_value());
  EXPECT_FALSE(locator.locate({0.045, 0.045}).has_value());
  EXPECT_FALSE(locator.locate({-1e-9, 0.01}).has_value());
  EXPECT_TRUE(locator.locate({-1e-9, 0.01}, 1e-8).has_value());
  EXPECT_FALSE(locator.locate({1.0, 1.0}).has_value());
}

TEST(TriangleMeshTest, BarycentricRejectsDegenerateTriangles) {
  EXPECT_THROW(barycentric({0, 0}, {0, 0}, {1, 1}, {2, 2}), std::invalid_argument);
  const auto w = barycentric({0.25, 0.25}, {0, 0}, {1, 0}, {0, 1});
  EXPECT_NEAR(w[0], 0.5, kBarycentricTol);
  EXPECT_NEAR(w[1], 0.25, kBarycentricTol);
  EXPECT_NEAR(w[2], 0.25, kBarycentricTol);
}

TEST(TriangleMeshTest, MeshingTime) {
  // Reports the meshing time; not asserted (machine dependent).
  const Polygon domain = rectangle(0.0, 0.0, 0.1, 0.1);
  for (double edge_m : {0.0063, 0.001}) {  // about 1,250 and 50,000 triangles
    MeshingOptions options;
    options.max_edge_m = edge_m;
    options.min_edge_m = edge_m;
    const auto start = std::chrono::steady_clock::now();
    const TriangleMesh mesh = meshDomain(domain, "tissue", {}, options);
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::cout << "[ timing   ] " << mesh.triangleCount() << " triangles in " << seconds << " s\n";
    const auto locate_start = std::chrono::steady_clock::now();
    const PointLocator locator(mesh);
    std::mt19937 random(42);
    std::uniform_real_distribution<double> coordinate(0.0, 0.1);
    int found = 0;
    for (int i = 0; i < 100000; ++i) {
      found += locator.locate({coordinate(random), coordinate(random)}).has_value();
    }
    const double locate_seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - locate_start).count();
    std::cout << "[ timing   ] locator build + 1e5 queries in " << locate_seconds << " s\n";
    EXPECT_EQ(found, 100000);
    expectValidMesh(mesh, domain);
  }
}

}  // namespace
}  // namespace needle_guidance::geometry

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
