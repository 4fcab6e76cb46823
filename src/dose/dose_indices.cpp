#include "needle_guidance/dose/dose_indices.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <functional>
#include <stdexcept>

namespace needle_guidance::dose {
namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
  return s;
}

}  // namespace

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
    if (!s.contours.empty()) {
      Point3 lo, hi;
      s.bounds(lo, hi);
      const double half = 0.5 * s.sliceSpacing();
      for (double z = lo.z() - half + 0.5 * spacing_m; z < hi.z() + half; z += spacing_m) {
        for (double y = lo.y() + 0.5 * spacing_m; y < hi.y(); y += spacing_m) {
          for (double x = lo.x() + 0.5 * spacing_m; x < hi.x(); x += spacing_m) {
            const Point3 p(x, y, z);
            if (!s.contains(p)) {
              continue;
            }
            double dose = doseAt(c, source, times_s, p);
            for (const ExtraDwell& e : extra) {
              if (e.time_s > 0.0) {
                dose += e.time_s * dwellDoseRate(c, source, e.dwell, p);
              }
            }
            sd.dose_Gy.push_back(dose);
          }
        }
      }
    }
    out.push_back(std::move(sd));
  }
  return out;
}

double volumePercentAbove(const StructureDose& s, double dose_Gy) {
  if (s.dose_Gy.empty()) {
    return 0.0;
  }
  const auto count =
      std::count_if(s.dose_Gy.begin(), s.dose_Gy.end(), [&](double d) { return d >= dose_Gy; });
  return 100.0 * static_cast<double>(count) / static_cast<double>(s.dose_Gy.size());
}

double doseCoveringPercent(const StructureDose& s, double percent) {
  if (s.dose_Gy.empty()) {
    return 0.0;
  }
  std::vector<double> sorted = s.dose_Gy;
  std::sort(sorted.begin(), sorted.end(), std::greater<double>());
  const std::size_t k = std::min(
      sorted.size() - 1,
      static_cast<std::size_t>(std::ceil(percent / 100.0 * sorted.size())) - (percent > 0 ? 1 : 0));
  return sorted[k];
}

double doseCoveringVolume(const StructureDose& s, double volume_m3) {
  if (s.dose_Gy.empty() || !(s.voxel_volume_m3 > 0.0)) {
    return 0.0;
  }
  std::vector<double> sorted = s.dose_Gy;
  std::sort(sorted.begin(), sorted.end(), std::greater<double>());
  const double voxels = volume_m3 / s.voxel_volume_m3;
  const std::size_t k =
      std::min(sorted.size() - 1, static_cast<std::size_t>(std::max(1.0, std::ceil(voxels))) - 1);
  return sorted[k];
}

std::map<std::string, double> dosimetricIndices(const std::vector<StructureDose>& doses,
                                                double rx) {
  std::map<std::string, double> out;
  for (const StructureDose& s : doses) {
    const std::string name = lower(s.name);
    if (name == "prostate") {
      out["prostate_V100"] = volumePercentAbove(s, rx);
      out["prostate_V150"] = volumePercentAbove(s, 1.5 * rx);
      out["prostate_D90"] = doseCoveringPercent(s, 90.0);
    } else if (name == "urethra") {
      out["urethra_V100"] = volumePercentAbove(s, rx);
      out["urethra_V150"] = volumePercentAbove(s, 1.5 * rx);
      out["urethra_D10"] = doseCoveringPercent(s, 10.0);
    } else if (name == "rectum" || name == "bladder") {
      out[name + "_V50"] = volumePercentAbove(s, 0.5 * rx);
      out[name + "_V100"] = volumePercentAbove(s, rx);
      out[name + "_D2cc"] = doseCoveringVolume(s, 2e-6);
    }
  }
  return out;
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
