// Segmented probe-out and probe-in slices: the input of deformable registration with tissue
// parameter estimation (dissertation 3.2.1 "Method Input", 3.3.2). Polygons in metres, in one
// frame shared by both slices (the images are assumed rigidly pre-registered on bone, 3.3.2).
#pragma once

#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "needle_guidance/geometry/polygon.h"

namespace needle_guidance::registration {

using geometry::Point2;
using geometry::Polygon;

/// One segmented structure: an outer ring and optional inner rings (holes). The registration
/// supports hole-free, simple outlines only; inner rings and self-intersecting outer rings are
/// refused with RegistrationStatus::kInvalidSegmentation. Implicitly constructible from a
/// Polygon, so `seg.cg = polygon;` works.
struct Outline {
  Outline() = default;
  Outline(Polygon outer_ring)
      : outer(std::move(outer_ring)) {}  // NOLINT(google-explicit-constructor)
  Polygon outer;                         ///< outer ring [m], either orientation
  std::vector<Polygon> holes;            ///< inner rings [m] (refused by the registration)
};

/// The probe-out slice (fixed image F, 3.3.2): the biomechanical model is built on it.
/// CG and PZ must not overlap (they may share boundary vertices); all structures lie inside
/// `domain`. The rectum lumen is not meshed; bones are rigid and fixed (3.2.2).
struct SliceSegmentation {
  Polygon domain;                  ///< field of view / modelled tissue outline [m]; free boundary
  Outline cg;                      ///< central gland [m]
  Outline pz;                      ///< peripheral zone [m]
  Outline rectum;                  ///< rectum wall (probe entry location) [m]
  std::vector<Outline> bones;      ///< rigid, fixed structures (e.g. pubic bone) [m]
  std::optional<Outline> bladder;  ///< bladder [m]: a cavity (not meshed, its volume may change,
                                   ///< 3.2.1); its wall nodes are the default force set L (3.2.4)
};

/// The probe-in slice (moving image M, 3.3.2): only the prostate (total gland) and the probe
/// are segmented.
struct ProbeInSegmentation {
  Outline prostate;  ///< total gland [m]
  Outline probe;     ///< probe cross-section outline [m]
};

/// Result of validating a segmentation: empty `problem` when usable.
struct SegmentationCheck {
  bool ok = true;
  std::string problem;  ///< names the structure and the defect (e.g. "cg: inner ring")
};

/// Checks both slices for the defects the registration cannot handle: inner rings, fewer than
/// 3 vertices, non-finite or self-intersecting rings, structures outside the domain, CG/PZ
/// overlap. Never throws.
SegmentationCheck checkSegmentation(const SliceSegmentation& probe_out,
                                    const ProbeInSegmentation& probe_in);

}  // namespace needle_guidance::registration
