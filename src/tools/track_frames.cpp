// Needle tracking on a folder of recorded B-mode frames, no robot; priors optional:
// track_frames --frames DIR --out FILE.csv [--pixel-size-mm S] [--needle straight|arc]
//              [--radius-mm R] [--entry left|right|top|bottom|auto] [--entry-point X,Y]
//              [--entry-angle DEG] [--overlay DIR]
// Reads the PNG/BMP/JPEG frames of DIR in name order, runs the SequenceTracker
// (needle_acquisition.h; the imaging region, a linear probe's rectangle or a convex probe's
// fan, worked out from the frames) and writes one CSV row per frame: frame, found, confident,
// tip_x_px, tip_y_px, angle_deg, ms (tip in pixel columns/rows, origin at the top-left pixel's
// centre; angle = atan2(row step, column step) towards the tip). --overlay writes the frames with
// the detection drawn. Exit 2 with a message naming the problem for bad arguments, an empty folder,
// an unreadable file or mixed frame sizes.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <string>
#include <vector>

#include "needle_guidance/imaging/needle_acquisition.h"

namespace fs = std::filesystem;
namespace im = needle_guidance::imaging;

namespace {

constexpr double kDegPerRad = 180.0 / 3.14159265358979323846;

struct Args {
  std::string frames, out, overlay, needle = "straight", entry = "auto", entry_point, entry_angle;
  double pixel_size_mm = 0.0, radius_mm = 0.0;
  bool help = false;
};

constexpr const char* kUsage =
    "usage: track_frames --frames DIR --out FILE.csv [--pixel-size-mm S] [--needle straight|arc]\n"
    "                    [--radius-mm R] [--entry left|right|top|bottom|auto]\n"
    "                    [--entry-point X,Y] [--entry-angle DEG] [--overlay DIR]\n"
    "  --entry-point X,Y  where the needle enters the image [px, column,row]: only a shaft whose\n"
    "                     line passes within 25 px of it is the needle; its end nearer is the "
    "tail\n"
    "  --entry-angle DEG  the needle's rough direction towards its tip, atan2(row step, column\n"
    "                     step) [deg]: only a shaft within 10 deg of it is the needle\n"
    "Writes one CSV row per frame: frame,found,confident,tip_x_px,tip_y_px,angle_deg,ms.\n";

int usage(const std::string& why) {
  std::cerr << "track_frames: " << why << "\n" << kUsage;
  return 2;
}

/// "X,Y" as a point; false when not two finite numbers.
bool parsePoint(const std::string& text, cv::Point2d* p) {
  const std::size_t comma = text.find(',');
  if (comma == std::string::npos)
    return false;
  try {
    std::size_t used_x = 0, used_y = 0;
    const std::string xs = text.substr(0, comma), ys = text.substr(comma + 1);
    p->x = std::stod(xs, &used_x);
    p->y = std::stod(ys, &used_y);
    return used_x == xs.size() && used_y == ys.size() && std::isfinite(p->x) && std::isfinite(p->y);
  } catch (const std::exception&) {
    return false;
  }
}

bool parse(int argc, char** argv, Args* a, std::string* why) {
  std::map<std::string, std::string*> text = {
      {"--frames", &a->frames},          {"--out", &a->out},     {"--overlay", &a->overlay},
      {"--needle", &a->needle},          {"--entry", &a->entry}, {"--entry-point", &a->entry_point},
      {"--entry-angle", &a->entry_angle}};
  std::map<std::string, double*> number = {{"--pixel-size-mm", &a->pixel_size_mm},
                                           {"--radius-mm", &a->radius_mm}};
  for (int i = 1; i < argc; ++i) {
    const std::string key = argv[i];
    if (key == "--help" || key == "-h")
      return a->help = true, true;
    if (i + 1 >= argc)
      return *why = key + " needs a value", false;
    const std::string value = argv[++i];
    if (text.count(key)) {
      *text[key] = value;
    } else if (number.count(key)) {
      try {
        *number[key] = std::stod(value);
      } catch (const std::exception&) {
        return *why = key + " " + value + " is not a number", false;
      }
      if (!std::isfinite(*number[key]) || *number[key] <= 0) {
        return *why = key + " " + value + " must be positive", false;
      }
    } else {
      return *why = "unknown option " + key, false;
    }
  }
  if (a->frames.empty() || a->out.empty())
    return *why = "--frames and --out are required", false;
  if (a->needle != "straight" && a->needle != "arc") {
    return *why = "--needle " + a->needle + ": need straight or arc", false;
  }
  if (a->needle == "arc" && a->radius_mm <= 0)
    return *why = "--needle arc needs --radius-mm (the needle's radius of curvature)", false;
  if (a->needle == "straight" && a->radius_mm > 0)
    return *why = "--radius-mm is for --needle arc (the needle is straight by default)", false;
  if (a->radius_mm > 0 && a->pixel_size_mm <= 0)
    return *why = "--radius-mm needs --pixel-size-mm to convert the radius to pixels", false;
  if (!im::entrySideFromString(a->entry)) {
    return *why = "--entry " + a->entry + ": need left, right, top, bottom or auto", false;
  }
  cv::Point2d point;
  if (!a->entry_point.empty() && !parsePoint(a->entry_point, &point))
    return *why = "--entry-point " + a->entry_point + ": need X,Y in pixels (e.g. 120,15)", false;
  if (!a->entry_angle.empty()) {
    try {
      std::size_t used = 0;
      const double deg = std::stod(a->entry_angle, &used);
      if (used != a->entry_angle.size() || !std::isfinite(deg))
        throw std::invalid_argument("not a number");
    } catch (const std::exception&) {
      return *why = "--entry-angle " + a->entry_angle + " is not a number (degrees)", false;
    }
  }
  return true;
}

std::vector<fs::path> frameFiles(const std::string& dir, std::string* why) {
  std::vector<fs::path> files;
  std::error_code ec;
  if (!fs::is_directory(dir, ec))
    return *why = "--frames " + dir + " is not a folder", files;
  for (const auto& e : fs::directory_iterator(dir, ec)) {
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), ::tolower);
    if (ext == ".png" || ext == ".bmp" || ext == ".jpg" || ext == ".jpeg")
      files.push_back(e.path());
  }
  std::sort(files.begin(), files.end());
  if (files.empty())
    *why = "no PNG/BMP/JPEG frames in " + dir;
  return files;
}

