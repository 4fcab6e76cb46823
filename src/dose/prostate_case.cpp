#include "needle_guidance/dose/prostate_case.h"
#include "needle_guidance/math.h"

#include <cmath>
#include <random>
#include <stdexcept>
#include <string>

namespace needle_guidance::dose {
namespace {

constexpr int kContourVertices = 36;

/// Ellipse contour (centre, semi-axes) at height z.
Contour ellipse(double z, const Point2d& centre, double a, double b) {
  Contour c;
  c.z_m = z;
  for (int k = 0; k < kContourVertices; ++k) {
    const double phi = 2.0 * kPi * k / kContourVertices;
    c.xy_m.emplace_back(centre.x() + a * std::cos(phi), centre.y() + b * std::sin(phi));
  }
  return c;
}

double perimeter(const std::vector<Point2d>& poly) {
  double length = 0.0;
  for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    length += (poly[i] - poly[j]).norm();
  }
  return length;
}

}  // namespace

std::vector<Criterion> table61Criteria(double rx) {
  const double s = rx / 9.5;  // Table 6.1 is written for 950 cGy
  return {
      {"prostate", PointKind::kSurface, 9.5 * s, 14.25 * s, 100.0, 100.0},
      {"prostate", PointKind::kVolume, 9.5 * s, 14.25 * s, 100.0, 30.0},
      {"urethra", PointKind::kSurface, 9.5 * s, 11.40 * s, 100.0, 30.0},
      {"urethra", PointKind::kVolume, 9.5 * s, 11.40 * s, 100.0, 30.0},
      {"rectum", PointKind::kSurface, 0.0, 4.75 * s, 0.0, 20.0},
      {"rectum", PointKind::kVolume, 0.0, 4.75 * s, 0.0, 20.0},
      {"bladder", PointKind::kSurface, 0.0, 4.75 * s, 0.0, 20.0},
      {"bladder", PointKind::kVolume, 0.0, 4.75 * s, 0.0, 20.0},
  };
}

std::vector<DosePoint> makeDosePoints(const HdrCase& c, const DosePointOptions& options) {
  if (!(options.surface_spacing_m > 0.0) || options.volume_points < 0) {
    throw std::invalid_argument(
        "makeDosePoints: surface spacing must be > 0 and volume points >= 0");
  }
  std::mt19937 rng(options.seed);
  std::vector<DosePoint> points;
  double total_volume = 0.0;
  for (const Structure& s : c.structures) {
    total_volume += s.volume_m3();
  }
  for (std::size_t si = 0; si < c.structures.size(); ++si) {
    const Structure& s = c.structures[si];
    if (s.contours.empty()) {
      continue;
    }
    // Excluded: later structures inside this one (urethra in the prostate).
    auto excluded = [&](const Point3& p) {
      for (std::size_t other = si + 1; other < c.structures.size(); ++other) {
        if (c.structures[other].contains(p)) {
          return true;
        }
      }
      return false;
    };
    for (const Contour& contour : s.contours) {
      const double length = perimeter(contour.xy_m);
      const int count =
          std::max(3, static_cast<int>(std::round(length / options.surface_spacing_m)));
      // Walk the contour at equal arc length.
      double next = 0.0, walked = 0.0;
      const double step = length / count;
      for (std::size_t i = 0; i < contour.xy_m.size() && static_cast<int>(points.size()) >= 0;
           ++i) {
        const Point2d& a = contour.xy_m[i];
        const Point2d& b = contour.xy_m[(i + 1) % contour.xy_m.size()];
        const double edge = (b - a).norm();
        while (next <= walked + edge && next < length - 1e-12) {
          const Point2d p = a + (edge > 0.0 ? (next - walked) / edge : 0.0) * (b - a);
          points.push_back(
              {static_cast<int>(si), PointKind::kSurface, Point3(p.x(), p.y(), contour.z_m)});
          next += step;
        }
        walked += edge;
      }
    }
    const double share = total_volume > 0.0 ? s.volume_m3() / total_volume : 0.0;
    const int wanted = std::max(options.min_per_structure,
                                static_cast<int>(std::round(share * options.volume_points)));
    Point3 lo, hi;
    s.bounds(lo, hi);
    const double half = 0.5 * s.sliceSpacing();
    lo.z() -= half;
    hi.z() += half;
    std::uniform_real_distribution<double> ux(lo.x(), hi.x()), uy(lo.y(), hi.y()),
        uz(lo.z(), hi.z());
    int placed = 0;
    for (int attempt = 0; placed < wanted && attempt < 200 * wanted; ++attempt) {
      const Point3 p(ux(rng), uy(rng), uz(rng));
      if (s.contains(p) && !excluded(p)) {
        points.push_back({static_cast<int>(si), PointKind::kVolume, p});
        ++placed;
      }
    }
  }
  return points;
}

