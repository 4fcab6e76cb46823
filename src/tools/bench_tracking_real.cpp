// Benchmark of needle tracking on recorded B-mode frames: the frames of
// $NG_SHARED_DATA/us_needle_invitro (25 frames, 720 x 440, hand-drawn needle masks; the tip is
// the mask pixel farthest along the needle's axis, the axis the mask's principal direction
// pointing left to right, as its README states) through
//   new:   SequenceTracker (needle_acquisition.h), no prior, entry worked out from the data;
//   old:   detectTip without a prior (tip_tracker.h);
//   hough: houghBaselineTip without a prior;
// per frame found, confident, tip error [px], angle error [deg], ms; headline keys
// found_fraction, tip_error_px_median, tip_error_px_p90, angle_error_deg_median,
// confident_wrong (confident and > 20 px off), fps_720x440, baseline_tip_error_px_median;
// fps_720x440_cpu is the same rate from the tracking thread's CPU time, which the other
// processes on a shared machine leave (nearly) alone, unlike the wall clock.
// Overlays of the best and worst frames (best.png, worst.png). The pixel size (not recorded
// with the data) is assumed 0.1 mm for the old detector's metric settings. Without the data it
// runs on a synthetic B-mode sequence (synthetic_bmode.h) and says so (summary key data).
// The held-out halves: the acquisition's constants were chosen on the even frames; the odd ones
// are reported apart (keys ..._even, ..._odd). Held out entirely: two sequences of the imager's
// realistic ultrasound renderer (frame_renderer.h), a straight needle and a steerable one (arc
// of 10 cm radius, tracked with the arc model), seeds and geometry never used for tuning (keys
// heldout_straight_*, heldout_arc_*). Realism: speckle, needle and interface statistics
// (bmode_statistics.h) of the recorded frames against the imager's classic and realistic
// renderers at the same assumed 0.1 mm pixels (realism.csv, keys realism_*).
// Usage: bench_tracking_real --out DIR [--quick]
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/imaging/bmode_statistics.h"
#include "needle_guidance/imaging/convex_ultrasound.h"
#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/imaging/synthetic_bmode.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/scene/scene.h"

namespace fs = std::filesystem;
namespace ng = needle_guidance;
namespace im = ng::imaging;

namespace {

using needle_guidance::kPi;
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
  double cpu_ms = 0.0;  ///< the tracking thread's CPU time (other processes' load left out)
  bool predicted = false;
  std::string message;
};

double angleError(double a, double b) {
  double d = std::fmod(std::abs(a - b), 2 * kPi);
  return std::min(d, 2 * kPi - d) * kDegPerRad;
}

/// The q-quantile; undefined (NaN, written as null) for an empty sample.
double quantile(const std::vector<double>& v, double q) {
  return v.empty() ? std::nan("") : ng::quantile(v, q);
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

/// CPU time of the calling thread [ms].
double threadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e3 * static_cast<double>(ts.tv_sec) + 1e-6 * static_cast<double>(ts.tv_nsec);
}

/// One frame through the SequenceTracker, timed (wall clock and thread CPU time).
Result trackTimed(im::SequenceTracker& tracker, const cv::Mat& frame) {
  const auto t0 = std::chrono::steady_clock::now();
  const double cpu0 = threadCpuMs();
  const im::SequenceTracker::Output o = tracker.onFrame(frame);
  Result r;
  r.cpu_ms = threadCpuMs() - cpu0;
  r.ms = msSince(t0);
  r.found = o.segment.found;
  r.confident = o.confident;
  r.tip = o.segment.tip_px;
  r.angle_rad = o.segment.angle_rad;
  r.predicted = o.predicted;
  r.message = o.segment.message;
  return r;
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
  double found_fraction = 0, median = 0, p90 = 0, angle_median = 0, fps = 0, fps_cpu = 0;
  int confident_wrong = 0;
};

/// parity -1: every frame; 0: the even ones; 1: the odd ones.
Summary summarise(const std::vector<Result>& rs, const std::vector<Truth>& ts, int parity = -1) {
  Summary s;
  std::vector<double> e, a;
  double ms = 0, cpu_ms = 0;
  std::size_t counted = 0;
  for (std::size_t i = 0; i < rs.size(); ++i) {
    if (parity >= 0 && static_cast<int>(i % 2) != parity)
      continue;
    ++counted;
    ms += rs[i].ms;
    cpu_ms += rs[i].cpu_ms;
    if (!rs[i].found)
      continue;
    const double err = cv::norm(rs[i].tip - ts[i].tip);
    e.push_back(err);
    a.push_back(angleError(rs[i].angle_rad, ts[i].angle_rad));
    if (rs[i].confident && err > kConfidentWrong_px)
      ++s.confident_wrong;
  }
  s.found_fraction = counted == 0 ? 0 : static_cast<double>(e.size()) / counted;
  s.median = quantile(e, 0.5);
  s.p90 = quantile(e, 0.9);
  s.angle_median = quantile(a, 0.5);
  s.fps = ms > 0 ? 1000.0 * counted / ms : 0;
  s.fps_cpu = cpu_ms > 0 ? 1000.0 * counted / cpu_ms : 0;
  return s;
}

