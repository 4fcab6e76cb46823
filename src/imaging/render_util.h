// Drawing functions shared by the imager's renderers (frame_renderer.cpp,
// realistic_ultrasound.cpp): seeded random draws that are pure functions of (seed, frame, stream),
// sub-pixel drawing coordinates, and the needle resampled into short pieces. Internal to
// src/imaging.
#pragma once

#include <cmath>
#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

#include "needle_guidance/geometry/polygon.h"
#include "needle_guidance/tissue/image_warp.h"

namespace needle_guidance::imaging::render {

constexpr int kShiftBits = 8;  ///< sub-pixel precision of the drawn polygons and needle
constexpr double kShiftScale = 1 << kShiftBits;

/// SplitMix64: decorrelated 64-bit values from (seed, index, stream).
inline std::uint64_t mix(std::uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30U)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27U)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31U);
}
inline std::uint64_t streamSeed(std::uint64_t seed, std::uint64_t index, std::uint64_t stream) {
  return mix(mix(mix(seed) ^ index) ^ stream);
}
/// Uniform in [0, 1) from 64 random bits.
inline double uniform01(std::uint64_t bits) {
  return double(bits >> 11U) * (1.0 / 9007199254740992.0);
}

/// Scene points [m] as fixed-point pixel coordinates (kShiftBits fractional bits).
inline std::vector<cv::Point> fixedPoint(const std::vector<geometry::Point2>& points,
                                         const tissue::ImageGeometry& g) {
  std::vector<cv::Point> out;
  out.reserve(points.size());
  for (const geometry::Point2& p : points) {
    const cv::Point2d px = g.toPixel(p);
    out.emplace_back(int(std::lround(px.x * kShiftScale)), int(std::lround(px.y * kShiftScale)));
  }
  return out;
}

/// The needle polyline (entry -> tip, scene [m]) resampled into pieces at most step_m long:
/// the points and their arc length from the entry [m]. Fewer than 2 points: empty.
inline void resampleNeedle(const std::vector<geometry::Point2>& needle_points, double step_m,
                           std::vector<geometry::Point2>* pieces, std::vector<double>* lengths) {
  pieces->clear();
  lengths->clear();
  if (needle_points.size() < 2) {
    return;
  }
  double s = 0.0;
  pieces->push_back(needle_points.front());
  lengths->push_back(0.0);
  for (std::size_t i = 1; i < needle_points.size(); ++i) {
    const geometry::Point2 a = needle_points[i - 1], b = needle_points[i];
    const double len = (b - a).norm();
    const int n = std::max(1, int(std::ceil(len / step_m)));
    for (int k = 1; k <= n; ++k) {
      pieces->push_back(a + (b - a) * (double(k) / n));
      lengths->push_back(s + len * double(k) / n);
    }
    s += len;
  }
}

}  // namespace needle_guidance::imaging::render
