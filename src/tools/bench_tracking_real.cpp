// Benchmark of needle tracking on recorded B-mode frames (issue 17): the frames of
// $NG_SHARED_DATA/us_needle_invitro (25 frames, 720 x 440, hand-drawn needle masks; the tip is
// the mask pixel farthest along the needle's axis, the axis the mask's principal direction
// pointing left to right, as its README states) through
//   new:   SequenceTracker (needle_acquisition.h), no prior, entry worked out from the data;
//   old:   detectTip without a prior (tip_tracker.h);
//   hough: houghBaselineTip without a prior;
// per frame found, confident, tip error [px], angle error [deg], ms; headline keys
// found_fraction, tip_error_px_median, tip_error_px_p90, angle_error_deg_median,
// confident_wrong (confident and > 20 px off), fps_720x440, baseline_tip_error_px_median.
// Overlays of the best and worst frames (best.png, worst.png). The pixel size (not recorded
// with the data) is assumed 0.1 mm for the old detector's metric settings. Without the data it
// runs on a synthetic B-mode sequence (synthetic_bmode.h) and says so (summary key data).
// Usage: bench_tracking_real --out DIR [--quick]
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/imaging/synthetic_bmode.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/table.h"

namespace fs = std::filesystem;
namespace ng = needle_guidance;
namespace im = ng::imaging;

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDegPerRad = 180.0 / kPi;
constexpr double kAssumedPixel_m = 0.1e-3;
constexpr double kConfidentWrong_px = 20.0;

struct Truth {
  cv::Point2d tip;
  double angle_rad = 0.0;
};

/// The mask's tip: principal axis of the mask pixels, oriented left to right (README), and the
/// pixel farthest along it.
Truth truthFromMask(const cv::Mat& mask) {
  std::vector<cv::Point> pts;
  cv::findNonZero(mask, pts);
  cv::Mat data(static_cast<int>(pts.size()), 2, CV_64F);
  for (int i = 0; i < data.rows; ++i) {
    data.at<double>(i, 0) = pts[i].x;
    data.at<double>(i, 1) = pts[i].y;
  }
  cv::PCA pca(data, cv::Mat(), cv::PCA::DATA_AS_ROW);
  cv::Point2d d(pca.eigenvectors.at<double>(0, 0), pca.eigenvectors.at<double>(0, 1));
  if (d.x < 0)
    d = -d;
  Truth t;
  double best = -1e18;
  for (const cv::Point& p : pts) {
    const double s = p.x * d.x + p.y * d.y;
    if (s > best)
      best = s, t.tip = cv::Point2d(p.x, p.y);
  }
  t.angle_rad = std::atan2(d.y, d.x);
  return t;
}

/// The fallback sequence: 25 frames of a needle entering from the left at 8 degrees above +x
/// and advancing 8 px per frame beside a brighter, frame-wide interface, its last tenth fading
/// out of the plane.
void syntheticSequence(std::vector<fs::path>* files, std::vector<cv::Mat>* frames,
                       std::vector<Truth>* truth) {
  const double a = -8.0 / kDegPerRad;
  const cv::Point2d u(std::cos(a), std::sin(a)), tail(120, 260);
  const im::BModeInterface iface{330, 310};
  for (int i = 0; i < 25; ++i) {
    im::BModeNeedle n;
    n.tail = tail;
    n.tip = tail + (200.0 + 8.0 * i) * u;
    n.fade_fraction = 0.1;
    frames->push_back(im::syntheticBMode(cv::Size(720, 440), 100 + i, iface, n));
    // Truth: where the fading echo is down to half (what a mask of the visible needle shows).
    truth->push_back({n.tail + (1.0 - 0.5 * n.fade_fraction) * (n.tip - n.tail), a});
    files->push_back("synthetic_" + std::to_string(100 + i) + ".png");
  }
}

struct Result {
  bool found = false, confident = false;
  cv::Point2d tip;
  double angle_rad = 0.0, ms = 0.0;
};

double angleError(double a, double b) {
  double d = std::fmod(std::abs(a - b), 2 * kPi);
  return std::min(d, 2 * kPi - d) * kDegPerRad;
}

