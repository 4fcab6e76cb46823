// Validation of our TG-43 dose against a vendor RTDOSE: dose-grid interpolation, voxel
// sampling, gamma index (3 %/3 mm, 2 %/2 mm) and the per-frame / shift diagnostics.
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

#include "needle_guidance/math.h"

namespace needle_guidance::dose {
using namespace dicom_io;  // NOLINT: the shared DICOM element readers and writers

// ---- dose grid ---------------------------------------------------------------------------------

bool DoseGrid::interpolate(const Point3& p, double* dose) const {
  const int nx = sizes[0];
  const int ny = sizes[1];
  const int nz = sizes[2];
  if (nx < 1 || ny < 1 || nz < 1 || !p.allFinite()) {
    return false;
  }
  constexpr double kEdge = 1e-9;  // voxel units
  auto axis = [&](double u, int n, int& i0, double& t) {
    if (u < -kEdge || u > (n - 1) + kEdge) {
      return false;
    }
    if (n == 1) {
      i0 = 0;
      t = 0.0;
      return true;
    }
    u = std::clamp(u, 0.0, static_cast<double>(n - 1));
    i0 = std::min(static_cast<int>(std::floor(u)), n - 2);
    t = u - i0;
    return true;
  };
  int i0 = 0, j0 = 0, k0 = 0;
  double tx = 0.0, ty = 0.0, tz = 0.0;
  if (!axis((p.x() - origin_m.x()) / spacing_m.x(), nx, i0, tx) ||
      !axis((p.y() - origin_m.y()) / spacing_m.y(), ny, j0, ty)) {
    return false;
  }
  // Frames: z offsets are monotone but possibly uneven or decreasing.
  const double z = p.z() - origin_m.z();
  const double zmin = std::min(z_offsets_m.front(), z_offsets_m.back());
  const double zmax = std::max(z_offsets_m.front(), z_offsets_m.back());
  const double ztol = kEdge * spacing_m.z();
  if (z < zmin - ztol || z > zmax + ztol) {
    return false;
  }
  if (nz == 1) {
    k0 = 0;
    tz = 0.0;
  } else {
    const bool increasing = z_offsets_m.back() > z_offsets_m.front();
    // first index whose offset is past z in the grid's direction
    const auto it = increasing ? std::upper_bound(z_offsets_m.begin(), z_offsets_m.end(), z)
                               : std::upper_bound(z_offsets_m.begin(), z_offsets_m.end(), z,
                                                  std::greater<double>());
    k0 = std::clamp(static_cast<int>(it - z_offsets_m.begin()) - 1, 0, nz - 2);
    const double za = z_offsets_m[static_cast<std::size_t>(k0)];
    const double zb = z_offsets_m[static_cast<std::size_t>(k0) + 1];
    tz = std::clamp((z - za) / (zb - za), 0.0, 1.0);
  }
  const int i1 = std::min(i0 + 1, nx - 1);
  const int j1 = std::min(j0 + 1, ny - 1);
  const int k1 = std::min(k0 + 1, nz - 1);
  auto lerp = [](double a, double b, double t) { return a + (b - a) * t; };
  const double c00 = lerp(at(i0, j0, k0), at(i1, j0, k0), tx);
  const double c10 = lerp(at(i0, j1, k0), at(i1, j1, k0), tx);
  const double c01 = lerp(at(i0, j0, k1), at(i1, j0, k1), tx);
  const double c11 = lerp(at(i0, j1, k1), at(i1, j1, k1), tx);
  *dose = lerp(lerp(c00, c10, ty), lerp(c01, c11, ty), tz);
  return true;
}

double DoseGrid::maxDose() const {
  double m = 0.0;
  for (const double d : dose_Gy) {
    m = std::max(m, d);
  }
  return m;
}

void DoseGrid::validate(const std::string& what) const {
  for (int a = 0; a < 3; ++a) {
    if (sizes[static_cast<std::size_t>(a)] < 1) {
      throw std::invalid_argument(what + ": grid size " +
                                  std::to_string(sizes[static_cast<std::size_t>(a)]) +
                                  " along axis " + std::to_string(a) + " must be >= 1");
    }
  }
  if (!spacing_m.allFinite() || !(spacing_m.minCoeff() > 0.0) || !origin_m.allFinite()) {
    throw std::invalid_argument(what + ": spacing must be finite and > 0 and the origin finite");
  }
  if (z_offsets_m.size() != static_cast<std::size_t>(sizes[2])) {
    throw std::invalid_argument(what + ": " + std::to_string(z_offsets_m.size()) +
                                " frame offsets for " + std::to_string(sizes[2]) + " frames");
  }
  for (std::size_t k = 0; k < z_offsets_m.size(); ++k) {
    if (!std::isfinite(z_offsets_m[k])) {
      throw std::invalid_argument(what + ": frame offset " + std::to_string(k) + " is not finite");
    }
  }
  if (z_offsets_m.size() > 1) {
    const double sign = z_offsets_m[1] > z_offsets_m[0] ? 1.0 : -1.0;
    for (std::size_t k = 1; k < z_offsets_m.size(); ++k) {
      if (!(sign * (z_offsets_m[k] - z_offsets_m[k - 1]) > 0.0)) {
        throw std::invalid_argument(what + ": frame offsets are not strictly monotone at frame " +
                                    std::to_string(k));
      }
    }
  }
  const std::size_t n = static_cast<std::size_t>(sizes[0]) * static_cast<std::size_t>(sizes[1]) *
                        static_cast<std::size_t>(sizes[2]);
  if (dose_Gy.size() != n) {
    throw std::invalid_argument(what + ": " + std::to_string(dose_Gy.size()) + " dose values for " +
                                std::to_string(sizes[0]) + " x " + std::to_string(sizes[1]) +
                                " x " + std::to_string(sizes[2]) + " voxels");
  }
  for (std::size_t v = 0; v < n; ++v) {
    if (!std::isfinite(dose_Gy[v]) || dose_Gy[v] < 0.0) {
      throw std::invalid_argument(what + ": dose value " + std::to_string(v) +
                                  " is negative or not finite");
    }
  }
}

// ---- sampling and gamma ------------------------------------------------------------------------

std::vector<VoxelIndex> voxelsAtOrAbove(const DoseGrid& grid, double min_dose_Gy) {
  std::vector<VoxelIndex> out;
  for (int k = 0; k < grid.sizes[2]; ++k) {
    for (int j = 0; j < grid.sizes[1]; ++j) {
      for (int i = 0; i < grid.sizes[0]; ++i) {
        if (grid.at(i, j, k) >= min_dose_Gy) {
          out.push_back({i, j, k});
        }
      }
    }
  }
  return out;
}

std::vector<VoxelIndex> sampleVoxels(const std::vector<VoxelIndex>& voxels, std::size_t max_samples,
                                     std::uint32_t seed) {
  std::vector<VoxelIndex> v = voxels;
  if (max_samples == 0 || max_samples >= v.size()) {
    return v;
  }
  // std::mt19937's sequence is fixed by the standard; distributions are not, hence the modulo
  // (its bias, < n / 2^32, is irrelevant here).
  std::mt19937 rng(seed);
  for (std::size_t s = 0; s < max_samples; ++s) {
    const std::size_t r =
        s + static_cast<std::size_t>(rng() % static_cast<std::uint32_t>(v.size() - s));
    std::swap(v[s], v[r]);
  }
  v.resize(max_samples);
  return v;
}

GammaResult gammaIndex(const DoseGrid& reference, const std::vector<Point3>& points_m,
                       const std::vector<double>& evaluated_Gy, const GammaCriteria& criteria) {
  if (points_m.size() != evaluated_Gy.size()) {
    throw std::invalid_argument("gammaIndex: " + std::to_string(points_m.size()) + " points but " +
                                std::to_string(evaluated_Gy.size()) + " evaluated doses");
  }
  if (!(criteria.dose_fraction > 0.0) || !(criteria.dta_m > 0.0) ||
      !(criteria.normalisation_Gy > 0.0) || !(criteria.search_step_fraction > 0.0) ||
      criteria.search_step_fraction > 1.0 ||
      !std::isfinite(criteria.dose_fraction + criteria.dta_m + criteria.normalisation_Gy)) {
    throw std::invalid_argument(
        "gammaIndex: criteria need dose_fraction > 0, dta_m > 0, normalisation_Gy > 0 and "
        "search_step_fraction in (0, 1]");
  }
  reference.validate("gammaIndex: reference grid");
  const double dd = criteria.dose_fraction * criteria.normalisation_Gy;
  // Search lattice inside the DTA sphere, nearest first so that the search can stop once the
  // distance term alone exceeds the best gamma found.
  const int n = static_cast<int>(std::ceil(1.0 / criteria.search_step_fraction - 1e-9));
  const double h = criteria.dta_m / n;
  struct Offset {
    Point3 d;
    double dist2;  ///< |d|^2 / DTA^2
  };
  std::vector<Offset> offsets;
  for (int a = -n; a <= n; ++a) {
    for (int b = -n; b <= n; ++b) {
      for (int e = -n; e <= n; ++e) {
        const double r2 = static_cast<double>(a * a + b * b + e * e) / static_cast<double>(n * n);
        if (r2 <= 1.0 + 1e-12) {
          offsets.push_back({Point3(a * h, b * h, e * h), r2});
        }
      }
    }
  }
  std::stable_sort(offsets.begin(), offsets.end(),
                   [](const Offset& x, const Offset& y) { return x.dist2 < y.dist2; });

  GammaResult result;
  result.points = static_cast<int>(points_m.size());
  int passed = 0;
  int inside = 0;
  double gamma_sum = 0.0;
  std::vector<double> rel;
  for (std::size_t p = 0; p < points_m.size(); ++p) {
    const double de = evaluated_Gy[p];
    if (!std::isfinite(de) || !points_m[p].allFinite()) {
      throw std::invalid_argument("gammaIndex: point " + std::to_string(p) +
                                  " has a non-finite position or dose");
    }
    double d0 = 0.0;
    if (!reference.interpolate(points_m[p], &d0)) {
      ++result.points_outside;
      continue;
    }
    ++inside;
    if (d0 > 0.0) {
      rel.push_back((de - d0) / d0);
    }
    double best2 = std::numeric_limits<double>::infinity();
    for (const Offset& o : offsets) {
      if (o.dist2 >= best2) {
        break;
      }
      double dq = 0.0;
      if (!reference.interpolate(points_m[p] + o.d, &dq)) {
        continue;
      }
      const double g2 = o.dist2 + (dq - de) * (dq - de) / (dd * dd);
      best2 = std::min(best2, g2);
    }
    const double gamma = std::sqrt(best2);  // finite: the zero offset is inside
    if (gamma <= 1.0 + 1e-12) {
      ++passed;
    }
    gamma_sum += gamma;
    result.max_gamma = std::max(result.max_gamma, gamma);
  }
  result.pass_rate = result.points > 0 ? static_cast<double>(passed) / result.points : 0.0;
  result.mean_gamma = inside > 0 ? gamma_sum / inside : 0.0;
  if (!rel.empty()) {
    const std::size_t mid = rel.size() / 2;
    std::nth_element(rel.begin(), rel.begin() + static_cast<long>(mid), rel.end());
    double median = rel[mid];
    if (rel.size() % 2 == 0) {
      median =
          0.5 * (median + *std::max_element(rel.begin(), rel.begin() + static_cast<long>(mid)));
    }
    result.median_relative_difference = median;
  }
  return result;
}

// ---- validation against an RTDOSE --------------------------------------------------------------
//
// Thresholds (RtDoseValidationOptions). Both doses are TG-43 line-source calculations with the
// same consensus data, so they should differ only by table interpolation and near-source
// handling: the data set's README reports a median of -0.02 % and a 95th percentile |diff| of
// 0.17 % for a correctly registered grid (we measure -0.024 % and 0.16 %). The thresholds leave
// an order of magnitude of margin for that, are the usual clinical ones, and fail a grid or plan
// that is off by one voxel:
//  * gamma 3 %/3 mm (global, % of Rx) >= 99 % in both directions: 3 %/3 mm is the customary
//    acceptance criterion for comparing dose distributions, and a calculation-vs-calculation
//    check can ask for 99 % where measurements get 95 % (AAPM TG-218). It is computed both ways
//    (our dose searched in the RTDOSE grid and the RTDOSE searched in ours) because a gamma
//    search forgives a shift towards whichever grid is searched: for the one-slice
//    misregistered example only the second direction drops (98.5 % against 99.9 %).
//  * |median relative difference| <= 1 %: a systematic error (S_K, dwell-time decoding, source
//    data, fractions) moves the median; 1 % is well inside the 2-5 % tolerances of independent
//    HDR dose checks and far above the 0.02 % expected here.
//  * 95th percentile |relative difference| <= 2 %: local agreement where gamma's DTA search is
//    forgiving; a 1 mm shift in the steep HDR gradients gives several % (7.2 % for the
//    misregistered example) while interpolation differences give 0.1-0.3 %.

namespace {

std::string percent(double fraction, int digits = 4) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*g %%", digits, 100.0 * fraction);
  return buf;
}

}  // namespace

