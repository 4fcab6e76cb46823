// DICOM-RT import: RTSTRUCT contours, RTPLAN channels and dwell times (either encoding), the
// prescription, and RTDOSE grids, into an HdrCase / DoseGrid with a report of what was read.
#include "dicom_rt_io.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::dose {
using namespace dicom_io;  // NOLINT: the shared DICOM element readers and writers

namespace {

// ---- RTSTRUCT ----------------------------------------------------------------------------------

/// Polylines of open (channel) ROIs by ROI number [m].
using RoiPolylines = std::map<int, std::vector<Point3>>;

bool isTargetRoi(const std::string& name, const std::string& interpreted_type) {
  const std::string n = lower(name);
  const std::string t = lower(interpreted_type);
  return n.find("prostate") != std::string::npos || n.find("ptv") != std::string::npos ||
         n.find("ctv") != std::string::npos || t == "ptv" || t == "ctv" || t == "gtv";
}

void readStructureSet(const Loaded& ss, HdrCase& c, RoiPolylines& polylines,
                      DicomRtImportReport& rep) {
  const std::string& file = ss.path;
  struct RoiInfo {
    std::string name;
    std::string type;
  };
  std::map<int, RoiInfo> rois;
  std::vector<int> roi_order;
  const auto roi_items = getItems(ss.data, DCM_StructureSetROISequence);
  for (std::size_t r = 0; r < roi_items.size(); ++r) {
    const std::string where = itemContext("", DCM_StructureSetROISequence, r);
    const int number = requireInt(roi_items[r], DCM_ROINumber, file, where);
    if (rois.count(number) != 0) {
      fail(file, where, tagName(DCM_ROINumber) + " " + std::to_string(number) + " appears twice");
    }
    rois[number].name = getString(roi_items[r], DCM_ROIName);
    if (rois[number].name.empty()) {
      rois[number].name = "ROI " + std::to_string(number);
    }
    roi_order.push_back(number);
  }
  const auto obs_items = getItems(ss.data, DCM_RTROIObservationsSequence);
  for (std::size_t o = 0; o < obs_items.size(); ++o) {
    const std::string where = itemContext("", DCM_RTROIObservationsSequence, o);
    const std::optional<int> ref = getInt(obs_items[o], DCM_ReferencedROINumber, file, where);
    if (ref && rois.count(*ref) != 0) {
      rois[*ref].type = getString(obs_items[o], DCM_RTROIInterpretedType);
    }
  }

  std::map<int, Structure> structures;
  const auto contour_items = getItems(ss.data, DCM_ROIContourSequence);
  for (std::size_t r = 0; r < contour_items.size(); ++r) {
    const std::string where = itemContext("", DCM_ROIContourSequence, r);
    const int number = requireInt(contour_items[r], DCM_ReferencedROINumber, file, where);
    if (rois.count(number) == 0) {
      rep.warnings.push_back(file + ": " + where + ": " + tagName(DCM_ReferencedROINumber) + " " +
                             std::to_string(number) +
                             " is not in StructureSetROISequence; ignored");
      continue;
    }
    const RoiInfo& info = rois[number];
    const bool channel = info.type == "BRACHY_CHANNEL";
    Structure s;
    s.name = info.name;
    s.role =
        isTargetRoi(info.name, info.type) ? StructureRole::kTarget : StructureRole::kOrganAtRisk;
    const auto contours = getItems(contour_items[r], DCM_ContourSequence);
    for (std::size_t k = 0; k < contours.size(); ++k) {
      const std::string cwhere =
          itemContext(where + " (ROI '" + info.name + "')", DCM_ContourSequence, k);
      const std::string type = getString(contours[k], DCM_ContourGeometricType);
      const std::vector<double> data = getNumbers(contours[k], DCM_ContourData, file, cwhere);
      if (data.size() % 3 != 0) {
        fail(file, cwhere,
             tagName(DCM_ContourData) + " has " + std::to_string(data.size()) +
                 " values, not a multiple of 3");
      }
      if (const std::optional<int> n = getInt(contours[k], DCM_NumberOfContourPoints, file, cwhere);
          n && static_cast<std::size_t>(*n) * 3 != data.size()) {
        fail(file, cwhere,
             tagName(DCM_NumberOfContourPoints) + " = " + std::to_string(*n) + " but " +
                 tagName(DCM_ContourData) + " holds " + std::to_string(data.size() / 3) +
                 " points");
      }
      std::vector<Point3> pts;
      for (std::size_t v = 0; v + 2 < data.size(); v += 3) {
        pts.emplace_back(data[v] * kMmToM, data[v + 1] * kMmToM, data[v + 2] * kMmToM);
      }
      if (channel || type == "OPEN_NONPLANAR" || type == "OPEN_PLANAR") {
        if (pts.size() >= polylines[number].size()) {  // the longest open contour of the ROI
          polylines[number] = pts;
        }
        continue;
      }
      if (type != "CLOSED_PLANAR") {
        continue;  // POINT and unknown types carry no volume
      }
      Contour contour;
      contour.z_m = pts.empty() ? 0.0 : pts.front().z();
      for (const Point3& p : pts) {
        if (std::abs(p.z() - contour.z_m) * kMToMm > kPlanarTol_mm) {
          fail(file, cwhere,
               "CLOSED_PLANAR contour is not axial (z varies from " +
                   formatNumber(contour.z_m * kMToMm) + " to " + formatNumber(p.z() * kMToMm) +
                   " mm); only axial contours are supported");
        }
        const Point2d xy = p.head<2>();
        if (contour.xy_m.empty() || (xy - contour.xy_m.back()).norm() > 1e-9) {
          contour.xy_m.push_back(xy);
        }
      }
      if (contour.xy_m.size() > 1 && (contour.xy_m.front() - contour.xy_m.back()).norm() <= 1e-9) {
        contour.xy_m.pop_back();  // closing vertex written twice
      }
      if (contour.xy_m.size() < 3) {
        rep.warnings.push_back(file + ": " + cwhere +
                               ": contour with fewer than 3 distinct vertices skipped");
        continue;
      }
      s.contours.push_back(std::move(contour));
    }
    if (!channel && !s.contours.empty()) {
      structures[number] = std::move(s);
    }
  }
  for (const int number : roi_order) {
    auto it = structures.find(number);
    if (it == structures.end()) {
      continue;
    }
    try {
      it->second.normalise();
    } catch (const std::invalid_argument& e) {
      fail(file, "ROI " + std::to_string(number), e.what());
    }
    c.structures.push_back(std::move(it->second));
  }
}

// ---- RTPLAN ------------------------------------------------------------------------------------

struct ControlPoint {
  Point3 position_mm = Point3::Zero();
  std::optional<double> relative_mm;
  double weight = 0.0;
  std::optional<Point3> orientation;
};

/// Consecutive control points at one position.
struct DwellGroup {
  std::size_t first = 0;
  std::size_t last = 0;
};

DwellTimeEncoding combine(DwellTimeEncoding a, DwellTimeEncoding b) {
  using E = DwellTimeEncoding;
  if (a == E::kNoActiveDwells) {
    return b;
  }
  if (b == E::kNoActiveDwells || a == b) {
    return a;
  }
  if (a == E::kIndistinguishable) {
    return b;
  }
  if (b == E::kIndistinguishable) {
    return a;
  }
  return E::kMixed;
}

void readSource(const Loaded& plan, HdrCase& c, DicomRtImportReport& rep,
                const std::vector<std::optional<int>>& used_sources) {
  const std::string& file = plan.path;
  const auto sources = requireItems(plan.data, DCM_SourceSequence, file, "");
  std::map<int, std::size_t> by_number;
  for (std::size_t s = 0; s < sources.size(); ++s) {
    if (const auto n =
            getInt(sources[s], DCM_SourceNumber, file, itemContext("", DCM_SourceSequence, s))) {
      by_number[*n] = s;
    }
  }
  std::vector<std::size_t> used;
  for (const auto& ref : used_sources) {
    if (!ref) {
      if (sources.size() > 1) {
        fail(file, tagName(DCM_ChannelSequence),
             "a channel has no " + tagName(DCM_ReferencedSourceNumber) + " and the plan has " +
                 std::to_string(sources.size()) + " sources");
      }
      used.push_back(0);
      continue;
    }
    const auto it = by_number.find(*ref);
    if (it == by_number.end()) {
      fail(file, tagName(DCM_ChannelSequence),
           tagName(DCM_ReferencedSourceNumber) + " " + std::to_string(*ref) + " is not in " +
               tagName(DCM_SourceSequence));
    }
    used.push_back(it->second);
  }
  if (used.empty()) {
    used.push_back(0);
  }
  std::sort(used.begin(), used.end());
  used.erase(std::unique(used.begin(), used.end()), used.end());
  std::optional<double> rakr;
  for (const std::size_t s : used) {
    const std::string where = itemContext("", DCM_SourceSequence, s);
    const double value = requireNumber(sources[s], DCM_ReferenceAirKermaRate, file, where);
    if (!(value > 0.0)) {
      fail(file, where,
           tagName(DCM_ReferenceAirKermaRate) + " = " + formatNumber(value) + " uGy/h must be > 0");
    }
    if (rakr && std::abs(*rakr - value) > 1e-9 * value) {
      fail(file, where,
           "channels use sources of different " + tagName(DCM_ReferenceAirKermaRate) + " (" +
               formatNumber(*rakr) + " and " + formatNumber(value) +
               "); an HdrCase holds a single air-kerma strength");
    }
    rakr = value;
  }
  DcmItem* src = sources[used.front()];
  // Reference Air Kerma Rate [uGy h^-1 at 1 m] is numerically the air-kerma strength in U
  // (1 U = 1 uGy m^2 h^-1). Applied as written: the decay to the treatment date is the
  // planning system's business and the treatment date is usually anonymised.
  c.air_kerma_strength_U = *rakr;
  rep.source_type = getString(src, DCM_SourceType);
  if (const auto length = getNumber(src, DCM_ActiveSourceLength, file,
                                    itemContext("", DCM_SourceSequence, used.front()))) {
    rep.active_source_length_m = *length * kMmToM;
  }
  rep.source_strength_reference_date = getString(src, DCM_SourceStrengthReferenceDate);
}

void readPrescription(const Loaded& plan, HdrCase& c, DicomRtImportReport& rep) {
  const std::string& file = plan.path;
  std::optional<double> setup_dose;
  int fractions = 1;
  const auto groups = getItems(plan.data, DCM_FractionGroupSequence);
  if (groups.size() > 1) {
    rep.warnings.push_back(
        file + ": " + std::to_string(groups.size()) +
        " fraction groups; the first one is used for fractions and prescription");
  }
  if (!groups.empty()) {
    const std::string where = itemContext("", DCM_FractionGroupSequence, 0);
    if (const auto n = getInt(groups[0], DCM_NumberOfFractionsPlanned, file, where)) {
      if (*n < 1) {
        fail(file, where,
             tagName(DCM_NumberOfFractionsPlanned) + " = " + std::to_string(*n) + " must be >= 1");
      }
      fractions = *n;
    }
    const auto setups = getItems(groups[0], DCM_ReferencedBrachyApplicationSetupSequence);
    for (std::size_t s = 0; s < setups.size(); ++s) {
      const auto dose =
          getNumber(setups[s], DCM_BrachyApplicationSetupDose, file,
                    itemContext(where, DCM_ReferencedBrachyApplicationSetupSequence, s));
      if (dose && !setup_dose) {
        setup_dose = dose;
      } else if (dose && std::abs(*dose - *setup_dose) > 1e-9) {
        rep.warnings.push_back(file + ": application setups have different " +
                               tagName(DCM_BrachyApplicationSetupDose) + "; the first (" +
                               formatNumber(*setup_dose) + " Gy) is used");
      }
    }
  }
  rep.fractions_planned = fractions;
  std::optional<double> target_dose;
  const auto refs = getItems(plan.data, DCM_DoseReferenceSequence);
  for (std::size_t r = 0; r < refs.size() && !target_dose; ++r) {
    if (getString(refs[r], DCM_DoseReferenceType) == "TARGET") {
      target_dose = getNumber(refs[r], DCM_TargetPrescriptionDose, file,
                              itemContext("", DCM_DoseReferenceSequence, r));
    }
  }
  double rx = 0.0;
  if (setup_dose) {
    rx = *setup_dose;  // per fraction by definition
  } else if (target_dose) {
    rx = *target_dose / fractions;
    if (fractions > 1) {
      rep.warnings.push_back(file + ": prescription per fraction taken as " +
                             tagName(DCM_TargetPrescriptionDose) + " / " +
                             std::to_string(fractions) + " fractions");
    }
  } else {
    fail(file, "",
         "no prescription: neither " + tagName(DCM_BrachyApplicationSetupDose) + " nor a TARGET " +
             tagName(DCM_TargetPrescriptionDose));
  }
  if (!(rx > 0.0)) {
    fail(file, "", "prescription dose " + formatNumber(rx) + " Gy must be > 0");
  }
  if (setup_dose && target_dose &&
      std::abs(*target_dose - rx * fractions) > 1e-3 * rx * fractions &&
      std::abs(*target_dose - rx) > 1e-3 * rx) {
    rep.warnings.push_back(file + ": " + tagName(DCM_TargetPrescriptionDose) + " " +
                           formatNumber(*target_dose) + " Gy disagrees with " +
                           tagName(DCM_BrachyApplicationSetupDose) + " " + formatNumber(rx) +
                           " Gy; the latter is used");
  }
  c.prescription_Gy = rx;
}

/// Reads one channel into a catheter + dwells + times; returns its encoding.
/// The channel's Brachy Control Point Sequence (3.8.2 of the RT Brachy module).
std::vector<ControlPoint> readControlPoints(DcmItem* channel, const std::string& file,
                                            const std::string& ch_where) {
  const auto cp_items = requireItems(channel, DCM_BrachyControlPointSequence, file, ch_where);
  std::vector<ControlPoint> cps;
  for (std::size_t k = 0; k < cp_items.size(); ++k) {
    const std::string cw = itemContext(ch_where, DCM_BrachyControlPointSequence, k);
    ControlPoint cp;
    const std::vector<double> pos =
        requireNumbers(cp_items[k], DCM_ControlPoint3DPosition, 3, file, cw);
    cp.position_mm = Point3(pos[0], pos[1], pos[2]);
    cp.relative_mm = getNumber(cp_items[k], DCM_ControlPointRelativePosition, file, cw);
    cp.weight = requireNumber(cp_items[k], DCM_CumulativeTimeWeight, file, cw);
    const std::vector<double> orient =
        getNumbers(cp_items[k], DCM_ControlPointOrientation, file, cw);
    if (orient.size() == 3) {
      const Point3 o(orient[0], orient[1], orient[2]);
      if (o.norm() > 0.5) {  // a direction, not a placeholder
        cp.orientation = o.normalized();
      }
    } else if (!orient.empty()) {
      fail(file, cw,
           tagName(DCM_ControlPointOrientation) + " has " + std::to_string(orient.size()) +
               " values, expected 3");
    }
    cps.push_back(cp);
  }
  if (const auto n = getInt(channel, DCM_NumberOfControlPoints, file, ch_where);
      n && static_cast<std::size_t>(*n) != cps.size()) {
    fail(file, ch_where,
         tagName(DCM_NumberOfControlPoints) + " = " + std::to_string(*n) + " but " +
             tagName(DCM_BrachyControlPointSequence) + " has " + std::to_string(cps.size()) +
             " items");
  }
  return cps;
}

/// Consecutive control points at the same position: one dwell position each.
std::vector<DwellGroup> groupDwellPositions(const std::vector<ControlPoint>& cps) {
  std::vector<DwellGroup> groups;
  for (std::size_t k = 0; k < cps.size(); ++k) {
    const bool same =
        !groups.empty() &&
        (cps[k].position_mm - cps[groups.back().last].position_mm).norm() <= kSamePositionTol_mm &&
        (!cps[k].relative_mm || !cps[groups.back().last].relative_mm ||
         std::abs(*cps[k].relative_mm - *cps[groups.back().last].relative_mm) <=
             kSamePositionTol_mm);
    if (same) {
      groups.back().last = k;
    } else {
      groups.push_back({k, k});
    }
  }
  return groups;
}

/// The channel's dwell weights, decoded from the cumulative time weights.
struct DecodedWeights {
  DwellTimeEncoding encoding = DwellTimeEncoding::kNoActiveDwells;
  std::vector<double> weights;  ///< one per group
  double final_weight = 0.0;    ///< the weight that ChannelTotalTime corresponds to
};

/// Decodes the time weights (see DwellTimeEncoding): a group's weight is the change within it.
DecodedWeights decodeWeights(DcmItem* channel, const std::vector<ControlPoint>& cps,
                             const std::vector<DwellGroup>& groups, double total_time_s,
                             const std::string& file, const std::string& ch_where) {
  double max_abs_weight = 0.0;
  for (const ControlPoint& cp : cps) {
    max_abs_weight = std::max(max_abs_weight, std::abs(cp.weight));
  }
  const double tol = 1e-6 * std::max(1.0, max_abs_weight);
  std::vector<double> weights;
  bool standard = true;  // monotonic, nothing spent between groups
  bool per_pair = true;  // every group starts again from 0
  int active_groups = 0;
  for (std::size_t g = 0; g < groups.size(); ++g) {
    const double w = cps[groups[g].last].weight - cps[groups[g].first].weight;
    if (w < -tol) {
      fail(file, itemContext(ch_where, DCM_BrachyControlPointSequence, groups[g].last),
           tagName(DCM_CumulativeTimeWeight) + " decreases within a dwell position (" +
               formatNumber(cps[groups[g].first].weight) + " -> " +
               formatNumber(cps[groups[g].last].weight) + ")");
    }
    weights.push_back(std::max(w, 0.0));
    if (w > tol) {
      ++active_groups;
    }
    if (std::abs(cps[groups[g].first].weight) > tol) {
      per_pair = false;
    }
    if (g > 0 && std::abs(cps[groups[g].first].weight - cps[groups[g - 1].last].weight) > tol) {
      standard = false;
    }
  }
  DwellTimeEncoding encoding = DwellTimeEncoding::kNoActiveDwells;
  if (active_groups > 0) {
    if (standard && per_pair) {
      encoding = DwellTimeEncoding::kIndistinguishable;
    } else if (standard) {
      encoding = DwellTimeEncoding::kStandardCumulative;
    } else if (per_pair) {
      encoding = DwellTimeEncoding::kPerPairNonCumulative;
    } else {
      fail(file, ch_where,
           tagName(DCM_CumulativeTimeWeight) +
               " fits neither the cumulative encoding (time spent between dwell positions) nor the "
               "per-pair encoding (a dwell position not starting from 0)");
    }
  }
  double weight_sum = 0.0;
  for (const double w : weights) {
    weight_sum += w;
  }
  double final_weight = weight_sum;
  if (const auto fw = getNumber(channel, DCM_FinalCumulativeTimeWeight, file, ch_where)) {
    // The decoded weights must add up to the final weight; rounding of the written weights
    // (DS strings) is allowed for.
    if (std::abs(*fw - weight_sum) > std::max(1e-3, 1e-4 * std::abs(*fw))) {
      fail(file, ch_where,
           "the dwell weights decoded from " + tagName(DCM_CumulativeTimeWeight) + " (" +
               toString(encoding) + ") add up to " + formatNumber(weight_sum) + ", but " +
               tagName(DCM_FinalCumulativeTimeWeight) + " = " + formatNumber(*fw));
    }
    final_weight = *fw;
  }
  if (final_weight <= 0.0 && total_time_s > 0.0) {
    fail(file, ch_where,
         tagName(DCM_ChannelTotalTime) + " = " + formatNumber(total_time_s) +
             " s but the time weights are all zero");
  }
  return {encoding, weights, final_weight};
}

/// The catheter polyline: the referenced BRACHY_CHANNEL ROI (its first point made the distal
/// tip), else the dwell positions.
Catheter channelCatheter(DcmItem* channel, const std::optional<int>& channel_number,
                         const std::vector<Point3>& dwell_points, const RoiPolylines& polylines,
                         const std::string& file, const std::string& ch_where,
                         std::size_t catheters_so_far, DicomRtImportReport& rep) {
  Catheter catheter;
  catheter.name = getString(channel, DCM_SourceApplicatorID);
  if (catheter.name.empty()) {
    catheter.name = "channel " + (channel_number ? std::to_string(*channel_number)
                                                 : std::to_string(catheters_so_far + 1));
  }
  if (const auto roi = getInt(channel, DCM_ReferencedROINumber, file, ch_where)) {
    const auto it = polylines.find(*roi);
    if (it != polylines.end() && it->second.size() >= 2) {
      catheter.points_m = it->second;
    } else if (!rep.structure_set_path.empty()) {
      rep.warnings.push_back(
          file + ": " + ch_where + ": " + tagName(DCM_ReferencedROINumber) + " " +
          std::to_string(*roi) +
          " has no open contour in the RTSTRUCT; catheter taken from the dwell positions");
    }
  }
  if (!catheter.points_m.empty()) {
    // First point = distal tip: the dwell nearest the tip must project nearer the first point.
    const Projection a = projectOntoPolyline(catheter.points_m, dwell_points.front());
    const Projection b = projectOntoPolyline(catheter.points_m, dwell_points.back());
    if (dwell_points.size() > 1 && a.arc_m > b.arc_m + 1e-9) {
      std::reverse(catheter.points_m.begin(), catheter.points_m.end());
      rep.warnings.push_back(file + ": catheter '" + catheter.name +
                             "': ROI polyline reversed so that its first point is the distal tip");
    }
  } else {
    for (const Point3& p : dwell_points) {
      if (catheter.points_m.empty() ||
          (p - catheter.points_m.back()).norm() > kSamePositionTol_mm * kMmToM) {
        catheter.points_m.push_back(p);
      }
    }
  }
  return catheter;
}

/// The source axis at dwell n: the control point's orientation (made to point to the tip, checked
/// against the catheter), else the catheter direction.
Point3 dwellAxis(const std::optional<Point3>& tag, const Point3& geometric,
                 const Catheter& catheter, std::size_t n, const std::string& file,
                 const std::string& ch_where, DicomRtImportReport& rep) {
  if (tag) {
    Point3 axis = *tag;
    if (geometric.norm() > 0.5) {
      if (axis.dot(geometric) < 0.0) {
        axis = -axis;
        ++rep.orientation_flips;
      }
      const double angle = std::acos(std::clamp(axis.dot(geometric), -1.0, 1.0));
      rep.max_axis_deviation_rad = std::max(rep.max_axis_deviation_rad, angle);
      if (angle > kAxisWarnAngle_rad) {
        rep.warnings.push_back(file + ": catheter '" + catheter.name + "' dwell " +
                               std::to_string(n) + ": " + tagName(DCM_ControlPointOrientation) +
                               " is " + formatNumber(angle * 180.0 / M_PI) +
                               " deg off the catheter direction");
      }
    }
    return axis;
  }
  if (geometric.norm() > 0.5)
    return geometric;
  fail(file, ch_where,
       "cannot tell the source axis of dwell position " + std::to_string(n) + ": no " +
           tagName(DCM_ControlPointOrientation) +
           " and no catheter direction (fewer than two points)");
}

DwellTimeEncoding readChannel(const Loaded& plan, DcmItem* channel, const std::string& where,
                              const RoiPolylines& polylines, HdrCase& c, DicomRtImportReport& rep) {
  const std::string& file = plan.path;
  const std::optional<int> channel_number = getInt(channel, DCM_ChannelNumber, file, where);
  const std::string ch_where =
      where + (channel_number ? " (channel " + std::to_string(*channel_number) + ")" : "");
  const double total_time_s = requireNumber(channel, DCM_ChannelTotalTime, file, ch_where);
  if (total_time_s < 0.0) {
    fail(file, ch_where,
         tagName(DCM_ChannelTotalTime) + " = " + formatNumber(total_time_s) + " s is negative");
  }
  const std::string movement = getString(channel, DCM_SourceMovementType);
  if (movement == "DYNAMIC") {
    fail(file, ch_where,
         tagName(DCM_SourceMovementType) +
             " DYNAMIC is not supported (stepwise dwell positions only)");
  }
  const std::vector<ControlPoint> cps = readControlPoints(channel, file, ch_where);
  const std::vector<DwellGroup> groups = groupDwellPositions(cps);
  const DecodedWeights decoded = decodeWeights(channel, cps, groups, total_time_s, file, ch_where);

  // Dwell positions ordered from the tip (increasing relative position when every group has one).
  std::vector<std::size_t> order(groups.size());
  for (std::size_t g = 0; g < groups.size(); ++g) {
    order[g] = g;
  }
  const bool have_relative = std::all_of(groups.begin(), groups.end(), [&](const DwellGroup& g) {
    return cps[g.first].relative_mm.has_value();
  });
  if (have_relative) {
    std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
      return *cps[groups[a].first].relative_mm < *cps[groups[b].first].relative_mm;
    });
  }
  std::vector<Point3> dwell_points;
  for (const std::size_t g : order) {
    dwell_points.push_back(cps[groups[g].first].position_mm * kMmToM);
  }
  Catheter catheter = channelCatheter(channel, channel_number, dwell_points, polylines, file,
                                      ch_where, c.catheters.size(), rep);

  const int catheter_index = static_cast<int>(c.catheters.size());
  for (std::size_t n = 0; n < order.size(); ++n) {
    const DwellGroup& g = groups[order[n]];
    DwellPosition d;
    d.catheter = catheter_index;
    d.index = static_cast<int>(n);
    d.position_m = dwell_points[n];
    std::optional<Point3> tag;
    for (std::size_t k = g.first; k <= g.last && !tag; ++k) {
      tag = cps[k].orientation;
    }
    d.axis = dwellAxis(tag, tipDirection(catheter.points_m, d.position_m), catheter, n, file,
                       ch_where, rep);
    c.dwells.push_back(d);
    const double t = decoded.final_weight > 0.0
                         ? decoded.weights[order[n]] * total_time_s / decoded.final_weight
                         : 0.0;
    c.dwell_times_s.push_back(t);
    rep.total_dwell_time_s += t;
  }
  c.catheters.push_back(std::move(catheter));
  return decoded.encoding;
}