// ---- held-out sequences and realism: the imager's frames at the assumed 0.1 mm pixels ----

constexpr int kCols = 720, kRows = 440;
constexpr double kUsNoise = 0.1, kUsBlur_m = 0.3e-3;  // bench tracking's ultrasound device
/// The realistic model's point-spread function already sets its speckle grain; the classic
/// device's 0.3 mm display blur on top of it made the grain 4.4 px along the beam against the
/// recorded frames' 1.3 px (realism.csv), and the needle three times as wide as the recorded
/// one. The realistic frames get a display blur of one 0.1 mm pixel only.
constexpr double kRealisticBlur_m = 0.1e-3;

/// The imager on steering_workspace: 720 x 440 px of 0.1 mm from the scene's left edge, rows
/// from y = 50 mm down to 6 mm (clear of the obstacles' middle).
im::ImagerConfig imager(const ng::scene::Scene& scene, im::UltrasoundModel model,
                        std::uint64_t seed) {
  im::ImagerConfig c = im::imagerConfigFromScene(scene, seed);
  c.modality = im::Modality::kUltrasound;
  c.ultrasound_model = model;
  c.geometry.pixel_size_m = kAssumedPixel_m;
  c.geometry.cols = kCols;
  c.geometry.rows = kRows;
  c.geometry.origin_m = im::Point2(0.0, 0.05);
  c.noise_std = kUsNoise;
  c.blur_sigma_m = model == im::UltrasoundModel::kRealistic ? kRealisticBlur_m : kUsBlur_m;
  c.drop_probability = 0.0;
  return c;
}

/// The needle's mask (5 px wide) in the frame, as a hand-drawn one would cover it.
cv::Mat needleMask(const std::vector<im::Point2>& pts, const im::ImageGeometry& g) {
  cv::Mat mask(g.size(), CV_8U, cv::Scalar(0));
  for (std::size_t i = 1; i < pts.size(); ++i)
    cv::line(mask, g.toPixel(pts[i - 1]), g.toPixel(pts[i]), cv::Scalar(255), 5);
  return mask;
}

/// A realistic synthetic sequence: the needle from `entry` [m] at `angle` [rad above +x],
/// straight (kappa 0) or on an arc of curvature kappa [1/m]; `held_out` ones are never looked at
/// while tuning the acquisition (their seeds and geometry were fixed before it).
struct SyntheticSpec {
  std::string name;
  std::uint64_t seed;
  im::Point2 entry;
  double angle, kappa;
  bool held_out;
  double tissue_motion_px = 0.0;  ///< ImagerConfig::tissue_motion_px (0: still tissue)
};

/// Tuning sequences (seeds 11, 23, 35) and held-out ones (77 and 91 from the first round,
/// 105 and 131 added with the tuning set, before any tuning).
const std::vector<SyntheticSpec>& syntheticSpecs() {
  static const std::vector<SyntheticSpec> specs = {
      {"tune_straight_a", 11, im::Point2(0.0, 0.020), 0.05, 0.0, false},
      {"tune_straight_b", 23, im::Point2(0.0, 0.010), 0.15, 0.0, false},
      {"tune_arc", 35, im::Point2(0.0, 0.012), 0.20, -8.0, false},
      // Second tuning round (seeds never used before): more layouts of the seeded layers, the
      // needle passing under and into them.
      {"tune_straight_c", 201, im::Point2(0.0, 0.018), 0.08, 0.0, false},
      {"tune_straight_d", 203, im::Point2(0.0, 0.025), 0.02, 0.0, false},
      {"tune_straight_e", 207, im::Point2(0.0, 0.012), 0.12, 0.0, false},
      {"tune_straight_f", 211, im::Point2(0.0, 0.030), -0.03, 0.0, false},
      {"tune_arc_c", 205, im::Point2(0.0, 0.015), 0.15, -9.0, false},
      {"tune_arc_d", 209, im::Point2(0.0, 0.020), 0.02, 7.0, false},
      {"tune_arc_e", 213, im::Point2(0.0, 0.010), 0.22, -6.0, false},
      // Third tuning round (seeds never used before), the needle entering in, under and just
      // above the seeded layers' band of rows, straight and bent either way.
      {"tune_straight_g", 301, im::Point2(0.0, 0.022), 0.03, 0.0, false},
      {"tune_straight_h", 303, im::Point2(0.0, 0.016), 0.10, 0.0, false},
      {"tune_straight_i", 307, im::Point2(0.0, 0.034), -0.06, 0.0, false},
      {"tune_straight_j", 311, im::Point2(0.0, 0.027), 0.04, 0.0, false},
      {"tune_arc_f", 313, im::Point2(0.0, 0.024), -0.05, 8.0, false},
      {"tune_arc_g", 317, im::Point2(0.0, 0.018), 0.12, -7.0, false},
      {"tune_arc_h", 319, im::Point2(0.0, 0.031), 0.0, -9.0, false},
      {"tune_arc_i", 323, im::Point2(0.0, 0.014), 0.05, 10.0, false},
      // Closing check: moving tissue (drift, sway, compression, partly fresh speckle), the
      // motion cue's hard case; seeds never used before.
      {"tune_motion_straight", 401, im::Point2(0.0, 0.020), 0.06, 0.0, false, 1.0},
      {"tune_motion_arc", 403, im::Point2(0.0, 0.016), 0.10, -8.0, false, 2.0},
      {"straight", 77, im::Point2(0.0, 0.015), 0.10, 0.0, true},
      {"arc", 91, im::Point2(0.0, 0.008), 0.25, -10.0, true},
      {"straight_b", 105, im::Point2(0.0, 0.028), 0.0, 0.0, true},
      {"arc_b", 131, im::Point2(0.0, 0.022), 0.05, 8.0, true},
      // Held out with moving tissue (fixed with the two tuning ones above, never tuned on).
      {"motion_straight", 501, im::Point2(0.0, 0.024), 0.04, 0.0, true, 1.5},
      {"motion_arc", 503, im::Point2(0.0, 0.012), 0.15, 9.0, true, 0.75}};
  return specs;
}