double quantile(std::vector<double> v, double q) {
  if (v.empty())
    return std::nan("");
  std::sort(v.begin(), v.end());
  const double pos = q * static_cast<double>(v.size() - 1);
  const auto i = static_cast<std::size_t>(pos);
  const double f = pos - static_cast<double>(i);
  return i + 1 < v.size() ? v[i] * (1 - f) + v[i + 1] * f : v[i];
}

Result fromDetection(const im::Detection& d, const im::ImageGeometry& g, double ms) {
  Result r;
  r.found = d.found;
  r.ms = ms;
  if (d.found) {
    r.tip = g.toPixel(d.p_SceneTip);
    r.angle_rad = -d.theta_rad;  // scene y up, image rows down
  }
  return r;
}

double msSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

void overlay(const cv::Mat& grey, const Truth& t, const Result& r, const std::string& title,
             const std::string& path) {
  cv::Mat bgr;
  cv::cvtColor(grey, bgr, cv::COLOR_GRAY2BGR);
  cv::drawMarker(bgr, t.tip, cv::Scalar(0, 255, 0), cv::MARKER_CROSS, 15, 2);
  if (r.found)
    cv::drawMarker(bgr, r.tip, cv::Scalar(0, 0, 255), cv::MARKER_TILTED_CROSS, 15, 2);
  cv::putText(bgr, title + " (green truth, red new)", cv::Point(10, 20), cv::FONT_HERSHEY_SIMPLEX,
              0.5, cv::Scalar(255, 255, 0), 1);
  cv::imwrite(path, bgr);
}

struct Summary {
  double found_fraction = 0, median = 0, p90 = 0, angle_median = 0, fps = 0;
  int confident_wrong = 0;
};

