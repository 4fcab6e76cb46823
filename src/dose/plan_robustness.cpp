#include "needle_guidance/dose/plan_robustness.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>

namespace needle_guidance::dose {

HdrCase transformedCase(const HdrCase& c, const Eigen::Isometry3d& pose) {
  const Eigen::Matrix3d r = pose.linear();
  if (std::abs(std::abs(r(2, 2)) - 1.0) > 1e-9 || !pose.matrix().allFinite())
    throw std::invalid_argument("transformedCase: case '" + c.name +
                                "': the rotation must keep the contour planes axial");
  HdrCase out = c;
  for (Structure& s : out.structures) {
    for (Contour& k : s.contours) {
      double z = 0.0;
      for (Point2d& p : k.xy_m) {
        const Point3 q = pose * Point3(p.x(), p.y(), k.z_m);
        p = q.head<2>();
        z = q.z();
      }
      k.z_m = z;
    }
    s.normalise();
  }
  for (Catheter& k : out.catheters) {
    for (Point3& p : k.points_m)
      p = pose * p;
  }
  for (DwellPosition& d : out.dwells) {
    d.position_m = pose * d.position_m;
    d.axis = r * d.axis;
  }
  for (DosePoint& p : out.points)
    p.position_m = pose * p.position_m;
  return out;
}

IndexChange indexChange(const std::map<std::string, DoseVolumeIndex>& a,
                        const std::map<std::string, DoseVolumeIndex>& b) {
  IndexChange out;
  for (const auto& [key, ia] : a) {
    const auto it = b.find(key);
    if (it == b.end() || !ia.defined || !it->second.defined) {
      if (it != b.end() && ia.defined == it->second.defined)
        continue;  // undefined in both: nothing to compare
      out.dose_Gy = std::numeric_limits<double>::infinity();
      out.worst_dose = key + " (defined in one only)";
      continue;
    }
    const double change = std::abs(ia.value - it->second.value);
    const bool dose = key.find("_D") != std::string::npos;
    double& worst = dose ? out.dose_Gy : out.volume_pp;
    if (change > worst) {
      worst = change;
      (dose ? out.worst_dose : out.worst_volume) = key;
    }
  }
  return out;
}

HdrCase shiftedCatheters(const HdrCase& c, double max_shift_m, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  HdrCase out = c;
  for (std::size_t k = 0; k < c.catheters.size(); ++k) {
    const auto& pts = c.catheters[k].points_m;
    Point3 axis = pts.size() >= 2 ? Point3(pts.back() - pts.front()) : Point3::UnitZ();
    axis = axis.norm() > 0.0 ? axis.normalized() : Point3::UnitZ();
    const Point3 u = axis.unitOrthogonal(), v = axis.cross(u);
    double a = 0.0, b = 0.0;
    do {  // uniform in the unit disc
      a = unit(rng);
      b = unit(rng);
    } while (a * a + b * b > 1.0);
    const Point3 shift = max_shift_m * (unit(rng) * axis + a * u + b * v);
    for (Point3& p : out.catheters[k].points_m)
      p += shift;
    for (DwellPosition& d : out.dwells) {
      if (d.catheter == static_cast<int>(k))
        d.position_m += shift;
    }
  }
  return out;
}

std::map<std::string, IndexSpread> shiftSpread(
    const HdrCase& c, const Tg43Source& source, const std::vector<double>& times_s,
    const std::map<std::string, std::vector<std::string>>& specs, double max_shift_m, int samples,
    unsigned seed, double spacing_m) {
  const auto nominal =
      indexSet(structureDoses(c, source, times_s, spacing_m), specs, c.prescription_Gy);
  std::map<std::string, std::vector<double>> changes;
  for (int s = 0; s < samples; ++s) {
    const HdrCase shifted = shiftedCatheters(c, max_shift_m, seed + static_cast<unsigned>(s));
    const auto got =
        indexSet(structureDoses(shifted, source, times_s, spacing_m), specs, c.prescription_Gy);
    for (const auto& [key, index] : got) {
      const auto it = nominal.find(key);
      if (index.defined && it != nominal.end() && it->second.defined)
        changes[key].push_back(index.value - it->second.value);
    }
  }
  std::map<std::string, IndexSpread> out;
  for (const auto& [key, index] : nominal) {
    IndexSpread sp;
    sp.nominal = index.value;
    std::vector<double> v = changes[key];
    sp.samples = static_cast<int>(v.size());
    if (!index.defined || v.empty())
      continue;  // an undefined index has no spread
    std::sort(v.begin(), v.end());
    const auto at = [&](double q) {
      return v[static_cast<std::size_t>(std::lround(q * static_cast<double>(v.size() - 1)))];
    };
    sp.p5 = at(0.05);
    sp.p95 = at(0.95);
    double mean = 0.0, sq = 0.0;
    for (double x : v)
      mean += x / static_cast<double>(v.size());
    for (double x : v) {
      sq += (x - mean) * (x - mean);
      sp.worst = std::max(sp.worst, std::abs(x));
    }
    sp.sd = std::sqrt(sq / static_cast<double>(v.size()));
    out[key] = sp;
  }
  return out;
}

}  // namespace needle_guidance::dose