struct SyntheticRun {
  const SyntheticSpec* spec = nullptr;
  Summary summary;
  Summary hough;  ///< houghBaselineTip (no prior) on the same frames
};

/// One sequence: 20 frames of the realistic imager, the needle advancing 1 mm a frame, tracked
/// by SequenceTracker (with the arc model when kappa != 0) against the true tip; per-frame rows
/// into `table`.
SyntheticRun syntheticRun(const ng::scene::Scene& scene, const SyntheticSpec& spec,
                          ng::report::Table* table, const std::string& overlay_dir) {
  im::ImagerConfig c = imager(scene, im::UltrasoundModel::kRealistic, spec.seed);
  c.tissue_motion_px = spec.tissue_motion_px;
  const im::FrameRenderer renderer(scene, c);
  im::TrackerConfig hough_config;  // the baseline on the imager's own grid
  hough_config.geometry = c.geometry;
  std::vector<Result> hough;
  im::AcquisitionOptions options;
  options.entry = im::EntrySide::kLeft;
  if (spec.kappa != 0.0)
    options.radius_px = 1.0 / std::abs(spec.kappa) / kAssumedPixel_m;
  im::SequenceTracker tracker(options);
  std::vector<Result> rs;
  std::vector<Truth> ts;
  for (int k = 0; k < 20; ++k) {
    const double length = 0.02 + 1e-3 * k;
    const std::vector<im::Point2> pts =
        im::insertedNeedlePoints(spec.entry, spec.angle, length, spec.kappa);
    const cv::Mat image = renderer.render(pts, static_cast<std::uint64_t>(k)).image;
    rs.push_back(trackTimed(tracker, image));
    hough.push_back(
        fromDetection(im::houghBaselineTip(image, hough_config, std::nullopt), c.geometry, 0.0));
    const double h = spec.angle + spec.kappa * length;  // heading at the tip, scene y up
    ts.push_back({c.geometry.toPixel(pts.back()), std::atan2(-std::sin(h), std::cos(h))});
    const Result& r = rs.back();
    table->addRow({spec.name, static_cast<double>(k), spec.held_out ? 1.0 : 0.0,
                   r.found ? 1.0 : 0.0, r.confident ? 1.0 : 0.0,
                   r.found ? cv::norm(r.tip - ts.back().tip) : std::nan(""),
                   r.found ? angleError(r.angle_rad, ts.back().angle_rad) : std::nan(""), r.ms});
    // NG_TRACKING_STUDY=1: every tuning frame's estimate, truth and message on stderr, and its
    // overlay (never a held-out one).
    const char* study = std::getenv("NG_TRACKING_STUDY");
    if (study && std::string(study) == "1" && !spec.held_out) {
      std::cerr << spec.name << " " << k << ": truth (" << ts.back().tip.x << ", "
                << ts.back().tip.y << ") est (" << r.tip.x << ", " << r.tip.y << ") found "
                << r.found << " conf " << r.confident << " pred " << r.predicted << ": "
                << r.message << "\n";
      overlay(image, ts.back(), r, spec.name + " " + std::to_string(k),
              overlay_dir + "/study_" + spec.name + "_" + std::to_string(k) + ".png");
    }
    if (!overlay_dir.empty() && (k == 0 || k == 19)) {
      overlay(image, ts.back(), r, spec.name + " " + std::to_string(k),
              overlay_dir + "/synthetic_" + spec.name + "_" + std::to_string(k) + ".png");
    }
  }
  return {&spec, summarise(rs, ts), summarise(hough, ts)};
}

