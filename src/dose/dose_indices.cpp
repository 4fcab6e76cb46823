#include "needle_guidance/dose/dose_indices.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <functional>
#include <numeric>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  return s;
}

/// Area moments of one polygon, counted positive whatever its orientation: area, first moments
/// (x, y) and second moments (xx, yy, xy) about the origin.
struct Moments {
  double a = 0, x = 0, y = 0, xx = 0, yy = 0, xy = 0;
  void add(const std::vector<Point2d>& poly) {
    Moments m;
    for (std::size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
      const double x0 = poly[j].x(), y0 = poly[j].y(), x1 = poly[i].x(), y1 = poly[i].y();
      const double cr = x0 * y1 - x1 * y0;
      m.a += cr / 2;
      m.x += (x0 + x1) * cr / 6;
      m.y += (y0 + y1) * cr / 6;
      m.xx += (x0 * x0 + x0 * x1 + x1 * x1) * cr / 12;
      m.yy += (y0 * y0 + y0 * y1 + y1 * y1) * cr / 12;
      m.xy += (x0 * y1 + 2 * x0 * y0 + 2 * x1 * y1 + x1 * y0) * cr / 24;
    }
    const double sign = m.a < 0 ? -1.0 : 1.0;
    a += sign * m.a;
    x += sign * m.x;
    y += sign * m.y;
    xx += sign * m.xx;
    yy += sign * m.yy;
    xy += sign * m.xy;
  }
};

/// The structure's in-plane frame: origin at the area centroid of all contours, first axis
/// along the major principal axis (for a round section, towards the farthest vertex).
struct PlaneFrame {
  Point2d origin = Point2d::Zero();
  Eigen::Matrix2d axes = Eigen::Matrix2d::Identity();  ///< columns: u, v
};

PlaneFrame planeFrame(const Structure& s) {
  Moments m;
  for (const Contour& c : s.contours)
    m.add(c.xy_m);
  PlaneFrame f;
  if (!(m.a > 0.0))
    return f;
  f.origin = Point2d(m.x / m.a, m.y / m.a);
  const double cxx = m.xx / m.a - f.origin.x() * f.origin.x();
  const double cyy = m.yy / m.a - f.origin.y() * f.origin.y();
  const double cxy = m.xy / m.a - f.origin.x() * f.origin.y();
  double angle = 0.5 * std::atan2(2 * cxy, cxx - cyy);
  if (std::hypot(cxx - cyy, 2 * cxy) < 1e-6 * (cxx + cyy)) {
    double far = -1.0;
    for (const Contour& c : s.contours) {
      for (const Point2d& p : c.xy_m) {
        if ((p - f.origin).norm() > far) {
          far = (p - f.origin).norm();
          angle = std::atan2(p.y() - f.origin.y(), p.x() - f.origin.x());
        }
      }
    }
  }
  f.axes << std::cos(angle), -std::sin(angle), std::sin(angle), std::cos(angle);
  return f;
}

double polygonArea(const std::vector<Point2d>& poly) {
  Moments m;
  m.add(poly);
  return m.a;
}

/// Lattice points of the plane at z inside s (the in-plane lattice of sampleStructure).
std::vector<Point2d> planeLattice(const Structure& s, const PlaneFrame& f,
                                  const Eigen::Vector2d& lo, const Eigen::Vector2d& hi,
                                  double spacing_m, double z) {
  // u = (i + 1/2) spacing: symmetric about the centroid along both axes.
  const auto first = [&](double v) { return static_cast<long>(std::floor(v / spacing_m - 0.5)); };
  const auto last = [&](double v) { return static_cast<long>(std::ceil(v / spacing_m - 0.5)); };
  std::vector<Point2d> inside;
  for (long i = first(lo.x()); i <= last(hi.x()); ++i) {
    for (long j = first(lo.y()); j <= last(hi.y()); ++j) {
      const Point2d xy =
          f.origin + f.axes * Eigen::Vector2d((i + 0.5) * spacing_m, (j + 0.5) * spacing_m);
      if (s.contains(Point3(xy.x(), xy.y(), z)))
        inside.push_back(xy);
    }
  }
  return inside;
}