double RtDoseValidation::gamma3pct3mm() const {
  return std::min(gamma33_ours_vs_rtdose.pass_rate, gamma33_rtdose_vs_ours.pass_rate);
}

double RtDoseValidation::gamma2pct2mm() const {
  return std::min(gamma22_ours_vs_rtdose.pass_rate, gamma22_rtdose_vs_ours.pass_rate);
}

DoseGrid computeDoseOnGrid(const HdrCase& c, const Tg43Source& source, const DoseGrid& geometry,
                           SourceModel model, double scale) {
  if (c.dwell_times_s.size() != c.dwells.size()) {
    throw std::invalid_argument("computeDoseOnGrid: case '" + c.name + "' has " +
                                std::to_string(c.dwell_times_s.size()) + " dwell times for " +
                                std::to_string(c.dwells.size()) + " dwell positions");
  }
  if (!std::isfinite(scale) || scale < 0.0) {
    throw std::invalid_argument("computeDoseOnGrid: scale must be finite and >= 0");
  }
  DoseGrid out = geometry;
  std::fill(out.dose_Gy.begin(), out.dose_Gy.end(), 0.0);
  out.validate("computeDoseOnGrid: grid");
  HdrCase active = c;  // only dwells with time: zero-time columns cost time and add nothing
  active.dwells.clear();
  active.dwell_times_s.clear();
  active.points.clear();
  for (std::size_t d = 0; d < c.dwells.size(); ++d) {
    if (!std::isfinite(c.dwell_times_s[d]) || c.dwell_times_s[d] < 0.0) {
      throw std::invalid_argument("computeDoseOnGrid: case '" + c.name + "': dwell time " +
                                  std::to_string(d) + " is negative or not finite");
    }
    if (c.dwell_times_s[d] > 0.0) {
      active.dwells.push_back(c.dwells[d]);
      active.dwell_times_s.push_back(c.dwell_times_s[d]);
    }
  }
  if (active.dwells.empty()) {
    return out;
  }
  const Eigen::Map<const Eigen::VectorXd> t(active.dwell_times_s.data(),
                                            static_cast<Eigen::Index>(active.dwell_times_s.size()));
  constexpr std::size_t kChunk = 4096;  // points per doseRateMatrix call (bounds its memory)
  std::vector<std::size_t> idx;
  auto flush = [&]() {
    const Eigen::VectorXd d = doseRateMatrix(active, source, model, 0.0) * t;
    for (std::size_t n = 0; n < idx.size(); ++n) {
      out.dose_Gy[idx[n]] = d(static_cast<Eigen::Index>(n)) * scale;
    }
    active.points.clear();
    idx.clear();
  };
  for (int k = 0; k < out.sizes[2]; ++k) {
    for (int j = 0; j < out.sizes[1]; ++j) {
      for (int i = 0; i < out.sizes[0]; ++i) {
        DosePoint p;
        p.position_m = out.position(i, j, k);
        active.points.push_back(p);
        idx.push_back(out.index(i, j, k));
        if (active.points.size() == kChunk) {
          flush();
        }
      }
    }
  }
  if (!idx.empty()) {
    flush();
  }
  return out;
}