void readPlan(const Loaded& plan, const RoiPolylines& polylines, HdrCase& c,
              DicomRtImportReport& rep) {
  const std::string& file = plan.path;
  const std::string type = getString(plan.data, DCM_BrachyTreatmentType);
  if (!type.empty() && type != "HDR" && type != "PDR") {
    rep.warnings.push_back(file + ": " + tagName(DCM_BrachyTreatmentType) + " is " + type +
                           " (expected HDR or PDR)");
  }
  const auto setups =
      requireItems(plan.data, DCM_ApplicationSetupSequence, file, "not a brachytherapy plan");
  std::vector<std::optional<int>> used_sources;
  double trak = 0.0;
  bool have_trak = false;
  for (std::size_t a = 0; a < setups.size(); ++a) {
    const std::string where = itemContext("", DCM_ApplicationSetupSequence, a);
    if (const auto t = getNumber(setups[a], DCM_TotalReferenceAirKerma, file, where)) {
      trak += *t;
      have_trak = true;
    }
    const auto channels = requireItems(setups[a], DCM_ChannelSequence, file, where);
    for (std::size_t ch = 0; ch < channels.size(); ++ch) {
      const std::string cw = itemContext(where, DCM_ChannelSequence, ch);
      used_sources.push_back(getInt(channels[ch], DCM_ReferencedSourceNumber, file, cw));
      const DwellTimeEncoding e = readChannel(plan, channels[ch], cw, polylines, c, rep);
      rep.channel_encodings.push_back(e);
      rep.encoding = combine(rep.encoding, e);
    }
  }
  readSource(plan, c, rep, used_sources);
  if (have_trak) {
    rep.total_reference_air_kerma_uGy = trak;
    // TRAK = S_K x total time [h]; an independent check of the decoded dwell times.
    const double expected = c.air_kerma_strength_U * rep.total_dwell_time_s / 3600.0;
    const double tol = 1e-2 * std::max(expected, 1e-6);
    if (std::abs(trak - expected) > tol &&
        std::abs(trak - expected * rep.fractions_planned) > tol) {
      rep.warnings.push_back(
          file + ": " + tagName(DCM_TotalReferenceAirKerma) + " = " + formatNumber(trak) +
          " uGy but S_K x total dwell time = " + formatNumber(expected) + " uGy");
    }
  }
}

}  // namespace

