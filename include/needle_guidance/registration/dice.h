// Overlap of polygonal regions and the Dice similarity coefficient (dissertation 3.3.2:
// D = 2a / (2a + b + c)), computed exactly on polygons (no rasterisation) so that it varies
// smoothly with the vertex positions, as the finite-difference gradient of 3.2.4 needs.
#pragma once

#include <vector>

#include "needle_guidance/geometry/polygon.h"

namespace needle_guidance::registration {

/// A region given by closed vertex loops [m]: outer loops counter-clockwise, hole loops
/// clockwise (the region lies to the left of every loop). Loops need not be simple; the
/// signed-area conventions of Green's theorem are used throughout.
using Loops = std::vector<std::vector<geometry::Point2>>;

/// Signed area of a region [m^2] (sum of the loops' shoelace areas).
double loopsArea(const Loops& region);

/// Area of the intersection of two regions [m^2], by Green's theorem over the parts of each
/// boundary inside the other region. Shared boundary pieces with the same orientation are
/// counted once, so identical regions give exactly their area. Regions with fewer than three
/// vertices in a loop contribute nothing. Never throws.
double intersectionArea(const Loops& a, const Loops& b);

/// Dice similarity coefficient 2|A n B| / (|A| + |B|), in [0, 1]; 0 when both are empty.
double diceSimilarity(const Loops& a, const Loops& b);

/// A simple polygon as a one-loop region, oriented counter-clockwise.
Loops toLoops(const geometry::Polygon& polygon);

}  // namespace needle_guidance::registration