/// Realism rows: the recorded frames' statistics (median over frames) and the imager's, classic
/// and realistic, on 5 frames of a needle entering from the left 8 degrees up (as recorded).
std::vector<std::pair<std::string, im::BModeStatistics>> realism(
    const ng::scene::Scene& scene, const std::vector<cv::Mat>& frames,
    const std::vector<cv::Mat>& masks) {
  auto median_of = [](const std::vector<im::BModeStatistics>& v) {
    auto med = [&](double im::BModeStatistics::*field) {
      std::vector<double> x;
      for (const auto& s : v)
        x.push_back(s.*field);
      return quantile(x, 0.5);
    };
    im::BModeStatistics m;
    m.tissue_patches = v.empty() ? 0 : v.front().tissue_patches;
    for (auto f :
         {&im::BModeStatistics::tissue_mean_grey, &im::BModeStatistics::speckle_snr,
          &im::BModeStatistics::speckle_lateral_px, &im::BModeStatistics::speckle_axial_px,
          &im::BModeStatistics::needle_grey, &im::BModeStatistics::needle_contrast,
          &im::BModeStatistics::brightest_other_over_needle, &im::BModeStatistics::dark_fraction})
      m.*f = med(f);
    return m;
  };
  std::vector<std::pair<std::string, im::BModeStatistics>> rows;
  std::vector<im::BModeStatistics> recorded;
  for (std::size_t i = 0; i < frames.size() && i < masks.size(); ++i)
    recorded.push_back(im::bmodeStatistics(frames[i], masks[i]));
  if (!recorded.empty())
    rows.emplace_back("recorded", median_of(recorded));
  for (const auto model : {im::UltrasoundModel::kClassic, im::UltrasoundModel::kRealistic}) {
    const im::ImagerConfig c = imager(scene, model, 5);
    const im::FrameRenderer renderer(scene, c);
    std::vector<im::BModeStatistics> v;
    for (int k = 0; k < 5; ++k) {
      const auto pts =
          im::insertedNeedlePoints(im::Point2(0.0, 0.012), 8.0 / kDegPerRad, 0.02 + 2e-3 * k, 0.0);
      v.push_back(im::bmodeStatistics(renderer.render(pts, static_cast<std::uint64_t>(k)).image,
                                      needleMask(pts, c.geometry)));
    }
    rows.emplace_back("imager_" + im::toString(model), median_of(v));
  }
  // The convex-probe renderer at its own 0.15 mm pixels: a needle from the probe's end, 35
  // degrees, two interfaces below.
  im::ConvexInsertion c;
  c.seed = 5;
  const im::ConvexScene convex_scene = c.scene();
  std::vector<im::BModeStatistics> v;
  for (int k = 0; k < 5; ++k) {
    Truth t;
    const std::vector<cv::Point2d> pts = c.needleAt(3 * k, &t.tip, &t.angle_rad);
    cv::Mat mask(c.size, CV_8U, cv::Scalar(0));
    cv::line(mask, pts.front(), pts.back(), cv::Scalar(255), 5);
    const cv::Mat image = im::renderConvexFrame(convex_scene, c.size, pts, std::uint64_t(k));
    mask.setTo(0, image == 0);  // the part outside the sector is not seen
    v.push_back(im::bmodeStatistics(image, mask));
  }
  rows.emplace_back("convex", median_of(v));
  return rows;
}

void writeRealism(const std::vector<std::pair<std::string, im::BModeStatistics>>& rows,
                  const std::string& dir, std::ostringstream& js) {
  ng::report::Table t({"source", "tissue_patches", "tissue_mean_grey", "speckle_snr",
                       "speckle_lateral_px", "speckle_axial_px", "needle_grey", "needle_contrast",
                       "brightest_other_over_needle", "dark_fraction"},
                      4);
  for (const auto& [name, s] : rows) {
    t.addRow({name, double(s.tissue_patches), s.tissue_mean_grey, s.speckle_snr,
              s.speckle_lateral_px, s.speckle_axial_px, s.needle_grey, s.needle_contrast,
              s.brightest_other_over_needle, s.dark_fraction});
    using ng::report::jsonNumber;
    js << ",\n  \"realism_speckle_snr_" << name << "\": " << jsonNumber(s.speckle_snr)
       << ",\n  \"realism_speckle_lateral_px_" << name << "\": " << jsonNumber(s.speckle_lateral_px)
       << ",\n  \"realism_speckle_axial_px_" << name << "\": " << jsonNumber(s.speckle_axial_px)
       << ",\n  \"realism_needle_contrast_" << name << "\": " << jsonNumber(s.needle_contrast)
       << ",\n  \"realism_brightest_other_over_needle_" << name
       << "\": " << jsonNumber(s.brightest_other_over_needle);
  }
  t.writeCsv(dir + "/realism.csv");
}

/// Better than the Hough baseline on a sequence: found in at least half the frames, and a lower
/// median tip error over its found frames (or the baseline found nothing). (The baseline reports
/// a line in nearly every frame; the tracker refuses where it sees no needle.)
bool betterThanHough(const Summary& s, const Summary& hough) {
  return s.found_fraction >= 0.5 && (hough.found_fraction == 0 || s.median < hough.median);
}