std::vector<DwellPosition> makeDwellPositions(const HdrCase& c, double step_m, double margin_m) {
  if (!(step_m > 0.0)) {
    throw std::invalid_argument("makeDwellPositions: step must be > 0");
  }
  std::vector<DwellPosition> dwells;
  const Structure* target = nullptr;
  for (const Structure& s : c.structures) {
    if (s.role == StructureRole::kTarget) {
      target = &s;
      break;
    }
  }
  if (!target) {
    throw std::invalid_argument("makeDwellPositions: case '" + c.name +
                                "' has no target structure");
  }
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const auto& pts = c.catheters[k].points_m;
    if (pts.size() < 2) {
      throw std::invalid_argument("makeDwellPositions: catheter '" + c.catheters[k].name +
                                  "' needs >= 2 points");
    }
    int index = 0;
    double along = 0.0;  // arc length from the tip
    for (std::size_t seg = 0; seg + 1 < pts.size(); ++seg) {
      const Point3 a = pts[seg];
      const Point3 b = pts[seg + 1];
      const double length = (b - a).norm();
      if (length <= 0.0) {
        continue;
      }
      const Point3 towards_tip = (a - b) / length;
      for (double s = along == 0.0 ? 0.0 : std::ceil(along / step_m) * step_m - along;
           s <= length + 1e-12; s += step_m) {
        const Point3 p = a + s / length * (b - a);
        const bool near = target->contains(p) || target->contains(p + margin_m * towards_tip) ||
                          target->contains(p - margin_m * towards_tip);
        if (near) {
          dwells.push_back({static_cast<int>(k), index, p, towards_tip});
        }
        ++index;
      }
      along += length;
    }
  }
  return dwells;
}