// ---- public API --------------------------------------------------------------------------------

std::string toString(DwellTimeEncoding encoding) {
  switch (encoding) {
    case DwellTimeEncoding::kNoActiveDwells:
      return "no_active_dwells";
    case DwellTimeEncoding::kStandardCumulative:
      return "standard_cumulative";
    case DwellTimeEncoding::kPerPairNonCumulative:
      return "per_pair_non_cumulative";
    case DwellTimeEncoding::kIndistinguishable:
      return "indistinguishable";
    case DwellTimeEncoding::kMixed:
      return "mixed";
  }
  return "unknown";
}

DicomRtFiles findDicomRtFiles(const std::string& dir) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) {
    fail(dir, "", "not a directory");
  }
  struct Candidate {
    std::string path;
    std::string sop_instance;
    std::string referenced;  ///< plan: its structure set; dose: its plan
  };
  std::vector<Candidate> plans, structs, doses;
  std::vector<std::string> paths;
  for (const fs::directory_entry& entry : fs::directory_iterator(dir, ec)) {
    if (entry.is_regular_file(ec)) {
      paths.push_back(entry.path().string());
    }
  }
  if (ec) {
    fail(dir, "", "cannot list the directory: " + ec.message());
  }
  std::sort(paths.begin(), paths.end());
  for (const std::string& path : paths) {
    // Only files with the DICM preamble or a .dcm extension: DCMTK would otherwise try to
    // parse any text file as a raw data set.
    bool dicm = false;
    {
      std::ifstream in(path, std::ios::binary);
      char magic[132] = {};
      dicm = in.read(magic, sizeof(magic)) && std::string(magic + 128, 4) == "DICM";
    }
    if (!dicm && lower(fs::path(path).extension().string()) != ".dcm") {
      continue;
    }
    DcmFileFormat ff;
    // Large values (pixel data) stay on disk: only the header elements are needed here.
    if (ff.loadFile(path.c_str(), EXS_Unknown, EGL_noChange, DCM_MaxReadLength, ERM_autoDetect)
            .bad()) {
      continue;
    }
    DcmDataset* ds = ff.getDataset();
    const std::string sop = getString(ds, DCM_SOPClassUID);
    const std::string modality = getString(ds, DCM_Modality);
    Candidate cand{path, getString(ds, DCM_SOPInstanceUID), {}};
    DcmItem* ref = nullptr;
    if (sop == UID_RTPlanStorage || (sop.empty() && modality == "RTPLAN")) {
      if (ds->findAndGetSequenceItem(DCM_ReferencedStructureSetSequence, ref).good() &&
          ref != nullptr) {
        cand.referenced = getString(ref, DCM_ReferencedSOPInstanceUID);
      }
      plans.push_back(cand);
    } else if (sop == UID_RTStructureSetStorage || (sop.empty() && modality == "RTSTRUCT")) {
      structs.push_back(cand);
    } else if (sop == UID_RTDoseStorage || (sop.empty() && modality == "RTDOSE")) {
      if (ds->findAndGetSequenceItem(DCM_ReferencedRTPlanSequence, ref).good() && ref != nullptr) {
        cand.referenced = getString(ref, DCM_ReferencedSOPInstanceUID);
      }
      doses.push_back(cand);
    }
  }
  auto list = [](const std::vector<Candidate>& v) {
    std::string s;
    for (const Candidate& c : v) {
      s += (s.empty() ? "" : ", ") + c.path;
    }
    return s;
  };
  if (plans.empty()) {
    fail(dir, "", "no RTPLAN (RT Plan Storage) object in the directory");
  }
  if (plans.size() > 1) {
    fail(dir, "", "several RTPLAN objects (" + list(plans) + "); give the files explicitly");
  }
  DicomRtFiles files;
  files.plan = plans.front().path;
  auto pick = [&](const std::vector<Candidate>& v, bool by_plan_reference,
                  const std::string& what) -> std::string {
    if (v.empty()) {
      return {};
    }
    if (v.size() == 1) {
      return v.front().path;
    }
    std::vector<Candidate> matching;
    for (const Candidate& c : v) {
      const bool match =
          by_plan_reference
              ? (!c.referenced.empty() && c.referenced == plans.front().sop_instance)
              : (!c.sop_instance.empty() && c.sop_instance == plans.front().referenced);
      if (match) {
        matching.push_back(c);
      }
    }
    if (matching.size() != 1) {
      fail(dir, "",
           "several " + what + " objects (" + list(v) + ") and " + std::to_string(matching.size()) +
               " of them match the plan's references");
    }
    return matching.front().path;
  };
  files.structure_set = pick(structs, false, "RTSTRUCT");
  files.dose = pick(doses, true, "RTDOSE");
  return files;
}

