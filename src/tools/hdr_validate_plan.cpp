// Validates our TG-43 dose against a vendor RTDOSE for a DICOM-RT HDR plan:
//   hdr_validate_plan DIR [--source gammamed_plus_hdr] [--out FILE.json] [--samples N] [--seed S]
// DIR holds the RTPLAN, RTSTRUCT (optional) and RTDOSE. The plan is imported (dicom_rt.h), our
// dose (2-D line source, the plan's dwell times and S_K, doseRateMatrix) is computed on the
// RTDOSE grid, and the two are compared at every RTDOSE voxel >= 10 % of the prescription
// (relative differences) and at a fixed-seed sample of them (global gamma, both directions).
// Exit 0: the plan passes; 3: it fails validation (the reasons are printed); 2: bad input.
// The pass thresholds (gamma 3 %/3 mm >= 99 % both ways, |median| <= 1 %, 95th percentile
// |diff| <= 2 %) are justified next to validateAgainstRtDose in src/dose/dicom_rt.cpp.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/dose/dicom_rt.h"
#include "needle_guidance/dose/hdr_case.h"
#include "needle_guidance/dose/tg43.h"
#include "needle_guidance/report/bench_args.h"

namespace dose = needle_guidance::dose;

namespace {

constexpr int kExitPass = 0;
constexpr int kExitBadInput = 2;
constexpr int kExitFail = 3;

struct Args {
  std::string dir;
  std::string source = "gammamed_plus_hdr";
  std::string out;
  std::size_t samples = 3000;
  std::uint32_t seed = 1;
};

void usage(std::ostream& out = std::cerr) {
  out << "usage: hdr_validate_plan DIR [--source NAME] [--out FILE.json] [--samples N] [--seed S]\n"
         "  DIR      folder with RTPLAN, RTSTRUCT and RTDOSE\n"
         "  --source TG-43 data set in config/sources/ (default gammamed_plus_hdr)\n"
         "  --samples voxels sampled for the gamma index (default 3000, 0 = all)\n"
         "exit 0 pass, 3 validation failed, 2 bad input\n";
}

bool parseArgs(int argc, char** argv, Args& a) {
  for (int i = 1; i < argc; ++i) {
    const std::string s = argv[i];
    auto value = [&](std::string& v) {
      if (i + 1 >= argc) {
        std::cerr << "hdr_validate_plan: " << s << " needs a value\n";
        return false;
      }
      v = argv[++i];
      return true;
    };
    std::string v;
    if (s == "--source") {
      if (!value(a.source)) {
        return false;
      }
    } else if (s == "--out") {
      if (!value(a.out)) {
        return false;
      }
    } else if (s == "--samples" || s == "--seed") {
      if (!value(v)) {
        return false;
      }
      char* end = nullptr;
      const long long n = std::strtoll(v.c_str(), &end, 10);
      if (end == v.c_str() || *end != '\0' || n < 0 || n > 4294967295LL) {
        std::cerr << "hdr_validate_plan: " << s << " must be a non-negative integer, got '" << v
                  << "'\n";
        return false;
      }
      if (s == "--samples") {
        a.samples = static_cast<std::size_t>(n);
      } else {
        a.seed = static_cast<std::uint32_t>(n);
      }
    } else if (s == "-h" || s == "--help") {
      return false;
    } else if (!s.empty() && s[0] == '-') {
      std::cerr << "hdr_validate_plan: unknown option " << s << "\n";
      return false;
    } else if (a.dir.empty()) {
      a.dir = s;
    } else {
      std::cerr << "hdr_validate_plan: more than one DIR given\n";
      return false;
    }
  }
  return !a.dir.empty();
}

std::string num(double v, int digits = 6) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*g", digits, std::isfinite(v) ? v : 0.0);
  return buf;
}

std::string quote(const std::string& s) {
  std::string out = "\"";
  for (const char ch : s) {
    if (ch == '"' || ch == '\\') {
      out += '\\';
      out += ch;
    } else if (static_cast<unsigned char>(ch) < 0x20) {
      out += ' ';
    } else {
      out += ch;
    }
  }
  return out + "\"";
}

}  // namespace