/// The even (tuned on) and odd (held-out) halves, and the held-out imager sequences. Returns
/// whether the tracker beat the Hough baseline on every synthetic sequence it ran.
bool writeHalvesAndHeldOut(const std::vector<Result>& fresh, const std::vector<Truth>& truth,
                           const std::string& dir, std::ostringstream& js) {
  using ng::report::jsonNumber;
  for (const auto& [name, parity] : {std::pair<std::string, int>{"even", 0}, {"odd", 1}}) {
    const Summary h = summarise(fresh, truth, parity);
    js << ",\n  \"tip_error_px_median_" << name << "\": " << jsonNumber(h.median)
       << ",\n  \"tip_error_px_p90_" << name << "\": " << jsonNumber(h.p90)
       << ",\n  \"found_fraction_" << name << "\": " << jsonNumber(h.found_fraction)
       << ",\n  \"confident_wrong_" << name << "\": " << h.confident_wrong;
  }
  const ng::scene::Scene scene = ng::scene::loadSceneSpec("steering_workspace");
  ng::report::Table table({"sequence", "frame", "held_out", "found", "confident", "tip_error_px",
                           "angle_error_deg", "ms"});
  std::vector<SyntheticRun> runs;
  // NG_TRACKING_TUNING_ONLY=1: the tuning sequences only (for studying failures without ever
  // seeing a held-out frame or error).
  const char* tuning_only = std::getenv("NG_TRACKING_TUNING_ONLY");
  const bool skip_held_out = tuning_only && std::string(tuning_only) == "1";
  // NG_TRACKING_ONLY=PREFIX: the synthetic sequences whose name starts with it only (with the
  // above, never a held-out one).
  const char* only = std::getenv("NG_TRACKING_ONLY");
  for (const SyntheticSpec& spec : syntheticSpecs()) {
    if (only && *only && spec.name.rfind(only, 0) != 0)
      continue;
    if (!(skip_held_out && spec.held_out))
      runs.push_back(syntheticRun(scene, spec, &table, dir));
  }
  table.writeCsv(dir + "/synthetic.csv");
  // Pooled over each set: the tuning set and the held-out set, reported apart.
  bool better_everywhere = true;
  for (const bool held_out : {false, true}) {
    std::vector<double> medians, p90s;
    int wrong = 0;
    double found = 0;
    for (const SyntheticRun& r : runs) {
      if (r.spec->held_out != held_out)
        continue;
      medians.push_back(r.summary.median);
      p90s.push_back(r.summary.p90);
      wrong += r.summary.confident_wrong;
      found += r.summary.found_fraction;
      const std::string key = (held_out ? "heldout_" : "") + r.spec->name;
      js << ",\n  \"" << key << "_found_fraction\": " << jsonNumber(r.summary.found_fraction)
         << ",\n  \"" << key << "_tip_error_px_median\": " << jsonNumber(r.summary.median)
         << ",\n  \"" << key << "_tip_error_px_p90\": " << jsonNumber(r.summary.p90) << ",\n  \""
         << key << "_angle_error_deg_median\": " << jsonNumber(r.summary.angle_median) << ",\n  \""
         << key << "_confident_wrong\": " << r.summary.confident_wrong << ",\n  \"" << key
         << "_hough_found_fraction\": " << jsonNumber(r.hough.found_fraction) << ",\n  \"" << key
         << "_hough_tip_error_px_median\": " << jsonNumber(r.hough.median) << ",\n  \"" << key
         << "_better_than_hough\": " << (betterThanHough(r.summary, r.hough) ? "true" : "false");
      better_everywhere = better_everywhere && betterThanHough(r.summary, r.hough);
      std::cout << "[tracking_real] " << key << ": found " << r.summary.found_fraction
                << ", median " << r.summary.median << " px, p90 " << r.summary.p90
                << " px, confident wrong " << r.summary.confident_wrong << "\n";
    }
    if (medians.empty())
      continue;
    const std::string set = held_out ? "synthetic_heldout" : "synthetic_tuning";
    js << ",\n  \"" << set << "_tip_error_px_median_worst\": "
       << jsonNumber(*std::max_element(medians.begin(), medians.end())) << ",\n  \"" << set
       << "_tip_error_px_p90_worst\": " << jsonNumber(*std::max_element(p90s.begin(), p90s.end()))
       << ",\n  \"" << set << "_found_fraction_mean\": " << jsonNumber(found / medians.size())
       << ",\n  \"" << set << "_confident_wrong\": " << wrong;
  }
  return better_everywhere;
}

// ---- synthetic convex-probe sequences (convex_ultrasound.h) --------------------------------

/// A convex sequence: the needle in-plane from the probe's end, steep or shallow; `held_out`
/// ones are never looked at while tuning (their seeds and layouts were fixed with the tuning
/// ones, before any tuning).
struct ConvexSpec {
  std::string name;
  bool held_out;
  im::ConvexInsertion c;
};

im::ConvexInsertion convex(std::uint64_t seed, cv::Size size, double entry, double angle_deg,
                           double step_px) {
  im::ConvexInsertion c;
  c.seed = seed;
  c.size = size;
  c.entry = entry;
  c.angle_deg = angle_deg;
  c.step_px = step_px;
  return c;
}