HdrCase importDicomRt(const std::string& dir, DicomRtImportReport* report,
                      const DicomRtImportOptions& options) {
  const DicomRtFiles files = findDicomRtFiles(dir);
  return importDicomRt(files.plan, files.structure_set, report, options);
}

HdrCase importDicomRt(const std::string& plan_path, const std::string& structure_set_path,
                      DicomRtImportReport* report, const DicomRtImportOptions& options) {
  DicomRtImportReport rep;
  rep.plan_path = plan_path;
  rep.structure_set_path = structure_set_path;
  const Loaded plan = load(plan_path, "RTPLAN", UID_RTPlanStorage);
  HdrCase c;
  c.name = getString(plan.data, DCM_RTPlanLabel);
  if (c.name.empty()) {
    c.name = std::filesystem::path(plan_path).stem().string();
  }
  if (!options.source_name.empty()) {
    c.source = options.source_name;
  }
  RoiPolylines polylines;
  if (!structure_set_path.empty()) {
    const Loaded ss = load(structure_set_path, "RTSTRUCT", UID_RTStructureSetStorage);
    readStructureSet(ss, c, polylines, rep);
  }
  readPrescription(plan, c, rep);
  readPlan(plan, polylines, c, rep);
  if (c.dwells.empty()) {
    fail(plan_path, "", "the plan has no dwell positions");
  }
  if (report != nullptr) {
    *report = std::move(rep);
  }
  return c;
}