/// The figures as JSON (--out); false if the file cannot be written.
bool writeJson(const Args& args, const dose::DicomRtFiles& files,
               const dose::DicomRtImportReport& rep, const dose::HdrCase& c, std::size_t active,
               const dose::RtDoseValidation& v, const dose::RtDoseValidationOptions& options) {
  std::ofstream f(args.out);
  auto gamma_json = [&](const dose::GammaResult& a, const dose::GammaResult& b) {
    std::ostringstream os;
    os << "{\"ours_vs_rtdose\": " << num(a.pass_rate)
       << ", \"rtdose_vs_ours\": " << num(b.pass_rate)
       << ", \"mean_gamma_ours_vs_rtdose\": " << num(a.mean_gamma)
       << ", \"mean_gamma_rtdose_vs_ours\": " << num(b.mean_gamma) << "}";
    return os.str();
  };
  std::string encodings;
  for (std::size_t k = 0; k < rep.channel_encodings.size(); ++k) {
    encodings += (k ? ", " : "") + quote(dose::toString(rep.channel_encodings[k]));
  }
  std::string reason_list;
  for (std::size_t k = 0; k < v.reasons.size(); ++k) {
    reason_list += (k ? ", " : "") + quote(v.reasons[k]);
  }
  const dose::Point3 shift_mm = v.best_shift_m * 1e3;
  f << "{\n"
    << "  \"plan_dir\": " << quote(args.dir) << ",\n"
    << "  \"plan\": " << quote(files.plan) << ",\n"
    << "  \"structure_set\": " << quote(files.structure_set) << ",\n"
    << "  \"dose\": " << quote(files.dose) << ",\n"
    << "  \"source\": " << quote(args.source) << ",\n"
    << "  \"dwell_encoding\": " << quote(dose::toString(rep.encoding)) << ",\n"
    << "  \"channel_encodings\": [" << encodings << "],\n"
    << "  \"max_axis_deviation_deg\": " << num(rep.max_axis_deviation_rad * 180.0 / M_PI) << ",\n"
    << "  \"orientation_flips\": " << rep.orientation_flips << ",\n"
    << "  \"catheters\": " << c.catheters.size() << ",\n"
    << "  \"dwell_positions\": " << c.dwells.size() << ",\n"
    << "  \"active_dwell_positions\": " << active << ",\n"
    << "  \"total_dwell_time_s\": " << num(rep.total_dwell_time_s, 8) << ",\n"
    << "  \"air_kerma_strength_U\": " << num(c.air_kerma_strength_U, 8) << ",\n"
    << "  \"prescription_Gy\": " << num(c.prescription_Gy) << ",\n"
    << "  \"fractions\": " << rep.fractions_planned << ",\n"
    << "  \"voxels\": " << v.voxels << ",\n"
    << "  \"gamma_points\": " << v.gamma_points << ",\n"
    << "  \"seed\": " << args.seed << ",\n"
    << "  \"gamma_3pct3mm\": " << num(v.gamma3pct3mm()) << ",\n"
    << "  \"gamma_2pct2mm\": " << num(v.gamma2pct2mm()) << ",\n"
    << "  \"gamma_3pct3mm_detail\": "
    << gamma_json(v.gamma33_ours_vs_rtdose, v.gamma33_rtdose_vs_ours) << ",\n"
    << "  \"gamma_2pct2mm_detail\": "
    << gamma_json(v.gamma22_ours_vs_rtdose, v.gamma22_rtdose_vs_ours) << ",\n"
    << "  \"median_relative_difference\": " << num(v.median_relative_difference) << ",\n"
    << "  \"p95_abs_relative_difference\": " << num(v.p95_abs_relative_difference) << ",\n"
    << "  \"p99_abs_relative_difference\": " << num(v.p99_abs_relative_difference) << ",\n"
    << "  \"worst_frame\": {\"index\": " << v.worst_frame
    << ", \"median_relative_difference\": " << num(v.worst_frame_median)
    << ", \"voxels\": " << v.worst_frame_voxels << "},\n"
    << "  \"best_shift_mm\": [" << num(shift_mm.x()) << ", " << num(shift_mm.y()) << ", "
    << num(shift_mm.z()) << "],\n"
    << "  \"thresholds\": {\"gamma_3pct3mm_min\": " << num(options.min_gamma_3pct3mm)
    << ", \"abs_median_max\": " << num(options.max_abs_median)
    << ", \"p95_abs_max\": " << num(options.max_p95_abs) << "},\n"
    << "  \"verdict\": " << quote(v.pass ? "pass" : "fail") << ",\n"
    << "  \"reasons\": [" << reason_list << "]\n"
    << "}\n";
  return static_cast<bool>(f);
}