RtDoseValidation validateAgainstRtDose(const HdrCase& c, const Tg43Source& source,
                                       const DoseGrid& rtdose, int fractions,
                                       const RtDoseValidationOptions& options) {
  if (fractions < 1) {
    throw std::invalid_argument("validateAgainstRtDose: fractions must be >= 1");
  }
  if (!(c.prescription_Gy > 0.0)) {
    throw std::invalid_argument("validateAgainstRtDose: case '" + c.name +
                                "': prescription must be > 0 Gy");
  }
  rtdose.validate("validateAgainstRtDose: RTDOSE");
  RtDoseValidation v;
  // A PLAN (or unspecified) RTDOSE holds all fractions; our dwell times are one fraction's.
  v.fraction_factor = (rtdose.summation_type == "FRACTION" || rtdose.summation_type == "BRACHY")
                          ? 1.0
                          : static_cast<double>(fractions);
  v.normalisation_Gy = c.prescription_Gy * v.fraction_factor;
  const DoseGrid ours = computeDoseOnGrid(c, source, rtdose, SourceModel::kLine, v.fraction_factor);

  const std::vector<VoxelIndex> voxels =
      voxelsAtOrAbove(rtdose, options.low_dose_cutoff * v.normalisation_Gy);
  if (voxels.empty()) {
    throw std::invalid_argument("validateAgainstRtDose: no RTDOSE voxel reaches " +
                                percent(options.low_dose_cutoff) + " of the prescription (" +
                                formatNumber(options.low_dose_cutoff * v.normalisation_Gy) +
                                " Gy)");
  }
  v.voxels = voxels.size();
  std::vector<double> rel, abs_rel;
  rel.reserve(voxels.size());
  abs_rel.reserve(voxels.size());
  std::vector<std::vector<double>> by_frame(static_cast<std::size_t>(rtdose.sizes[2]));
  for (const VoxelIndex& x : voxels) {
    const double ref = rtdose.at(x.i, x.j, x.k);
    const double r = (ours.at(x.i, x.j, x.k) - ref) / ref;
    rel.push_back(r);
    abs_rel.push_back(std::abs(r));
    by_frame[static_cast<std::size_t>(x.k)].push_back(r);
  }
  v.median_relative_difference = quantile(rel, 0.5);
  v.p95_abs_relative_difference = quantile(abs_rel, 0.95);
  v.p99_abs_relative_difference = quantile(abs_rel, 0.99);
  for (std::size_t k = 0; k < by_frame.size(); ++k) {
    if (by_frame[k].size() < 20) {
      continue;
    }
    const double m = quantile(by_frame[k], 0.5);
    if (v.worst_frame < 0 || std::abs(m) > std::abs(v.worst_frame_median)) {
      v.worst_frame = static_cast<int>(k);
      v.worst_frame_median = m;
      v.worst_frame_voxels = by_frame[k].size();
    }
  }
  // Shift diagnostic: RTDOSE(x) against ours(x + s e_axis), s = -2..2 voxels.
  v.unshifted_median_abs = quantile(abs_rel, 0.5);
  v.best_shift_median_abs = v.unshifted_median_abs;
  for (int axis = 0; axis < 3; ++axis) {
    for (int s = -2; s <= 2; ++s) {
      if (s == 0) {
        continue;
      }
      std::vector<double> a;
      Point3 shift = Point3::Zero();
      bool have_shift = false;
      for (const VoxelIndex& x : voxels) {
        int q[3] = {x.i, x.j, x.k};
        q[axis] += s;
        if (q[axis] < 0 || q[axis] >= rtdose.sizes[static_cast<std::size_t>(axis)]) {
          continue;
        }
        const double ref = rtdose.at(x.i, x.j, x.k);
        a.push_back(std::abs(ours.at(q[0], q[1], q[2]) - ref) / ref);
        if (!have_shift) {
          shift = ours.position(q[0], q[1], q[2]) - ours.position(x.i, x.j, x.k);
          have_shift = true;
        }
      }
      if (a.size() <= voxels.size() / 2) {
        continue;  // too little overlap to mean anything
      }
      const double m = quantile(a, 0.5);
      if (m < v.best_shift_median_abs) {
        v.best_shift_median_abs = m;
        v.best_shift_m = shift;
      }
    }
  }

  const std::vector<VoxelIndex> sample = sampleVoxels(voxels, options.gamma_samples, options.seed);
  v.gamma_points = sample.size();
  std::vector<Point3> points;
  std::vector<double> ours_at, rtdose_at;
  for (const VoxelIndex& x : sample) {
    points.push_back(rtdose.position(x.i, x.j, x.k));
    ours_at.push_back(ours.at(x.i, x.j, x.k));
    rtdose_at.push_back(rtdose.at(x.i, x.j, x.k));
  }
  GammaCriteria cr;
  cr.normalisation_Gy = v.normalisation_Gy;
  cr.dose_fraction = 0.03;
  cr.dta_m = 3e-3;
  v.gamma33_ours_vs_rtdose = gammaIndex(rtdose, points, ours_at, cr);
  v.gamma33_rtdose_vs_ours = gammaIndex(ours, points, rtdose_at, cr);
  cr.dose_fraction = 0.02;
  cr.dta_m = 2e-3;
  v.gamma22_ours_vs_rtdose = gammaIndex(rtdose, points, ours_at, cr);
  v.gamma22_rtdose_vs_ours = gammaIndex(ours, points, rtdose_at, cr);

  if (v.gamma3pct3mm() < options.min_gamma_3pct3mm) {
    v.reasons.push_back("gamma 3%/3mm pass rate " + percent(v.gamma3pct3mm()) + " < " +
                        percent(options.min_gamma_3pct3mm) + " (ours vs RTDOSE " +
                        percent(v.gamma33_ours_vs_rtdose.pass_rate) + ", RTDOSE vs ours " +
                        percent(v.gamma33_rtdose_vs_ours.pass_rate) + ")");
  }
  if (std::abs(v.median_relative_difference) > options.max_abs_median) {
    v.reasons.push_back("|median relative difference| " +
                        percent(std::abs(v.median_relative_difference), 3) + " > " +
                        percent(options.max_abs_median));
  }
  if (v.p95_abs_relative_difference > options.max_p95_abs) {
    v.reasons.push_back("95th percentile |relative difference| " +
                        percent(v.p95_abs_relative_difference, 3) + " > " +
                        percent(options.max_p95_abs));
  }
  v.pass = v.reasons.empty();
  if (!v.pass && v.worst_frame >= 0 && std::abs(v.worst_frame_median) > options.max_p95_abs) {
    v.reasons.push_back("hint: frame " + std::to_string(v.worst_frame) + " (written z " +
                        formatNumber(rtdose.position(0, 0, v.worst_frame).z() * kMToMm) +
                        " mm) is off by " + percent(v.worst_frame_median, 3) + " (median)");
  }
  if (!v.pass && v.best_shift_m.norm() > 0.0) {
    const Point3 mm = v.best_shift_m * kMToMm;
    v.reasons.push_back(
        "hint: the RTDOSE values match our dose best at their written positions "
        "displaced by (" +
        formatNumber(mm.x()) + ", " + formatNumber(mm.y()) + ", " + formatNumber(mm.z()) +
        ") mm (median |diff| " + percent(v.best_shift_median_abs, 3) + " instead of " +
        percent(v.unshifted_median_abs, 3) + "): the RTDOSE looks misregistered");
  }
  return v;
}

}  // namespace needle_guidance::dose