HdrCase syntheticProstateCase(const SyntheticCaseOptions& o) {
  std::mt19937 rng(o.seed);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double cc = o.prostate_cc > 0.0 ? o.prostate_cc : 23.0 + 80.0 * unit(rng);
  const int n_catheters = o.catheters > 0 ? o.catheters : 14 + static_cast<int>(rng() % 5);
  const int n_points =
      o.dose_points > 0 ? o.dose_points : 1781 + static_cast<int>(rng() % (3510 - 1781 + 1));
  if (cc < 5.0 || cc > 200.0 || n_catheters < 1 || n_catheters > 40 || !(o.slice_m > 0.0)) {
    throw std::invalid_argument(
        "syntheticProstateCase: prostate 5-200 cc, 1-40 catheters, slice > 0");
  }
  HdrCase c;
  c.name = "synthetic_" + std::to_string(o.seed);
  c.prescription_Gy = o.prescription_Gy;
  // Prostate: ellipsoid, wider (x) than deep (y), volume = 4/3 pi a b h.
  const double r = std::cbrt(cc * 1e-6 / (4.0 / 3.0 * kPi * 1.15 * 0.85 * 1.0));
  const double a = 1.15 * r, b = 0.85 * r, h = 1.0 * r;
  Structure prostate{"prostate", StructureRole::kTarget, {}};
  Structure urethra{"urethra", StructureRole::kOrganAtRisk, {}};
  Structure rectum{"rectum", StructureRole::kOrganAtRisk, {}};
  Structure bladder{"bladder", StructureRole::kOrganAtRisk, {}};
  const double urethra_r = 3.5e-3;
  const Point2d urethra_centre(0.0, -0.2 * b);  // DICOM: -y is anterior
  const double rectum_r = 13e-3;
  const Point2d rectum_centre(0.0, b + rectum_r + 2e-3);
  const double bladder_r = std::max(22e-3, 0.9 * a);
  const double bladder_z = h + 0.75 * bladder_r;
  const int half_slices = static_cast<int>(std::ceil((h + 2.0 * bladder_r) / o.slice_m));
  for (int k = -half_slices; k <= half_slices; ++k) {
    const double z = k * o.slice_m;
    if (std::abs(z) < h) {
      const double f = std::sqrt(1.0 - (z / h) * (z / h));
      if (f * b > 2.0 * urethra_r) {
        prostate.contours.push_back(ellipse(z, Point2d::Zero(), a * f, b * f));
        urethra.contours.push_back(ellipse(z, urethra_centre, urethra_r, urethra_r));
      }
    }
    if (z > -h - 2.0 * o.slice_m && z < h + 2.0 * o.slice_m) {  // two slices beyond the CTV (6.3.1)
      rectum.contours.push_back(ellipse(z, rectum_centre, 1.3 * rectum_r, rectum_r));
    }
    if (std::abs(z - bladder_z) < bladder_r && z > h - 1.5 * o.slice_m) {
      const double f =
          std::sqrt(1.0 - ((z - bladder_z) / bladder_r) * ((z - bladder_z) / bladder_r));
      bladder.contours.push_back(
          ellipse(z, Point2d(0.0, -0.2 * b), 1.2 * bladder_r * f, bladder_r * f));
    }
  }
  for (Structure* s : {&prostate, &urethra, &rectum, &bladder}) {
    s->normalise();
  }
  c.structures = {prostate, urethra, rectum, bladder};
  // Catheters: transperineal, parallel to z, tip at the base; an outer ring and an inner ring,
  // none within 6 mm of the urethra, jittered by up to 1.5 mm.
  std::uniform_real_distribution<double> jitter(-1.5e-3, 1.5e-3);
  const int outer = static_cast<int>(std::round(0.62 * n_catheters));
  std::vector<Point2d> xy;
  for (int i = 0; i < outer; ++i) {
    const double phi = 2.0 * kPi * (i + 0.5) / outer;
    xy.emplace_back(0.75 * a * std::cos(phi), 0.72 * b * std::sin(phi));
  }
  for (int i = 0; static_cast<int>(xy.size()) < n_catheters && i < 1000; ++i) {
    const int inner = n_catheters - outer;
    const double phi = 2.0 * kPi * (i + 0.25) / std::max(1, inner) + 0.3 * (i / std::max(1, inner));
    const double scale = 0.38 + 0.05 * (i / std::max(1, inner));
    const Point2d p(scale * a * std::cos(phi), scale * b * std::sin(phi));
    if ((p - urethra_centre).norm() >= 6e-3) {
      xy.push_back(p);
    }
  }
  for (std::size_t i = 0; i < xy.size(); ++i) {
    const Point2d p = xy[i] + Point2d(jitter(rng), jitter(rng));
    Catheter cat;
    cat.name = "c" + std::to_string(i + 1);
    cat.points_m = {Point3(p.x(), p.y(), 0.95 * h),
                    Point3(p.x() + jitter(rng), p.y() + jitter(rng), -h - 0.04)};
    c.catheters.push_back(cat);
  }
  c.dwells = makeDwellPositions(c, o.dwell_step_m);
  c.criteria = table61Criteria(o.prescription_Gy);
  DosePointOptions points;
  points.seed = o.seed;
  // Surface points first at 4 mm; the rest of the drawn total are volume points.
  points.volume_points = 0;
  points.min_per_structure = 0;
  const std::size_t surface = makeDosePoints(c, points).size();
  points.volume_points = std::max(200, n_points - static_cast<int>(surface));
  points.min_per_structure = 40;
  c.points = makeDosePoints(c, points);
  return c;
}

std::vector<HdrCase> syntheticCohort(int n, unsigned seed) {
  std::vector<HdrCase> cases;
  for (int i = 0; i < n; ++i) {
    SyntheticCaseOptions o;
    o.seed = seed + static_cast<unsigned>(i);
    cases.push_back(syntheticProstateCase(o));
  }
  return cases;
}

}  // namespace needle_guidance::dose