int main(int argc, char** argv) {
  if (needle_guidance::report::helpRequested(argc, argv)) {
    usage(std::cout);
    return 0;
  }
  Args args;
  if (!parseArgs(argc, argv, args)) {
    usage();
    return kExitBadInput;
  }
  const auto t0 = std::chrono::steady_clock::now();
  dose::DicomRtFiles files;
  dose::DicomRtImportReport rep;
  dose::HdrCase c;
  dose::DoseGrid rtdose;
  std::optional<dose::Tg43Source> source;
  try {
    files = dose::findDicomRtFiles(args.dir);
    if (files.dose.empty()) {
      std::cerr << "hdr_validate_plan: " << args.dir << ": no RTDOSE object to validate against\n";
      return kExitBadInput;
    }
    dose::DicomRtImportOptions options;
    options.source_name = args.source;
    c = dose::importDicomRt(files.plan, files.structure_set, &rep, options);
    rtdose = dose::readRtDose(files.dose);
    source.emplace(dose::loadSource(args.source));
  } catch (const std::exception& e) {
    std::cerr << "hdr_validate_plan: bad input: " << e.what() << "\n";
    return kExitBadInput;
  }

  std::cout << "plan:       " << files.plan
            << "\nstructures: " << (files.structure_set.empty() ? "(none)" : files.structure_set)
            << "\ndose:       " << files.dose << "\n";
  std::size_t active = 0;
  for (const double t : c.dwell_times_s) {
    active += t > 0.0 ? 1 : 0;
  }
  std::cout << "imported '" << c.name << "': " << c.structures.size() << " structures, "
            << c.catheters.size() << " catheters, " << c.dwells.size() << " dwell positions ("
            << active << " active), total dwell time " << num(rep.total_dwell_time_s) << " s, S_K "
            << num(c.air_kerma_strength_U) << " U, Rx " << num(c.prescription_Gy) << " Gy x "
            << rep.fractions_planned << " fraction(s)\n";
  std::cout << "dwell-time encoding: " << dose::toString(rep.encoding) << "\n";
  std::cout << "source axis: ControlPointOrientation within "
            << num(rep.max_axis_deviation_rad * 180.0 / M_PI, 3)
            << " deg of the catheter direction, " << rep.orientation_flips
            << " reversed to point at the tip\n";
  for (const std::string& w : rep.warnings) {
    std::cout << "warning: " << w << "\n";
  }
  if (rep.active_source_length_m &&
      std::abs(*rep.active_source_length_m - source->data().active_length_m) > 0.2e-3) {
    std::cout << "warning: the plan's ActiveSourceLength " << num(*rep.active_source_length_m * 1e3)
              << " mm differs from " << args.source << "'s "
              << num(source->data().active_length_m * 1e3) << " mm\n";
  }

  dose::RtDoseValidationOptions options;
  options.gamma_samples = args.samples;
  options.seed = args.seed;
  dose::RtDoseValidation v;
  try {
    v = dose::validateAgainstRtDose(c, *source, rtdose, rep.fractions_planned, options);
  } catch (const std::invalid_argument& e) {
    std::cerr << "hdr_validate_plan: bad input: " << files.dose << ": " << e.what() << "\n";
    return kExitBadInput;
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::cout << "compared " << v.voxels << " RTDOSE voxels >= " << num(100 * options.low_dose_cutoff)
            << " % Rx (gamma sample " << v.gamma_points << ", seed " << args.seed << ") in "
            << num(seconds, 3) << " s\n";
  std::cout << "relative difference (ours - RTDOSE) / RTDOSE: median "
            << num(100 * v.median_relative_difference, 4) << " %, 95th pct |diff| "
            << num(100 * v.p95_abs_relative_difference, 4) << " %, 99th "
            << num(100 * v.p99_abs_relative_difference, 4) << " %\n";
  if (v.worst_frame >= 0) {
    std::cout << "worst frame: " << v.worst_frame << " (written z "
              << num(rtdose.position(0, 0, v.worst_frame).z() * 1e3, 5) << " mm, "
              << v.worst_frame_voxels << " voxels): median " << num(100 * v.worst_frame_median, 4)
              << " %\n";
  }
  std::cout << "gamma 3%/3mm: " << num(100 * v.gamma3pct3mm(), 5) << " % (ours vs RTDOSE "
            << num(100 * v.gamma33_ours_vs_rtdose.pass_rate, 5) << " %, RTDOSE vs ours "
            << num(100 * v.gamma33_rtdose_vs_ours.pass_rate, 5) << " %)\n";
  std::cout << "gamma 2%/2mm: " << num(100 * v.gamma2pct2mm(), 5) << " % (ours vs RTDOSE "
            << num(100 * v.gamma22_ours_vs_rtdose.pass_rate, 5) << " %, RTDOSE vs ours "
            << num(100 * v.gamma22_rtdose_vs_ours.pass_rate, 5) << " %)\n";
  std::cout << "verdict: " << (v.pass ? "PASS" : "FAIL") << "\n";
  for (const std::string& r : v.reasons) {
    std::cout << "  " << r << "\n";
  }

  if (!args.out.empty() && !writeJson(args, files, rep, c, active, v, options)) {
    std::cerr << "hdr_validate_plan: cannot write " << args.out << "\n";
    return kExitBadInput;
  }
  return v.pass ? kExitPass : kExitFail;
}