namespace {

DoseGrid readDoseGrid(const Loaded& l) {
  const std::string& file = l.path;
  DcmDataset* ds = l.data;
  DoseGrid g;
  const std::string units = getString(ds, DCM_DoseUnits);
  if (units != "GY") {
    fail(file, "", tagName(DCM_DoseUnits) + " is '" + units + "', expected GY");
  }
  g.summation_type = getString(ds, DCM_DoseSummationType);
  const int rows = requireInt(ds, DCM_Rows, file, "");
  const int cols = requireInt(ds, DCM_Columns, file, "");
  const std::vector<double> offsets_mm = getNumbers(ds, DCM_GridFrameOffsetVector, file, "");
  int frames = 1;
  if (const auto n = getInt(ds, DCM_NumberOfFrames, file, "")) {
    frames = *n;
  } else if (offsets_mm.size() > 1) {
    fail(file, "",
         tagName(DCM_NumberOfFrames) + " is missing but " + tagName(DCM_GridFrameOffsetVector) +
             " has " + std::to_string(offsets_mm.size()) + " values");
  }
  if (rows < 1 || cols < 1 || frames < 1) {
    fail(file, "",
         "Rows x Columns x NumberOfFrames = " + std::to_string(rows) + " x " +
             std::to_string(cols) + " x " + std::to_string(frames) + " must all be >= 1");
  }
  const std::vector<double> ipp = requireNumbers(ds, DCM_ImagePositionPatient, 3, file, "");
  const std::vector<double> iop = requireNumbers(ds, DCM_ImageOrientationPatient, 6, file, "");
  const double identity[6] = {1, 0, 0, 0, 1, 0};
  for (int a = 0; a < 6; ++a) {
    if (std::abs(iop[static_cast<std::size_t>(a)] - identity[a]) > kOrientationTol) {
      fail(file, "",
           tagName(DCM_ImageOrientationPatient) + " = " + formatNumbers(iop) +
               ": only the axial identity orientation 1\\0\\0\\0\\1\\0 is supported");
    }
  }
  const std::vector<double> spacing = requireNumbers(ds, DCM_PixelSpacing, 2, file, "");
  if (!(spacing[0] > 0.0) || !(spacing[1] > 0.0)) {
    fail(file, "", tagName(DCM_PixelSpacing) + " = " + formatNumbers(spacing) + " must be > 0");
  }
  std::vector<double> offsets = offsets_mm;
  if (offsets.empty()) {
    if (frames > 1) {
      fail(file, "",
           tagName(DCM_GridFrameOffsetVector) + " is missing for " + std::to_string(frames) +
               " frames");
    }
    offsets.push_back(0.0);
  }
  if (offsets.size() != static_cast<std::size_t>(frames)) {
    fail(file, "",
         tagName(DCM_GridFrameOffsetVector) + " has " + std::to_string(offsets.size()) +
             " values but " + tagName(DCM_NumberOfFrames) + " = " + std::to_string(frames));
  }
  if (offsets.front() != 0.0) {
    // PS3.3 C.8.8.3.2: a non-zero first value means absolute z coordinates of the frames.
    if (std::abs(offsets.front() - ipp[2]) > 1e-3) {
      fail(file, "",
           tagName(DCM_GridFrameOffsetVector) + " starts at " + formatNumber(offsets.front()) +
               " mm: neither 0 (relative) nor the ImagePositionPatient z " + formatNumber(ipp[2]) +
               " mm (absolute)");
    }
    for (double& o : offsets) {
      o -= ipp[2];
    }
  }
  const double scaling = requireNumber(ds, DCM_DoseGridScaling, file, "");
  if (!(scaling > 0.0)) {
    fail(file, "", tagName(DCM_DoseGridScaling) + " = " + formatNumber(scaling) + " must be > 0");
  }
  const int bits = requireInt(ds, DCM_BitsAllocated, file, "");
  if (bits != 16 && bits != 32) {
    fail(file, "",
         tagName(DCM_BitsAllocated) + " = " + std::to_string(bits) +
             ": only 16 or 32 are supported");
  }
  const int representation = getInt(ds, DCM_PixelRepresentation, file, "").value_or(0);
  if (const auto spp = getInt(ds, DCM_SamplesPerPixel, file, ""); spp && *spp != 1) {
    fail(file, "", tagName(DCM_SamplesPerPixel) + " = " + std::to_string(*spp) + ", expected 1");
  }
  const DcmXfer xfer(ds->getOriginalXfer());
  if (xfer.isEncapsulated()) {
    fail(file, tagName(DCM_PixelData),
         std::string("compressed transfer syntax ") + xfer.getXferName() + " is not supported");
  }
  if (xfer.getByteOrder() == EBO_BigEndian) {
    fail(file, tagName(DCM_PixelData), "big-endian transfer syntax is not supported");
  }

  g.sizes = {cols, rows, frames};
  g.origin_m = Point3(ipp[0], ipp[1], ipp[2]) * kMmToM;
  g.z_offsets_m.resize(offsets.size());
  for (std::size_t k = 0; k < offsets.size(); ++k) {
    g.z_offsets_m[k] = offsets[k] * kMmToM;
  }
  const double dz = frames > 1
                        ? std::abs(g.z_offsets_m.back() - g.z_offsets_m.front()) / (frames - 1)
                        : spacing[0] * kMmToM;
  // PixelSpacing is (row spacing = between rows, along y)\(column spacing = along x).
  g.spacing_m = Eigen::Vector3d(spacing[1] * kMmToM, spacing[0] * kMmToM,
                                dz > 0.0 ? dz : spacing[0] * kMmToM);

  const std::size_t n = static_cast<std::size_t>(rows) * static_cast<std::size_t>(cols) *
                        static_cast<std::size_t>(frames);
  const Uint16* words = nullptr;
  unsigned long count = 0;
  if (ds->findAndGetUint16Array(DCM_PixelData, words, &count).bad() || words == nullptr) {
    fail(file, "", tagName(DCM_PixelData) + " is missing or unreadable");
  }
  const std::size_t words_per_voxel = static_cast<std::size_t>(bits / 16);
  if (count < n * words_per_voxel) {
    fail(file, "",
         tagName(DCM_PixelData) + " holds " + std::to_string(count * 2) +
             " bytes, Rows x Columns x NumberOfFrames x " +
             "BitsAllocated / 8 = " + std::to_string(n * words_per_voxel * 2));
  }
  g.dose_Gy.resize(n);
  for (std::size_t v = 0; v < n; ++v) {
    double raw = 0.0;
    if (bits == 16) {
      raw = representation == 0 ? static_cast<double>(words[v])
                                : static_cast<double>(static_cast<Sint16>(words[v]));
    } else {
      // DCMTK hands out 16-bit words in host order; a little-endian file stores the low word first.
      const Uint32 value =
          static_cast<Uint32>(words[2 * v]) | (static_cast<Uint32>(words[2 * v + 1]) << 16);
      raw = representation == 0 ? static_cast<double>(value)
                                : static_cast<double>(static_cast<Sint32>(value));
    }
    if (raw < 0.0) {
      fail(file, "",
           tagName(DCM_PixelData) + " voxel " + std::to_string(v) + " is negative (" +
               formatNumber(raw) + ")");
    }
    g.dose_Gy[v] = raw * scaling;
  }
  try {
    g.validate("RTDOSE");
  } catch (const std::invalid_argument& e) {
    fail(file, "", e.what());
  }
  return g;
}

}  // namespace

DoseGrid readRtDose(const std::string& path) {
  const Loaded l = load(path, "RTDOSE", UID_RTDoseStorage);
  return readDoseGrid(l);
}
}  // namespace needle_guidance::dose