Summary summarise(const std::vector<Result>& rs, const std::vector<Truth>& ts) {
  Summary s;
  std::vector<double> e, a;
  double ms = 0;
  for (std::size_t i = 0; i < rs.size(); ++i) {
    ms += rs[i].ms;
    if (!rs[i].found)
      continue;
    const double err = cv::norm(rs[i].tip - ts[i].tip);
    e.push_back(err);
    a.push_back(angleError(rs[i].angle_rad, ts[i].angle_rad));
    if (rs[i].confident && err > kConfidentWrong_px)
      ++s.confident_wrong;
  }
  s.found_fraction = rs.empty() ? 0 : static_cast<double>(e.size()) / rs.size();
  s.median = quantile(e, 0.5);
  s.p90 = quantile(e, 0.9);
  s.angle_median = quantile(a, 0.5);
  s.fps = ms > 0 ? 1000.0 * rs.size() / ms : 0;
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_tracking_real");
  if (!args)
    return 2;
  const char* shared = std::getenv("NG_SHARED_DATA");
  const fs::path data = fs::path(shared ? shared : "/work/shared/data") / "us_needle_invitro";
  std::vector<fs::path> files;
  std::vector<cv::Mat> frames;
  std::vector<Truth> truth;
  const bool real = fs::is_directory(data / "image");
  if (!real) {
    std::cerr << "bench_tracking_real: " << data
              << " absent: running on the synthetic B-mode sequence instead\n";
    syntheticSequence(&files, &frames, &truth);
  } else {
    for (const auto& e : fs::directory_iterator(data / "image"))
      files.push_back(e.path());
    std::sort(files.begin(), files.end());
  }
  const std::vector<fs::path> to_read = real ? files : std::vector<fs::path>{};
  for (const fs::path& f : to_read) {
    frames.push_back(cv::imread(f.string(), cv::IMREAD_GRAYSCALE));
    const cv::Mat mask =
        cv::imread((data / "mask" / (f.stem().string() + ".bmp")).string(), cv::IMREAD_GRAYSCALE);
    if (frames.back().empty() || mask.empty()) {
      std::cerr << "bench_tracking_real: cannot read " << f << " or its mask\n";
      return 1;
    }
    truth.push_back(truthFromMask(mask));
  }
  im::TrackerConfig config;
  config.geometry.pixel_size_m = kAssumedPixel_m;
  config.geometry.rows = frames[0].rows;
  config.geometry.cols = frames[0].cols;
  config.geometry.origin_m = im::Point2(0.0, frames[0].rows * kAssumedPixel_m);
  im::SequenceTracker tracker(im::AcquisitionOptions{});
  std::vector<Result> fresh, old, hough;
  for (const cv::Mat& frame : frames) {
    auto t0 = std::chrono::steady_clock::now();
    const im::SequenceTracker::Output o = tracker.onFrame(frame);
    Result r;
    r.ms = msSince(t0);
    r.found = o.segment.found;
    r.confident = o.confident;
    r.tip = o.segment.tip_px;
    r.angle_rad = o.segment.angle_rad;
    fresh.push_back(r);
    t0 = std::chrono::steady_clock::now();
    const im::Detection d_old = im::detectTip(frame, config, std::nullopt);
    old.push_back(fromDetection(d_old, config.geometry, msSince(t0)));
    t0 = std::chrono::steady_clock::now();
    const im::Detection d_hough = im::houghBaselineTip(frame, config, std::nullopt);
    hough.push_back(fromDetection(d_hough, config.geometry, msSince(t0)));
  }
  ng::report::Table table({"frame_index", "frame", "method", "found", "confident", "tip_error_px",
                           "angle_error_deg", "ms"});
  std::size_t best = 0, worst = 0;
  double best_e = 1e18, worst_e = -1;
  const std::vector<std::pair<std::string, const std::vector<Result>*>> methods = {
      {"new", &fresh}, {"old", &old}, {"hough", &hough}};
  for (std::size_t i = 0; i < frames.size(); ++i) {
    for (const auto& [name, rs] : methods) {
      const Result& r = (*rs)[i];
      const double e = r.found ? cv::norm(r.tip - truth[i].tip) : std::nan("");
      table.addRow({static_cast<double>(i), files[i].stem().string(), name, r.found ? 1.0 : 0.0,
                    r.confident ? 1.0 : 0.0, e,
                    r.found ? angleError(r.angle_rad, truth[i].angle_rad) : std::nan(""), r.ms});
    }
    const double e = fresh[i].found ? cv::norm(fresh[i].tip - truth[i].tip) : 1e9;
    if (e < best_e)
      best_e = e, best = i;
    if (e > worst_e)
      worst_e = e, worst = i;
  }
  table.writeCsv(args->out_dir + "/per_frame.csv");
  overlay(frames[best], truth[best], fresh[best], "best " + files[best].stem().string(),
          args->out_dir + "/best.png");
  overlay(frames[worst], truth[worst], fresh[worst], "worst " + files[worst].stem().string(),
          args->out_dir + "/worst.png");
  const Summary n = summarise(fresh, truth), o = summarise(old, truth), h = summarise(hough, truth);
  using ng::report::jsonNumber;
  std::ostringstream js;
  js << "{\n  \"data\": \"" << (real ? "us_needle_invitro" : "synthetic (shared data absent)")
     << "\",\n  \"frames\": " << frames.size()
     << ",\n  \"found_fraction\": " << jsonNumber(n.found_fraction)
     << ",\n  \"tip_error_px_median\": " << jsonNumber(n.median)
     << ",\n  \"tip_error_px_p90\": " << jsonNumber(n.p90)
     << ",\n  \"angle_error_deg_median\": " << jsonNumber(n.angle_median)
     << ",\n  \"confident_wrong\": " << n.confident_wrong
     << ",\n  \"fps_720x440\": " << jsonNumber(n.fps)
     << ",\n  \"baseline_tip_error_px_median\": " << jsonNumber(h.median)
     << ",\n  \"baseline_found_fraction\": " << jsonNumber(h.found_fraction)
     << ",\n  \"old_found_fraction\": " << jsonNumber(o.found_fraction)
     << ",\n  \"old_tip_error_px_median\": " << jsonNumber(o.median) << ",\n  \"targets_met\": "
     << ((n.found_fraction >= 0.95 && n.median <= 8 && n.p90 <= 15 && n.angle_median <= 3 &&
          n.confident_wrong == 0 && n.fps >= 30 && !(h.median < n.median))
             ? "true"
             : "false")
     << "\n}\n";
  ng::report::writeTextFile(args->out_dir + "/summary.json", js.str());
  ng::report::writeTextFile(
      args->out_dir + "/plot.json",
      "[{\"csv\": \"per_frame.csv\", \"x\": \"frame_index\", \"y\": \"tip_error_px\", \"group\": "
      "\"method\", \"title\": \"tip error per frame (us_needle_invitro)\", \"png\": "
      "\"tip_error.png\"}]\n");
  return 0;
}