/// Planes every plane_spacing_m through the structure's z extent (sampleStructure's coarse form).
VolumeSample coarseSample(const Structure& s, const PlaneFrame& f, const Eigen::Vector2d& lo,
                          const Eigen::Vector2d& hi, double spacing_m, double plane_spacing_m) {
  VolumeSample out;
  const double h = s.sliceSpacing();
  const double z_lo = s.contours.front().z_m - 0.5 * h, z_hi = s.contours.back().z_m + 0.5 * h;
  const double mid = 0.5 * (z_lo + z_hi);
  const long n = static_cast<long>(std::ceil(0.5 * (z_hi - z_lo) / plane_spacing_m - 0.5));
  for (long k = -n - 1; k <= n; ++k) {
    const double z = mid + (k + 0.5) * plane_spacing_m;
    if (z <= z_lo || z >= z_hi)
      continue;
    for (const Point2d& xy : planeLattice(s, f, lo, hi, spacing_m, z)) {
      out.points_m.emplace_back(xy.x(), xy.y(), z);
      out.volume_m3.push_back(spacing_m * spacing_m * plane_spacing_m);
    }
  }
  const double sampled = std::accumulate(out.volume_m3.begin(), out.volume_m3.end(), 0.0);
  if (sampled > 0.0) {
    for (double& v : out.volume_m3)
      v *= s.volume_m3() / sampled;
  }
  return out;
}

}  // namespace

VolumeSample sampleStructure(const Structure& s, double spacing_m, double plane_spacing_m) {
  if (!(spacing_m > 0.0) || !std::isfinite(spacing_m) || !std::isfinite(plane_spacing_m) ||
      plane_spacing_m < 0.0)
    throw std::invalid_argument("sampleStructure: '" + s.name + "': spacing must be > 0");
  VolumeSample out;
  if (s.contours.empty())
    return out;
  const PlaneFrame f = planeFrame(s);
  Eigen::Vector2d lo = Eigen::Vector2d::Constant(1e300), hi = -lo;
  for (const Contour& c : s.contours) {
    for (const Point2d& p : c.xy_m) {
      const Eigen::Vector2d uv = f.axes.transpose() * (p - f.origin);
      lo = lo.cwiseMin(uv);
      hi = hi.cwiseMax(uv);
    }
  }
  const double h = s.sliceSpacing() > 0.0 ? s.sliceSpacing() : 0.0;
  if (h > 0.0 && plane_spacing_m > h) {
    out = coarseSample(s, f, lo, hi, spacing_m, plane_spacing_m);
    if (!out.points_m.empty())
      return out;
  }
  const double dz = plane_spacing_m > 0.0 ? plane_spacing_m : spacing_m;
  const int planes = h > 0.0 ? std::max(1, static_cast<int>(std::ceil(h / dz - 1e-9))) : 1;
  for (std::size_t k = 0; k < s.contours.size();) {
    std::size_t end = k;
    double area = 0.0;
    Moments slice;
    for (; end < s.contours.size() && std::abs(s.contours[end].z_m - s.contours[k].z_m) < 1e-12;
         ++end) {
      area += polygonArea(s.contours[end].xy_m);
      slice.add(s.contours[end].xy_m);
    }
    const double z = s.contours[k].z_m;
    std::vector<Point2d> inside = planeLattice(s, f, lo, hi, spacing_m, z);
    if (inside.empty() && slice.a > 0.0)
      inside.emplace_back(slice.x / slice.a, slice.y / slice.a);
    const double plane_volume = area * h / planes;
    for (int m = 0; m < planes && !inside.empty(); ++m) {
      const double pz = z + ((m + 0.5) / planes - 0.5) * h;
      for (const Point2d& xy : inside) {
        out.points_m.emplace_back(xy.x(), xy.y(), pz);
        out.volume_m3.push_back(plane_volume / static_cast<double>(inside.size()));
      }
    }
    k = end;
  }
  return out;
}