const std::vector<ConvexSpec>& convexSpecs() {
  const cv::Size wide(720, 440), crop(580, 400);
  static std::vector<ConvexSpec> specs;
  if (!specs.empty())
    return specs;
  auto add = [](const std::string& name, bool held_out, im::ConvexInsertion c) {
    specs.push_back({name, held_out, c});
    return &specs.back().c;
  };
  add("tune_convex_a", false, convex(601, wide, -0.8, 35, 8));
  add("tune_convex_b", false, convex(603, wide, 0.75, 45, 6));
  add("tune_convex_c", false, convex(605, wide, -1.1, 25, 8));  // through the fan's edge
  add("tune_convex_d", false, convex(607, wide, -0.6, 60, 7))->layer_amplitude = 2.2;
  {
    im::ConvexInsertion* c = add("tune_convex_e", false, convex(609, wide, 0.9, 30, 20));
    c->decorrelation = 0.6;  // sparse: frames far apart
  }
  add("tune_convex_f", false, convex(611, wide, -0.85, 40, 8))->appear_at = 5;
  add("tune_convex_g", false, convex(613, wide, -0.7, 72, 6));  // nearly along the beam
  add("tune_convex_h", false, convex(615, crop, -0.9, 30, 8))->apex_dx_px = -80;
  {
    im::ConvexInsertion* c = add("tune_convex_i", false, convex(617, wide, 0.8, 50, 8));
    c->gain_db = -6;
    c->noise_std = 0.2;
  }
  add("tune_convex_j", false, convex(619, wide, -0.8, 35, 8))->appear_at = -1;  // no needle
  add("tune_convex_k", false, convex(621, wide, 0.85, 20, 9));
  {
    im::ConvexInsertion* c = add("tune_convex_l", false, convex(623, wide, 0.75, 45, 8));
    c->face_radius_px = 70;  // a phased-array-like small face, wide sector
    c->half_angle_rad = 0.65;
    c->face_top_px = 8;
  }
  add("tune_convex_m", false, convex(625, crop, -0.85, 30, 8))->appear_at = -1;  // no needle
  {  // no needle under a small face: its arc's chords and tangents are no needle entering
    im::ConvexInsertion* c = add("tune_convex_n", false, convex(627, wide, 0.8, 40, 8));
    c->appear_at = -1;
    c->face_radius_px = 70;
    c->half_angle_rad = 0.65;
  }
  {  // a needle entering at a shallow angle to the face, from its first frames
    im::ConvexInsertion* c = add("tune_convex_o", false, convex(629, crop, 0.8, 33, 8));
    c->apex_dx_px = 60;
    c->layers = 3;
    c->start_px = 45;
  }
  add("tune_convex_p", false, convex(631, wide, -1.05, 38, 8))->appear_at = 3;  // fan's edge
  {
    im::ConvexInsertion* c = add("convex_a", true, convex(701, crop, -0.85, 35, 10));
    c->layers = 3;
  }
  {
    im::ConvexInsertion* c = add("convex_b", true, convex(703, wide, 0.8, 28, 8));
    c->half_angle_rad = 0.45;
    c->face_radius_px = 260;
  }
  {
    im::ConvexInsertion* c = add("convex_c", true, convex(705, crop, 1.05, 42, 18));
    c->decorrelation = 0.5;
  }
  add("convex_d", true, convex(707, wide, -0.75, 60, 7))->layer_amplitude = 2.5;
  {
    im::ConvexInsertion* c = add("convex_e", true, convex(709, wide, -0.9, 45, 8));
    c->appear_at = 4;
    c->gain_db = 4;
  }
  {
    im::ConvexInsertion* c = add("convex_f", true, convex(711, crop, 0.7, 25, 8));
    c->noise_std = 0.25;
    c->elevation_slope = 0.01;
  }
  add("convex_g", true, convex(713, crop, 0.8, 35, 8))->appear_at = -1;  // no needle
  {
    im::ConvexInsertion* c = add("convex_h", true, convex(715, wide, -0.8, 38, 8));
    c->face_radius_px = 60;  // a phased-array-like small face, wide sector
    c->half_angle_rad = 0.7;
    c->face_top_px = 5;
  }
  return specs;
}

struct ConvexRun {
  const ConvexSpec* spec = nullptr;
  std::vector<Result> rs, hough;  ///< frames with the needle
  std::vector<Truth> ts;
  int empty_frames = 0, empty_found = 0, empty_confident = 0;  ///< frames without the needle
};