void drawOverlay(const cv::Mat& frame, const im::SequenceTracker::Output& o, const fs::path& path) {
  std::string ignored;
  cv::Mat bgr;
  cv::cvtColor(im::toGrey8(frame, &ignored), bgr, cv::COLOR_GRAY2BGR);
  if (o.segment.found) {
    const cv::Scalar colour = o.confident ? cv::Scalar(0, 255, 0) : cv::Scalar(0, 200, 255);
    // The shaft walked back from the tip (an arc when it is curved).
    const double k = o.segment.curvature_per_px, chord = o.segment.length_px();
    const double length =
        k == 0.0 ? chord : 2.0 * std::asin(std::min(1.0, 0.5 * chord * std::abs(k))) / std::abs(k);
    std::vector<cv::Point> shaft;
    const double a0 = o.segment.angle_rad + 3.14159265358979323846;  // back along the shaft
    for (double u = 0; u <= length; u += 2.0) {
      // Backwards the curvature's sign flips; heading a0 - k u, position by the exact arc.
      const double heading = a0 - k * u;
      const cv::Point2d p = k == 0.0
                                ? o.segment.tip_px + u * cv::Point2d(std::cos(a0), std::sin(a0))
                                : o.segment.tip_px + cv::Point2d(std::sin(heading) - std::sin(a0),
                                                                 std::cos(a0) - std::cos(heading)) *
                                                         (-1.0 / k);
      shaft.emplace_back(cv::Point(int(std::lround(p.x)), int(std::lround(p.y))));
    }
    cv::polylines(bgr, shaft, false, colour, 1, cv::LINE_AA);
    cv::drawMarker(bgr, o.segment.tip_px, cv::Scalar(0, 0, 255), cv::MARKER_CROSS, 15, 2);
  }
  cv::putText(bgr, o.segment.found ? (o.confident ? "confident" : "found") : "not found",
              cv::Point(10, 20), cv::FONT_HERSHEY_SIMPLEX, 0.6, cv::Scalar(255, 255, 0), 1);
  cv::imwrite(path.string(), bgr);
}

}  // namespace

int main(int argc, char** argv) {
  Args a;
  std::string why;
  if (!parse(argc, argv, &a, &why))
    return usage(why);
  if (a.help) {
    std::cout << kUsage;
    return 0;
  }
  const std::vector<fs::path> files = frameFiles(a.frames, &why);
  if (files.empty())
    return usage(why);
  if (!a.overlay.empty())
    fs::create_directories(a.overlay);
  im::AcquisitionOptions options;
  options.entry = *im::entrySideFromString(a.entry);
  if (a.needle == "arc")
    options.radius_px = a.radius_mm / a.pixel_size_mm;
  cv::Point2d point;
  if (parsePoint(a.entry_point, &point))
    options.entry_point_px = point;
  if (!a.entry_angle.empty())
    options.entry_angle_rad = std::stod(a.entry_angle) / kDegPerRad;
  try {
    options.validate();
  } catch (const std::invalid_argument& e) {
    return usage(std::string("--radius-mm ") + std::to_string(a.radius_mm) + ": " + e.what());
  }
  im::keepFreedMemory();
  im::SequenceTracker tracker(options);
  std::ofstream csv(a.out);
  if (!csv)
    return usage("cannot write " + a.out);
  csv << "frame,found,confident,tip_x_px,tip_y_px,angle_deg,ms\n";
  cv::Size size;
  for (const fs::path& f : files) {
    const cv::Mat frame = cv::imread(f.string(), cv::IMREAD_UNCHANGED);
    if (frame.empty())
      return usage("cannot read frame " + f.string());
    if (size.area() == 0)
      size = frame.size();
    if (frame.size() != size) {
      return usage("frame " + f.string() + " is " + std::to_string(frame.cols) + " x " +
                   std::to_string(frame.rows) + ", the first frame " + std::to_string(size.width) +
                   " x " + std::to_string(size.height));
    }
    const auto t0 = std::chrono::steady_clock::now();
    const im::SequenceTracker::Output o = tracker.onFrame(frame);
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    const auto& s = o.segment;
    csv << f.stem().string() << ',' << (s.found ? 1 : 0) << ',' << (o.confident ? 1 : 0) << ',';
    if (s.found) {  // not found: empty fields, never NaN
      csv << s.tip_px.x << ',' << s.tip_px.y << ',' << s.angle_rad * kDegPerRad;
    } else {
      csv << ",,";
    }
    csv << ',' << ms << '\n';
    if (!a.overlay.empty())
      drawOverlay(frame, o, fs::path(a.overlay) / (f.stem().string() + ".png"));
  }
  std::cout << "track_frames: " << files.size() << " frames -> " << a.out << "\n";
  return 0;
}