double latticeSpacing(const Structure& s, double spacing_m, double max_samples,
                      double thin_area_m2) {
  double area = 0.0;
  int planes = 0;
  for (std::size_t k = 0; k < s.contours.size(); ++k) {
    area += polygonArea(s.contours[k].xy_m);
    planes += k == 0 || std::abs(s.contours[k].z_m - s.contours[k - 1].z_m) >= 1e-12;
  }
  const double fine = planes > 0 && area > 0.0 && thin_area_m2 > 0.0
                          ? spacing_m * std::min(1.0, std::sqrt(area / planes / thin_area_m2))
                          : spacing_m;
  return std::max(fine, std::cbrt(s.volume_m3() / max_samples));
}

double StructureDose::volume() const {
  if (volume_m3.empty())
    return voxel_volume_m3 * static_cast<double>(dose_Gy.size());
  return std::accumulate(volume_m3.begin(), volume_m3.end(), 0.0);
}

std::vector<StructureDose> structureDoses(const HdrCase& c, const Tg43Source& source,
                                          const std::vector<double>& times_s, double spacing_m) {
  return structureDoses(c, source, times_s, {}, spacing_m);
}

std::vector<StructureDose> structureDoses(const HdrCase& c, const Tg43Source& source,
                                          const std::vector<double>& times_s,
                                          const std::vector<ExtraDwell>& extra, double spacing_m) {
  for (std::size_t k = 0; k < extra.size(); ++k) {
    const ExtraDwell& e = extra[k];
    if (!std::isfinite(e.time_s) || e.time_s < 0.0 || !e.dwell.position_m.allFinite() ||
        !e.dwell.axis.allFinite()) {
      throw std::invalid_argument("structureDoses: extra stop " + std::to_string(k) +
                                  " needs a finite time >= 0 and a finite position and axis");
    }
  }
  if (times_s.size() != c.dwells.size()) {
    throw std::invalid_argument("structureDoses: " + std::to_string(times_s.size()) +
                                " dwell times for " + std::to_string(c.dwells.size()) +
                                " dwell positions");
  }
  if (!(spacing_m > 0.0)) {
    throw std::invalid_argument("structureDoses: grid spacing must be > 0");
  }
  std::vector<StructureDose> out;
  for (const Structure& s : c.structures) {
    StructureDose sd;
    sd.name = s.name;
    sd.voxel_volume_m3 = spacing_m * spacing_m * spacing_m;
    VolumeSample sample = sampleStructure(s, latticeSpacing(s, spacing_m));
    for (const Point3& p : sample.points_m) {
      double dose = doseAt(c, source, times_s, p);
      for (const ExtraDwell& e : extra) {
        if (e.time_s > 0.0) {
          dose += e.time_s * dwellDoseRate(c, source, e.dwell, p);
        }
      }
      sd.dose_Gy.push_back(dose);
    }
    sd.volume_m3 = std::move(sample.volume_m3);
    out.push_back(std::move(sd));
  }
  return out;
}

std::vector<StructureDose> structureDosesFromGrid(const HdrCase& c, const DoseGrid& grid,
                                                  double spacing_m, double plane_spacing_m,
                                                  bool adapt) {
  grid.validate("structureDosesFromGrid: dose grid");
  std::vector<StructureDose> out;
  const int nx = grid.sizes[0], ny = grid.sizes[1], nz = grid.sizes[2];
  const Point3 first = grid.position(0, 0, 0), lastp = grid.position(nx - 1, ny - 1, nz - 1);
  const Point3 lo = first.cwiseMin(lastp), hi = first.cwiseMax(lastp);
  const double half_z = nz > 1 ? 0.5 * std::abs(grid.z_offsets_m[1] - grid.z_offsets_m[0]) : 0.0;
  const Point3 half(0.5 * grid.spacing_m.x(), 0.5 * grid.spacing_m.y(), half_z);
  for (const Structure& s : c.structures) {
    StructureDose sd;
    sd.name = s.name;
    const VolumeSample sample =
        sampleStructure(s, adapt ? latticeSpacing(s, spacing_m) : spacing_m, plane_spacing_m);
    for (std::size_t i = 0; i < sample.points_m.size(); ++i) {
      const Point3& p = sample.points_m[i];
      double dose = 0.0;
      if (!grid.interpolate(p, &dose)) {
        const Point3 clamped = p.cwiseMax(lo).cwiseMin(hi);
        const bool covered = ((p - clamped).cwiseAbs().array() <= half.array() + 1e-9).all();
        if (!covered || !grid.interpolate(clamped, &dose)) {
          sd.outside_m3 += sample.volume_m3[i];
          continue;
        }
      }
      sd.dose_Gy.push_back(dose);
      sd.volume_m3.push_back(sample.volume_m3[i]);
    }
    out.push_back(std::move(sd));
  }
  return out;
}