/// One convex sequence through SequenceTracker (no prior) and the Hough baseline; rows into
/// `table`, overlays of its last frame into `dir`.
ConvexRun convexRun(const ConvexSpec& spec, ng::report::Table* table, const std::string& dir) {
  ConvexRun run;
  run.spec = &spec;
  const im::ConvexScene scene = spec.c.scene();
  im::SequenceTracker tracker(im::AcquisitionOptions{});
  im::TrackerConfig hough_config;
  hough_config.geometry.pixel_size_m = kAssumedPixel_m;
  hough_config.geometry.rows = spec.c.size.height;
  hough_config.geometry.cols = spec.c.size.width;
  hough_config.geometry.origin_m = im::Point2(0.0, spec.c.size.height * kAssumedPixel_m);
  for (int k = 0; k < spec.c.frames; ++k) {
    Truth t;
    const std::vector<cv::Point2d> pts = spec.c.needleAt(k, &t.tip, &t.angle_rad);
    const cv::Mat image = im::renderConvexFrame(scene, spec.c.size, pts, std::uint64_t(k));
    const Result r = trackTimed(tracker, image);
    // A needle with less than the acquisition's minimum length in view is no needle yet.
    const bool has_needle = spec.c.visibleLength(k) >= im::AcquisitionOptions{}.min_length_px;
    const double e = r.found && has_needle ? cv::norm(r.tip - t.tip) : std::nan("");
    table->addRow({spec.name, double(k), spec.held_out ? 1.0 : 0.0, has_needle ? 1.0 : 0.0,
                   r.found ? 1.0 : 0.0, r.confident ? 1.0 : 0.0, e,
                   r.found && has_needle ? angleError(r.angle_rad, t.angle_rad) : std::nan(""),
                   r.ms, r.cpu_ms});
    const char* study = std::getenv("NG_TRACKING_STUDY");
    if (study && std::string(study) == "1" && !spec.held_out) {
      std::cerr << spec.name << " " << k << ": truth (" << t.tip.x << ", " << t.tip.y << ") est ("
                << r.tip.x << ", " << r.tip.y << ") found " << r.found << " conf " << r.confident
                << ": " << r.message << "\n";
      overlay(image, t, r, spec.name + " " + std::to_string(k),
              dir + "/study_" + spec.name + "_" + std::to_string(k) + ".png");
    }
    if (k == spec.c.frames - 1)
      overlay(image, t, r, spec.name, dir + "/convex_" + spec.name + ".png");
    if (!has_needle) {
      ++run.empty_frames;
      run.empty_found += r.found ? 1 : 0;
      run.empty_confident += r.confident ? 1 : 0;
      continue;
    }
    run.rs.push_back(r);
    run.ts.push_back(t);
    run.hough.push_back(fromDetection(im::houghBaselineTip(image, hough_config, std::nullopt),
                                      hough_config.geometry, 0.0));
  }
  return run;
}

/// The convex sequences, per sequence and pooled per set (tuning, held out): found fraction,
/// tip error median and p90 over every frame of the set, angle error, confident wrong (also a
/// confident tip in a frame without the needle), CPU frames per second, the Hough baseline.
/// Returns whether the held-out set met every target.
bool writeConvex(const std::string& dir, std::ostringstream& js) {
  using ng::report::jsonNumber;
  ng::report::Table table({"sequence", "frame", "held_out", "needle", "found", "confident",
                           "tip_error_px", "angle_error_deg", "ms", "cpu_ms"});
  const char* tuning_only = std::getenv("NG_TRACKING_TUNING_ONLY");
  const bool skip_held_out = tuning_only && std::string(tuning_only) == "1";
  const char* only = std::getenv("NG_TRACKING_ONLY");
  std::vector<ConvexRun> runs;
  for (const ConvexSpec& spec : convexSpecs()) {
    if ((only && *only && spec.name.rfind(only, 0) != 0) || (skip_held_out && spec.held_out))
      continue;
    runs.push_back(convexRun(spec, &table, dir));
  }
  table.writeCsv(dir + "/convex.csv");
  bool met = false;
  for (const bool held_out : {false, true}) {
    std::vector<Result> all, all_hough;
    std::vector<Truth> truth;
    int empty_confident = 0, empty_found = 0, empty = 0;
    bool better_everywhere = true;
    for (const ConvexRun& r : runs) {
      if (r.spec->held_out != held_out)
        continue;
      const std::string key = (held_out ? "heldout_" : "") + r.spec->name;
      empty += r.empty_frames, empty_found += r.empty_found, empty_confident += r.empty_confident;
      if (r.rs.empty()) {  // no needle in the sequence: "not found" is the right answer
        js << ",\n  \"" << key << "_confident_without_needle\": " << r.empty_confident << ",\n  \""
           << key << "_not_found_fraction\": "
           << jsonNumber(double(r.empty_frames - r.empty_found) / std::max(r.empty_frames, 1));
        std::cout << "[tracking_real] " << key << " (no needle): not found in "
                  << r.empty_frames - r.empty_found << " of " << r.empty_frames
                  << " frames, confident in " << r.empty_confident << "\n";
        continue;
      }
      const Summary s = summarise(r.rs, r.ts), h = summarise(r.hough, r.ts);
      all.insert(all.end(), r.rs.begin(), r.rs.end());
      all_hough.insert(all_hough.end(), r.hough.begin(), r.hough.end());
      truth.insert(truth.end(), r.ts.begin(), r.ts.end());
      better_everywhere = better_everywhere && betterThanHough(s, h);
      js << ",\n  \"" << key << "_found_fraction\": " << jsonNumber(s.found_fraction) << ",\n  \""
         << key << "_tip_error_px_median\": " << jsonNumber(s.median) << ",\n  \"" << key
         << "_tip_error_px_p90\": " << jsonNumber(s.p90) << ",\n  \"" << key
         << "_angle_error_deg_median\": " << jsonNumber(s.angle_median) << ",\n  \"" << key
         << "_confident_wrong\": " << s.confident_wrong + r.empty_confident << ",\n  \"" << key
         << "_hough_tip_error_px_median\": " << jsonNumber(h.median) << ",\n  \"" << key
         << "_better_than_hough\": " << (betterThanHough(s, h) ? "true" : "false");
      std::cout << "[tracking_real] " << key << ": found " << s.found_fraction << ", median "
                << s.median << " px, p90 " << s.p90 << " px, angle " << s.angle_median
                << " deg, confident wrong " << s.confident_wrong + r.empty_confident << ", hough "
                << h.median << " px\n";
    }
    if (all.empty())
      continue;
    const Summary s = summarise(all, truth), h = summarise(all_hough, truth);
    const std::string set = held_out ? "convex_heldout" : "convex_tuning";
    const int wrong = s.confident_wrong + empty_confident;
    js << ",\n  \"" << set << "_found_fraction\": " << jsonNumber(s.found_fraction) << ",\n  \""
       << set << "_tip_error_px_median\": " << jsonNumber(s.median) << ",\n  \"" << set
       << "_tip_error_px_p90\": " << jsonNumber(s.p90) << ",\n  \"" << set
       << "_angle_error_deg_median\": " << jsonNumber(s.angle_median) << ",\n  \"" << set
       << "_confident_wrong\": " << wrong << ",\n  \"" << set
       << "_frames_without_needle\": " << empty << ",\n  \"" << set
       << "_found_without_needle\": " << empty_found << ",\n  \"" << set
       << "_without_needle_not_found_fraction\": "
       << jsonNumber(empty > 0 ? double(empty - empty_found) / empty : std::nan("")) << ",\n  \""
       << set << "_fps_cpu\": " << jsonNumber(s.fps_cpu) << ",\n  \"" << set
       << "_fps\": " << jsonNumber(s.fps) << ",\n  \"" << set
       << "_hough_tip_error_px_median\": " << jsonNumber(h.median) << ",\n  \"" << set
       << "_better_than_hough_every_sequence\": " << (better_everywhere ? "true" : "false");
    const bool ok = s.found_fraction >= 0.95 && s.median <= 8 && s.p90 <= 15 &&
                    s.angle_median <= 3 && wrong == 0 && s.fps_cpu >= 30 && better_everywhere;
    js << ",\n  \"" << set << "_targets_met\": " << (ok ? "true" : "false");
    met = held_out && ok;
  }
  return met;
}

}  // namespace

