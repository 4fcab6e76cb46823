// Validation of probe-out / probe-in segmentations (3.2.1, 3.3.2).
#include "needle_guidance/registration/segmentation.h"

#include <exception>

namespace needle_guidance::registration {
namespace {

/// Empty string when the outline is usable, else the defect prefixed by the name.
std::string outlineProblem(const std::string& name, const Outline& outline) {
  if (!outline.holes.empty()) {
    return name + ": has " + std::to_string(outline.holes.size()) +
           " inner ring(s) (hole); only hole-free outlines are supported";
  }
  if (outline.outer.size() < 3)
    return name + ": outline has fewer than 3 vertices";
  if (const auto crossing = outline.outer.selfIntersection()) {
    return name + ": outline is not simple (edges " + std::to_string(crossing->edge_a) + " and " +
           std::to_string(crossing->edge_b) + " intersect)";
  }
  return "";
}

}  // namespace

SegmentationCheck checkSegmentation(const SliceSegmentation& probe_out,
                                    const ProbeInSegmentation& probe_in) {
  SegmentationCheck check;
  const auto fail = [&](std::string problem) {
    check.ok = false;
    check.problem = std::move(problem);
    return check;
  };
  try {
    if (std::string p = outlineProblem("domain", Outline(probe_out.domain)); !p.empty())
      return fail(p);
    std::vector<std::pair<std::string, const Outline*>> structures{
        {"cg", &probe_out.cg}, {"pz", &probe_out.pz}, {"rectum", &probe_out.rectum}};
    for (std::size_t b = 0; b < probe_out.bones.size(); ++b) {
      structures.emplace_back("bone" + std::to_string(b), &probe_out.bones[b]);
    }
    if (probe_out.bladder)
      structures.emplace_back("bladder", &*probe_out.bladder);
    for (const auto& [name, outline] : structures) {
      if (std::string p = outlineProblem(name, *outline); !p.empty())
        return fail(p);
      if (!geometry::polygonInside(outline->outer, probe_out.domain))
        return fail(name + ": not inside the domain");
    }
    for (std::size_t i = 0; i < structures.size(); ++i) {
      for (std::size_t j = i + 1; j < structures.size(); ++j) {
        if (geometry::polygonsOverlap(structures[i].second->outer, structures[j].second->outer)) {
          return fail(structures[i].first + " overlaps " + structures[j].first);
        }
      }
    }
    if (std::string p = outlineProblem("probe-in prostate", probe_in.prostate); !p.empty())
      return fail(p);
    if (std::string p = outlineProblem("probe", probe_in.probe); !p.empty())
      return fail(p);
  } catch (const std::exception& e) {
    return fail(std::string("invalid geometry: ") + e.what());
  }
  return check;
}

}  // namespace needle_guidance::registration