std::vector<StructureDose> structureDosesOnGridPixels(const HdrCase& c, const DoseGrid& grid) {
  grid.validate("structureDosesOnGridPixels: dose grid");
  std::vector<StructureDose> out;
  const double pixel_m2 = grid.spacing_m.x() * grid.spacing_m.y();
  for (const Structure& s : c.structures) {
    StructureDose sd;
    sd.name = s.name;
    const double h = s.sliceSpacing();
    for (std::size_t k = 0; k < s.contours.size(); ++k) {
      const double z = s.contours[k].z_m;
      if (k > 0 && std::abs(z - s.contours[k - 1].z_m) < 1e-12)
        continue;  // one pass per plane (contains() takes all its contours)
      for (int j = 0; j < grid.sizes[1]; ++j) {
        for (int i = 0; i < grid.sizes[0]; ++i) {
          Point3 p = grid.position(i, j, 0);
          p.z() = z;
          if (!s.contains(p))
            continue;
          double dose = 0.0;
          if (grid.interpolate(p, &dose)) {
            sd.dose_Gy.push_back(dose);
            sd.volume_m3.push_back(pixel_m2 * h);
          } else {
            sd.outside_m3 += pixel_m2 * h;
          }
        }
      }
    }
    out.push_back(std::move(sd));
  }
  return out;
}

double volumePercentAbove(const StructureDose& s, double dose_Gy) {
  const double total = s.volume();
  if (s.dose_Gy.empty() || !(total > 0.0)) {
    return 0.0;
  }
  double above = 0.0;
  for (std::size_t i = 0; i < s.dose_Gy.size(); ++i) {
    if (s.dose_Gy[i] >= dose_Gy)
      above += s.volume_m3.empty() ? s.voxel_volume_m3 : s.volume_m3[i];
  }
  return 100.0 * above / total;
}

double doseCoveringVolume(const StructureDose& s, double volume_m3) {
  const double total = s.volume();
  if (s.dose_Gy.empty() || !(total > 0.0)) {
    return 0.0;
  }
  if (volume_m3 > total * (1.0 + 1e-9))
    return std::nan("");
  std::vector<std::size_t> order(s.dose_Gy.size());
  std::iota(order.begin(), order.end(), std::size_t{0});
  std::sort(order.begin(), order.end(),
            [&](std::size_t a, std::size_t b) { return s.dose_Gy[a] > s.dose_Gy[b]; });
  // The least dose among the hottest samples that together hold volume_m3.
  double cumulative = 0.0;
  for (const std::size_t i : order) {
    const double v = s.volume_m3.empty() ? s.voxel_volume_m3 : s.volume_m3[i];
    if (cumulative + v >= volume_m3 * (1.0 - 1e-9))
      return s.dose_Gy[i];
    cumulative += v;
  }
  return s.dose_Gy[order.back()];
}

double doseCoveringPercent(const StructureDose& s, double percent) {
  return doseCoveringVolume(s, std::clamp(percent, 0.0, 100.0) / 100.0 * s.volume());
}