int main(int argc, char** argv) {
  const auto args = ng::report::parseBenchArgs(argc, argv, "bench_tracking_real");
  if (!args)
    return 2;
  cv::setNumThreads(1);  // every figure is for one core
  im::keepFreedMemory();
  const char* shared = std::getenv("NG_SHARED_DATA");
  const fs::path data = fs::path(shared ? shared : "/work/shared/data") / "us_needle_invitro";
  std::vector<fs::path> files;
  std::vector<cv::Mat> frames;
  std::vector<Truth> truth;
  std::vector<cv::Mat> masks;
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
    masks.push_back(mask);
  }
  im::TrackerConfig config;
  config.geometry.pixel_size_m = kAssumedPixel_m;
  config.geometry.rows = frames[0].rows;
  config.geometry.cols = frames[0].cols;
  config.geometry.origin_m = im::Point2(0.0, frames[0].rows * kAssumedPixel_m);
  im::SequenceTracker tracker(im::AcquisitionOptions{});
  std::vector<Result> fresh, old, hough;
  for (const cv::Mat& frame : frames) {
    fresh.push_back(trackTimed(tracker, frame));
    auto t0 = std::chrono::steady_clock::now();
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
     << ",\n  \"fps_720x440_cpu\": " << jsonNumber(n.fps_cpu)
     << ",\n  \"baseline_tip_error_px_median\": " << jsonNumber(h.median)
     << ",\n  \"baseline_found_fraction\": " << jsonNumber(h.found_fraction)
     << ",\n  \"old_found_fraction\": " << jsonNumber(o.found_fraction)
     << ",\n  \"old_tip_error_px_median\": " << jsonNumber(o.median);
  const bool better_synthetic = writeHalvesAndHeldOut(fresh, truth, args->out_dir, js);
  // The recorded frames and every synthetic sequence ("better than the Hough baseline
  // on every sequence").
  js << ",\n  \"better_than_hough_recorded\": " << (betterThanHough(n, h) ? "true" : "false")
     << ",\n  \"better_than_hough_every_sequence\": "
     << (betterThanHough(n, h) && better_synthetic ? "true" : "false");
  writeRealism(realism(ng::scene::loadSceneSpec("steering_workspace"), frames, masks),
               args->out_dir, js);
  const bool convex_met = writeConvex(args->out_dir, js);
  js << ",\n  \"targets_met\": "
     << ((n.found_fraction >= 0.95 && n.median <= 8 && n.p90 <= 15 && n.angle_median <= 3 &&
          n.confident_wrong == 0 && n.fps_cpu >= 30 && !(h.median < n.median))
             ? "true"
             : "false")
     << ",\n  \"targets_met_convex\": " << (convex_met ? "true" : "false") << "\n}\n";
  ng::report::writeTextFile(args->out_dir + "/summary.json", js.str());
  ng::report::writeTextFile(
      args->out_dir + "/plot.json",
      "[{\"csv\": \"per_frame.csv\", \"x\": \"frame_index\", \"y\": \"tip_error_px\", \"group\": "
      "\"method\", \"title\": \"tip error per frame (us_needle_invitro)\", \"png\": "
      "\"tip_error.png\"}]\n");
  return 0;
}
