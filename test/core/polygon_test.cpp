// Tests for geometry::Polygon and the polygon predicates (dissertation 2.3.2, 5.3).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

#include "needle_guidance/geometry/polygon.h"

namespace needle_guidance::geometry {
namespace {

constexpr double kAreaRelTol = 1e-12;
constexpr double kDistanceTol_m = 1e-12;

Polygon unitSquare() {
  return Polygon({{0, 0}, {1, 0}, {1, 1}, {0, 1}});
}

/// L-shape of area 3 with a concave notch at the top right (its reflex vertex is (1, 1)).
Polygon lShape() {
  return Polygon({{0, 0}, {2, 0}, {2, 1}, {1, 1}, {1, 2}, {0, 2}});
}

TEST(PolygonTest, AreaAndOrientationOfKnownShapes) {
  EXPECT_NEAR(unitSquare().signedArea(), 1.0, kAreaRelTol);
  EXPECT_TRUE(unitSquare().isCounterClockwise());

  const Polygon clockwise({{0, 0}, {0, 1}, {1, 1}, {1, 0}});
  EXPECT_NEAR(clockwise.signedArea(), -1.0, kAreaRelTol);
  EXPECT_NEAR(clockwise.area(), 1.0, kAreaRelTol);
  EXPECT_FALSE(clockwise.isCounterClockwise());
  const Polygon ccw = clockwise.counterClockwise();
  EXPECT_TRUE(ccw.isCounterClockwise());
  EXPECT_NEAR(ccw.signedArea(), 1.0, kAreaRelTol);
  EXPECT_EQ(ccw.vertices().front(), clockwise.vertices().front());

  const Polygon triangle({{0, 0}, {2, 0}, {0, 1}});
  EXPECT_NEAR(triangle.signedArea(), 1.0, kAreaRelTol);
  EXPECT_NEAR(lShape().signedArea(), 3.0, 3.0 * kAreaRelTol);

  // Far from the origin the shoelace must not lose the area to cancellation.
  const Polygon far({{1e3, 1e3}, {1e3 + 1e-3, 1e3}, {1e3 + 1e-3, 1e3 + 1e-3}, {1e3, 1e3 + 1e-3}});
  EXPECT_NEAR(far.area(), 1e-6, 1e-6 * 1e-9);
}

TEST(PolygonTest, EdgesAndBounds) {
  const Polygon square = unitSquare();
  EXPECT_EQ(square.size(), 4u);
  EXPECT_EQ(square.edge(3).a, Point2(0, 1));
  EXPECT_EQ(square.edge(3).b, Point2(0, 0));
  EXPECT_THROW(square.edge(4), std::invalid_argument);
  EXPECT_EQ(lShape().minCorner(), Point2(0, 0));
  EXPECT_EQ(lShape().maxCorner(), Point2(2, 2));
}

TEST(PolygonTest, Contains) {
  const Polygon square = unitSquare();
  EXPECT_TRUE(square.contains({0.5, 0.5}));
  EXPECT_FALSE(square.contains({1.5, 0.5}));
  EXPECT_TRUE(square.contains({1.0, 0.5}));  // on an edge
  EXPECT_TRUE(square.contains({1.0, 1.0}));  // on a vertex
  EXPECT_TRUE(square.contains({0.0, 0.0}));
  EXPECT_FALSE(square.contains({1.0 + 1e-9, 0.5}));
  EXPECT_TRUE(square.contains({1.0 + 1e-9, 0.5}, 1e-8));
  EXPECT_FALSE(square.contains({-0.5, 1.0}));  // on the line of the top edge, outside
  // Orientation does not matter.
  EXPECT_TRUE(Polygon({{0, 0}, {0, 1}, {1, 1}, {1, 0}}).contains({0.25, 0.75}));

  const Polygon l_shape = lShape();
  EXPECT_FALSE(l_shape.contains({1.5, 1.5}));  // in the concave notch
  EXPECT_TRUE(l_shape.contains({0.5, 1.5}));
  EXPECT_TRUE(l_shape.contains({1.5, 0.5}));
  EXPECT_TRUE(l_shape.contains({1.0, 1.5}));  // on the notch edge
}

TEST(PolygonTest, DistanceToBoundary) {
  const Polygon square = unitSquare();
  EXPECT_NEAR(square.distanceToBoundary({0.5, 0.5}), 0.5, kDistanceTol_m);
  EXPECT_NEAR(square.distanceToBoundary({0.5, 0.1}), 0.1, kDistanceTol_m);
  EXPECT_NEAR(square.distanceToBoundary({2.0, 0.5}), 1.0, kDistanceTol_m);
  EXPECT_NEAR(square.distanceToBoundary({2.0, 2.0}), std::sqrt(2.0), kDistanceTol_m);
  EXPECT_EQ(square.distanceToBoundary({1.0, 0.5}), 0.0);
  EXPECT_NEAR(lShape().distanceToBoundary({1.5, 1.5}), 0.5, kDistanceTol_m);
}

TEST(PolygonTest, SelfIntersectionOfBowTieIsReported) {
  const Polygon bow_tie({{0, 0}, {1, 1}, {1, 0}, {0, 1}});
  const auto crossing = bow_tie.selfIntersection();
  ASSERT_TRUE(crossing.has_value());
  EXPECT_EQ(crossing->edge_a, 0u);
  EXPECT_EQ(crossing->edge_b, 2u);
  EXPECT_NEAR(crossing->point.x(), 0.5, kDistanceTol_m);
  EXPECT_NEAR(crossing->point.y(), 0.5, kDistanceTol_m);
}

TEST(PolygonTest, SelfIntersectionNoneForSimplePolygons) {
  EXPECT_FALSE(unitSquare().selfIntersection().has_value());
  EXPECT_FALSE(lShape().selfIntersection().has_value());
  // Collinear consecutive vertices without folding back are fine.
  EXPECT_FALSE(Polygon({{0, 0}, {1, 0}, {2, 0}, {2, 1}, {0, 1}}).selfIntersection().has_value());
}

TEST(PolygonTest, SelfIntersectionOfTouchingAndDegeneratePolygons) {
  // All vertices collinear: zero area, the boundary folds back on itself.
  const Polygon collinear({{0, 0}, {1, 0}, {2, 0}});
  EXPECT_EQ(collinear.signedArea(), 0.0);
  const auto fold = collinear.selfIntersection();
  ASSERT_TRUE(fold.has_value());
  // Edges 2 and 0 fold back at vertex 0 ((2,0) -> (0,0) -> (1,0)); edges 0 and 1 do not.
  EXPECT_EQ(fold->edge_a, 0u);
  EXPECT_EQ(fold->edge_b, 2u);
  EXPECT_EQ(fold->point, Point2(0, 0));

  // A vertex touching a non-adjacent edge.
  const Polygon touching({{0, 0}, {2, 0}, {2, 2}, {1, 0}, {0, 2}});
  const auto touch = touching.selfIntersection();
  ASSERT_TRUE(touch.has_value());
  EXPECT_EQ(touch->edge_a, 0u);
  EXPECT_EQ(touch->edge_b, 2u);
  EXPECT_EQ(touch->point, Point2(1, 0));

  // A spike: the boundary goes out and straight back.
  const Polygon spike({{0, 0}, {1, 0}, {1, 1}, {1, 2}, {1, 1}, {0, 1}});
  EXPECT_TRUE(spike.selfIntersection().has_value());
}

TEST(PolygonTest, ConstructorRejectsInvalidInput) {
  EXPECT_THROW(Polygon({{0, 0}, {1, 0}}), std::invalid_argument);
  EXPECT_THROW(Polygon({{0, 0}, {1, std::numeric_limits<double>::quiet_NaN()}, {0, 1}}),
               std::invalid_argument);
  EXPECT_THROW(Polygon({{0, 0}, {1, std::numeric_limits<double>::infinity()}, {0, 1}}),
               std::invalid_argument);
  EXPECT_THROW(Polygon({{0, 0}, {1, 0}, {1, 0}, {0, 1}}), std::invalid_argument);
  EXPECT_THROW(Polygon({{0, 0}, {1, 0}, {0, 1}, {0, 0}}), std::invalid_argument);  // closed
  try {
    const Polygon too_small({{0, 0}, {1, 0}});
    FAIL() << "expected std::invalid_argument, got " << too_small.size() << " vertices";
  } catch (const std::invalid_argument& error) {
    EXPECT_NE(std::string(error.what()).find("Polygon"), std::string::npos);
    EXPECT_NE(std::string(error.what()).find("got 2"), std::string::npos);
  }
}

TEST(PolygonTest, SegmentsIntersect) {
  EXPECT_TRUE(segmentsIntersect({{0, 0}, {1, 1}}, {{0, 1}, {1, 0}}));          // crossing
  EXPECT_TRUE(segmentsIntersect({{0, 0}, {1, 0}}, {{1, 0}, {2, 5}}));          // shared end point
  EXPECT_TRUE(segmentsIntersect({{0, 0}, {2, 0}}, {{1, 0}, {1, 3}}));          // T junction
  EXPECT_TRUE(segmentsIntersect({{0, 0}, {2, 0}}, {{1, 0}, {3, 0}}));          // collinear overlap
  EXPECT_FALSE(segmentsIntersect({{0, 0}, {1, 0}}, {{2, 0}, {3, 0}}));         // collinear apart
  EXPECT_FALSE(segmentsIntersect({{0, 0}, {1, 0}}, {{0, 1}, {1, 1}}));         // parallel
  EXPECT_FALSE(segmentsIntersect({{0, 0}, {1, 1}}, {{1, 0}, {2, -1}}));        // disjoint
  EXPECT_TRUE(segmentsIntersect({{0.5, 0.5}, {0.5, 0.5}}, {{0, 0}, {1, 1}}));  // point on it
  EXPECT_FALSE(segmentsIntersect({{0.5, 0.6}, {0.5, 0.6}}, {{0, 0}, {1, 1}}));
  // Exactness: 0.1 * 3 is not 0.3 in floating point, the predicate must not care.
  EXPECT_TRUE(segmentsIntersect({{0, 0}, {0.3, 0.3}}, {{0.3, 0.3}, {1, 0}}));
}

TEST(PolygonTest, PolygonsOverlap) {
  const Polygon square = unitSquare();
  EXPECT_TRUE(polygonsOverlap(square, Polygon({{0.5, 0.5}, {1.5, 0.5}, {1.5, 1.5}, {0.5, 1.5}})));
  EXPECT_FALSE(polygonsOverlap(square, Polygon({{1, 0}, {2, 0}, {2, 1}, {1, 1}})));  // shared edge
  EXPECT_FALSE(
      polygonsOverlap(square, Polygon({{1, 1}, {2, 1}, {2, 2}, {1, 2}})));  // shared vertex
  EXPECT_TRUE(
      polygonsOverlap(square, Polygon({{0.25, 0.25}, {0.75, 0.25}, {0.5, 0.75}})));  // nested
  EXPECT_TRUE(polygonsOverlap(Polygon({{0.25, 0.25}, {0.75, 0.25}, {0.5, 0.75}}), square));
  EXPECT_TRUE(
      polygonsOverlap(square, Polygon({{0, 0}, {0.5, 0}, {0.5, 0.5}})));     // nested, touching
  EXPECT_FALSE(polygonsOverlap(square, Polygon({{3, 3}, {4, 3}, {4, 4}})));  // disjoint
  EXPECT_TRUE(polygonsOverlap(square, unitSquare()));                        // identical
  EXPECT_TRUE(polygonsOverlap(square, Polygon({{0, 0}, {0, 1}, {1, 1}, {1, 0}})));  // identical, CW
  // Crossing without any vertex inside the other polygon (a plus sign).
  EXPECT_TRUE(polygonsOverlap(Polygon({{-1, 0.4}, {2, 0.4}, {2, 0.6}, {-1, 0.6}}),
                              Polygon({{0.4, -1}, {0.6, -1}, {0.6, 2}, {0.4, 2}})));
  // The L-shape's notch holds a square that touches it along two edges.
  EXPECT_FALSE(polygonsOverlap(lShape(), Polygon({{1, 1}, {2, 1}, {2, 2}, {1, 2}})));
  EXPECT_THROW(polygonsOverlap(square, Polygon({{0, 0}, {1, 1}, {1, 0}, {0, 1}})),
               std::invalid_argument);
}

TEST(PolygonTest, SegmentIntersectsPolygon) {
  const Polygon square = unitSquare();
  EXPECT_TRUE(segmentIntersectsPolygon({{-1, 0.5}, {2, 0.5}}, square));     // crosses
  EXPECT_TRUE(segmentIntersectsPolygon({{0.2, 0.2}, {0.4, 0.4}}, square));  // inside
  EXPECT_TRUE(segmentIntersectsPolygon({{-1, 0.5}, {0.5, 0.5}}, square));   // ends inside
  EXPECT_TRUE(segmentIntersectsPolygon({{-1, -1}, {2, 2}}, square));        // through vertices
  EXPECT_FALSE(segmentIntersectsPolygon({{-1, 0}, {2, 0}}, square));        // along an edge
  EXPECT_FALSE(segmentIntersectsPolygon({{0, 2}, {2, 0}}, square));         // grazes a vertex
  EXPECT_FALSE(segmentIntersectsPolygon({{2, 2}, {3, 3}}, square));         // outside
  // The L-shape's notch: a segment across it touches the boundary only.
  EXPECT_FALSE(segmentIntersectsPolygon({{1, 2}, {2, 1}}, lShape()));
  EXPECT_TRUE(segmentIntersectsPolygon({{0.5, 2}, {2, 0.5}}, lShape()));
}

TEST(PolygonTest, PolygonInside) {
  EXPECT_TRUE(polygonInside(Polygon({{0.2, 0.2}, {0.8, 0.2}, {0.5, 0.8}}), unitSquare()));
  EXPECT_TRUE(polygonInside(unitSquare(), unitSquare()));
  EXPECT_FALSE(polygonInside(Polygon({{0.5, 0.5}, {1.5, 0.5}, {1.5, 1.5}}), unitSquare()));
  // All vertices inside the L-shape, but an edge cuts across the notch.
  EXPECT_FALSE(polygonInside(Polygon({{0.5, 1.5}, {1.5, 0.5}, {1.8, 1.9}}), lShape()));
  EXPECT_THROW(polygonInside(Polygon({{0, 0}, {1, 1}, {1, 0}, {0, 1}}), unitSquare()),
               std::invalid_argument);
}

TEST(PolygonTest, OffsetOfSquareMatchesMinkowskiArea) {
  constexpr double kSide_m = 0.02;
  constexpr double kClearance_m = 0.005;
  constexpr double kChordError_m = 1e-5;
  const Polygon square({{0, 0}, {0, kSide_m}, {kSide_m, kSide_m}, {kSide_m, 0}});  // clockwise
  const Polygon expanded = square.offset(kClearance_m, kChordError_m);
  EXPECT_TRUE(expanded.isCounterClockwise());
  EXPECT_FALSE(expanded.selfIntersection().has_value());

  // Exact area of the Minkowski sum with the disc; the arcs are replaced by chords, each at most
  // the chord error inside the arc, so at most (arc length) * (chord error) is lost.
  const double exact_area =
      kSide_m * kSide_m + 4.0 * kSide_m * kClearance_m + M_PI * kClearance_m * kClearance_m;
  const double area_tol = 2.0 * M_PI * kClearance_m * kChordError_m;
  EXPECT_LE(expanded.area(), exact_area + 1e-15);
  EXPECT_GE(expanded.area(), exact_area - area_tol);

  for (const Point2& v : square.vertices()) {
    EXPECT_TRUE(expanded.contains(v));
    EXPECT_NEAR(expanded.distanceToBoundary(v), kClearance_m, kChordError_m);
  }
  // Every vertex of the offset lies on the true offset curve.
  for (const Point2& v : expanded.vertices()) {
    EXPECT_NEAR(square.distanceToBoundary(v), kClearance_m, kDistanceTol_m);
  }
}

TEST(PolygonTest, OffsetOfConcavePolygon) {
  constexpr double kClearance_m = 0.1;
  constexpr double kChordError_m = 1e-3;
  const Polygon l_shape = lShape();
  const Polygon expanded = l_shape.offset(kClearance_m, kChordError_m);
  EXPECT_TRUE(expanded.isCounterClockwise());
  EXPECT_FALSE(expanded.selfIntersection().has_value());
  EXPECT_TRUE(polygonInside(l_shape, expanded));
  for (const Point2& v : expanded.vertices()) {
    EXPECT_FALSE(l_shape.contains(v));
    EXPECT_GE(l_shape.distanceToBoundary(v), kClearance_m - kChordError_m);
    EXPECT_LE(l_shape.distanceToBoundary(v), kClearance_m + kDistanceTol_m);
  }
  for (const Point2& v : l_shape.vertices()) {
    EXPECT_GE(expanded.distanceToBoundary(v), kClearance_m - kChordError_m);
  }
  // The reflex corner (1, 1) gets the exact corner of the two shifted edges.
  bool found_corner = false;
  for (const Point2& v : expanded.vertices()) {
    found_corner = found_corner || (v - Point2(1.1, 1.1)).norm() < 1e-12;
  }
  EXPECT_TRUE(found_corner);
}

TEST(PolygonTest, OffsetEdgeCases) {
  const Polygon square = unitSquare();
  const Polygon copy = square.offset(0.0);
  EXPECT_EQ(copy.vertices(), square.vertices());
  EXPECT_THROW(square.offset(-0.1), std::invalid_argument);
  EXPECT_THROW(square.offset(0.1, 0.0), std::invalid_argument);
  EXPECT_THROW(square.offset(0.1, 1e-300), std::invalid_argument);
  EXPECT_THROW(Polygon({{0, 0}, {1, 1}, {1, 0}, {0, 1}}).offset(0.1), std::invalid_argument);
}

}  // namespace
}  // namespace needle_guidance::geometry

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