namespace {

/// Parses "V<p>", "D<p>" or "D<v>cc" into its letter, number and whether it is a volume (cc).
void parseSpec(const std::string& spec, char* letter, double* number, bool* cc) {
  const std::string bad = "dose-volume index '" + spec + "': expected V<p>, D<p> or D<v>cc";
  if (spec.size() < 2 || (spec[0] != 'V' && spec[0] != 'D'))
    throw std::invalid_argument(bad);
  *letter = spec[0];
  *cc = spec.size() > 3 && spec.compare(spec.size() - 2, 2, "cc") == 0;
  const std::string digits = spec.substr(1, spec.size() - 1 - (*cc ? 2 : 0));
  std::size_t used = 0;
  try {
    *number = std::stod(digits, &used);
  } catch (const std::exception&) {
    throw std::invalid_argument(bad);
  }
  if (used != digits.size() || !std::isfinite(*number) || *number < 0.0 || (*cc && *letter == 'V'))
    throw std::invalid_argument(bad);
}

std::string formatCc(double m3) {
  char text[32];
  std::snprintf(text, sizeof text, "%.3g", m3 * 1e6);
  return text;
}

}  // namespace

DoseVolumeIndex doseVolumeIndex(const StructureDose& s, const std::string& spec,
                                double prescription_Gy) {
  char letter = 'V';
  double number = 0.0;
  bool cc = false;
  parseSpec(spec, &letter, &number, &cc);
  DoseVolumeIndex out;
  const double volume = s.volume();
  if (s.dose_Gy.empty() || !(volume > 0.0)) {
    out.reason = s.name + " has no volume inside its contours";
  } else if (s.outside_m3 > 0.0) {
    out.reason = s.name + ": " + formatCc(s.outside_m3) + " cm3 of its " +
                 formatCc(volume + s.outside_m3) + " cm3 lie outside the dose grid";
  } else if (cc && number * 1e-6 > volume * (1.0 + 1e-9)) {
    out.reason = s.name + " holds " + formatCc(volume) + " cm3, less than the " +
                 formatCc(number * 1e-6) + " cm3 of " + spec;
  } else {
    out.defined = true;
    out.value = letter == 'V' ? volumePercentAbove(s, number / 100.0 * prescription_Gy)
                : cc          ? doseCoveringVolume(s, number * 1e-6)
                              : doseCoveringPercent(s, number);
    if (!std::isfinite(out.value)) {
      out.defined = false;
      out.reason = s.name + " " + spec + ": the dose is not finite";
    }
  }
  return out;
}

std::map<std::string, DoseVolumeIndex> indexSet(
    const std::vector<StructureDose>& doses,
    const std::map<std::string, std::vector<std::string>>& specs, double prescription_Gy) {
  std::map<std::string, DoseVolumeIndex> out;
  for (const StructureDose& s : doses) {
    const std::string name = lower(s.name);
    const auto it = specs.find(name);
    if (it == specs.end())
      continue;
    for (const std::string& spec : it->second)
      out[name + "_" + spec] = doseVolumeIndex(s, spec, prescription_Gy);
  }
  return out;
}

std::map<std::string, double> definedValues(const std::map<std::string, DoseVolumeIndex>& set) {
  std::map<std::string, double> out;
  for (const auto& [key, index] : set) {
    if (index.defined)
      out[key] = index.value;
  }
  return out;
}

std::map<std::string, double> dosimetricIndices(const std::vector<StructureDose>& doses,
                                                double rx) {
  return definedValues(indexSet(doses,
                                {{"prostate", {"V100", "V150", "D90"}},
                                 {"urethra", {"V100", "V150", "D10"}},
                                 {"rectum", {"V50", "V100", "D2cc"}},
                                 {"bladder", {"V50", "V100", "D2cc"}}},
                                rx));
}

std::vector<double> cumulativeDvh(const StructureDose& s, double max_Gy, int bins) {
  if (bins < 1 || !(max_Gy > 0.0)) {
    throw std::invalid_argument("cumulativeDvh: bins >= 1 and max dose > 0");
  }
  std::vector<double> out;
  for (int b = 0; b <= bins; ++b) {
    out.push_back(volumePercentAbove(s, max_Gy * b / bins));
  }
  return out;
}

}  // namespace needle_guidance::dose
