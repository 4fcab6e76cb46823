// An HDR brachytherapy case (dissertation 6.2): structures as closed planar contours per slice,
// catheters, active dwell positions, dose calculation points, the clinical criteria and the
// dose-rate matrix d_ij. Frame: the DICOM patient frame in metres.
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

#include "needle_guidance/dose/tg43.h"

namespace needle_guidance::dose {

using Point2d = Eigen::Vector2d;

/// A closed planar contour at height z (DICOM CLOSED_PLANAR), vertices in order, not repeated.
struct Contour {
  double z_m = 0.0;
  std::vector<Point2d> xy_m;
};

enum class StructureRole { kTarget, kOrganAtRisk };

/// A structure: closed contours on parallel slices (one or more per slice). Its volume is the
/// union over slices of contour area x slice thickness (each contour stands for the slab
/// half-way to its neighbours).
struct Structure {
  std::string name;
  StructureRole role = StructureRole::kOrganAtRisk;
  std::vector<Contour> contours;  ///< sorted by z after normalise()
  /// Median spacing of distinct contour z, set by normalise() (call it after changing contours)
  /// [m].
  double slice_spacing_m = 0.0;

  /// Sorts the contours by z, checks them (>= 3 finite vertices) and sets slice_spacing_m.
  /// Throws std::invalid_argument.
  void normalise();
  /// Point inside (even-odd over the contours of the nearest slice, within half a slice).
  bool contains(const Point3& p) const;
  double volume_m3() const;
  /// Slice spacing [m] (slice_spacing_m; 0 for one slice or before normalise()).
  double sliceSpacing() const { return slice_spacing_m; }
  /// Axis-aligned bounds.
  void bounds(Point3& lo, Point3& hi) const;
};

/// A catheter: a polyline from its distal tip (first point) to where it leaves the body.
struct Catheter {
  std::string name;
  std::vector<Point3> points_m;
};

/// A dwell position of the source in a catheter.
struct DwellPosition {
  int catheter = 0;                    ///< index into HdrCase::catheters
  int index = 0;                       ///< position number along the catheter from its tip
  Point3 position_m = Point3::Zero();  ///< source centre
  Point3 axis = Point3::UnitZ();  ///< unit source axis pointing to the catheter tip (theta = 0)
};

/// Dose calculation points (6.2.1): on a structure's surface or in its volume.
enum class PointKind { kSurface, kVolume };

struct DosePoint {
  int structure = 0;  ///< index into HdrCase::structures
  PointKind kind = PointKind::kVolume;
  Point3 position_m = Point3::Zero();
};

/// One clinical criterion (one row of Table 6.1): dose points of `kind` in `structure` should
/// get a dose in [min_Gy, max_Gy]; each Gy under min costs weight_under, each Gy over max costs
/// weight_over (the IPSA penalty, eq. 6.1-6.6). Penalties are averaged over the criterion's points.
struct Criterion {
  std::string structure;
  PointKind kind = PointKind::kVolume;
  double min_Gy = 0.0;
  double max_Gy = 0.0;
  double weight_under = 0.0;
  double weight_over = 0.0;
};

struct HdrCase {
  std::string name;
  std::string source = "microselectron_v2_hdr";  ///< config/sources/ name
  double air_kerma_strength_U = 40700.0;         ///< S_K [U]
  double prescription_Gy = 9.5;
  std::vector<Structure> structures;
  std::vector<Catheter> catheters;
  std::vector<DwellPosition> dwells;
  std::vector<DosePoint> points;
  std::vector<Criterion> criteria;
  std::vector<double> dwell_times_s;  ///< a plan's dwell times (empty when unplanned)

  int structureIndex(const std::string& name) const;  ///< -1 if absent
};

/// Dose rate [Gy s^-1] at p per second of dwell at `dwell`, including S_K. A point closer than
/// min_distance_m to the dwell centre gets the dose rate at min_distance_m off the source axis
/// (TG-43 is undefined inside the source).
double dwellDoseRate(const HdrCase& c, const Tg43Source& source, const DwellPosition& dwell,
                     const Point3& p, SourceModel model = SourceModel::kLine,
                     double min_distance_m = 1e-3);

/// Dose [Gy] at p from the dwell times (one per dwell position; zero times skipped).
double doseAt(const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
              const Point3& p);

/// The dose-rate matrix d_ij [Gy s^-1]: dose rate at point i per unit dwell time at dwell j,
/// including S_K. A dose point closer than min_distance_m to a dwell centre uses the dose rate
/// at min_distance_m (TG-43 is undefined inside the source).
Eigen::MatrixXd doseRateMatrix(const HdrCase& c, const Tg43Source& source,
                               SourceModel model = SourceModel::kLine,
                               double min_distance_m = 1e-3);

}  // namespace needle_guidance::dose
