// Benchmark of needle-tip tracking from images on steering_workspace:
// 1. accuracy: seeded needle insertions (entry, flips and deflections as in 5.3) imaged by the
//    simulated imager in 640 x 480 frames (0.2 mm pixels) in both modalities over noise levels;
//    at every step the TipTracker (ridge + RANSAC arc + filter) output, its raw single-frame
//    detection and the plain OpenCV HoughLinesP baseline (same window, same prior) against the
//    true tip: tip error [mm], heading error [deg], frames per second on one core;
// 2. closed loop: the same seeded trials from the policy's best start with ground-truth and with
//    image feedback (runGuidedTrial), success rate with its 95 % interval against noise.
// Ultrasound runs on both of the imager's renderers (UltrasoundModel classic and realistic):
// the keys without a suffix are the classic renderer's; the realistic ones end in _realistic.
// Usage: bench_tracking --out DIR [--quick] [--scene SPEC]
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <map>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"
#include "needle_guidance/procedures/guided_trial.h"
#include "needle_guidance/report/bench_args.h"
#include "needle_guidance/report/statistics.h"
#include "needle_guidance/report/table.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/monte_carlo.h"
#include "needle_guidance/steering/value_iteration.h"

namespace ng = needle_guidance;
namespace im = ng::imaging;
namespace st = ng::steering;

namespace {

using needle_guidance::kPi;
constexpr double kMmPerM = 1e3;
constexpr double kDegPerRad = 180.0 / kPi;
constexpr int kCols = 640;
constexpr int kRows = 480;
constexpr double kPixel_m = 0.2e-3;
/// The devices' default settings: ultrasound 0.1 noise with a 0.3 mm PSF; fluoroscopy the
/// scene's (0.02, 0.2 mm).
constexpr double kUsNoise = 0.1;
constexpr double kUsBlur_m = 0.3e-3;
constexpr double kFluoroNoise = 0.02;
constexpr double kFluoroBlur_m = 0.2e-3;
const std::vector<double> kNoiseLevels = {0.0, 0.05, 0.1, 0.2, 0.3};
/// Fluoroscopy adds its default (0.02) to the sweep.
const std::vector<double> kFluoroNoiseLevels = {0.0, 0.02, 0.05, 0.1, 0.2, 0.3};
/// Entries of the accuracy sequences: heights and angles that keep most of them in view.
constexpr double kEntryMinY_m = 0.02, kEntryMaxY_m = 0.08;
constexpr double kEntryMaxAngle_rad = 0.35;
constexpr double kFlipProbability = 0.3;
constexpr int kMaxSequenceSteps = 9;
constexpr std::uint64_t kSequenceSeed = 2026;
constexpr std::uint64_t kTrialSeed = 1;
constexpr double kWithin_mm = 1.0;

double secondsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

double headingError(double a, double b) {
  return std::abs(std::remainder(a - b, 2.0 * kPi));
}

/// One imaging device of the sweep: modality and, in ultrasound, the renderer.
struct Device {
  im::Modality modality = im::Modality::kUltrasound;
  im::UltrasoundModel model = im::UltrasoundModel::kClassic;
  bool realistic() const {
    return modality == im::Modality::kUltrasound && model == im::UltrasoundModel::kRealistic;
  }
  /// "ultrasound", "fluoroscopy" (the modality column of the CSV) and the renderer apart.
  std::string renderer() const {
    return modality == im::Modality::kUltrasound ? im::toString(model) : "-";
  }
  /// Headline key suffix: "_us", "_fluoro", "_us_realistic".
  std::string suffix() const {
    return modality == im::Modality::kFluoroscopy ? "_fluoro"
           : realistic()                          ? "_us_realistic"
                                                  : "_us";
  }
};

im::ImagerConfig deviceConfig(const ng::scene::Scene& scene, const Device& device, double noise,
                              std::uint64_t seed) {
  const im::Modality modality = device.modality;
  im::ImagerConfig c = im::imagerConfigFromScene(scene, seed);
  c.modality = modality;
  c.ultrasound_model = device.model;
  c.geometry = im::fieldOfView(scene, kPixel_m, kCols, kRows);
  c.noise_std = noise;
  c.blur_sigma_m = modality == im::Modality::kUltrasound ? kUsBlur_m : kFluoroBlur_m;
  c.drop_probability = 0.0;
  return c;
}

struct Errors {
  std::vector<double> tip_mm, heading_deg;
  int attempts = 0;
  double seconds = 0.0;
  void add(const ng::geometry::Point2& p, double theta, const st::TipPose& truth) {
    tip_mm.push_back((p - truth.p_SceneTip).norm() * kMmPerM);
    heading_deg.push_back(headingError(theta, truth.theta_rad) * kDegPerRad);
  }
};

/// Fraction of all attempts (misses count as outside) with a tip error within limit_mm.
double within(const Errors& e, double limit_mm) {
  const auto n =
      std::count_if(e.tip_mm.begin(), e.tip_mm.end(), [&](double v) { return v <= limit_mm; });
  return e.attempts > 0 ? double(n) / e.attempts : 0.0;
}

/// An example frame with the truth (green) and the estimate (red) drawn, for the report.
void writeExample(const std::string& path, const cv::Mat& frame, const im::ImageGeometry& g,
                  const st::TipPose& truth, const im::TipEstimate& est,
                  const im::Detection& hough) {
  cv::Mat bgr;
  cv::cvtColor(frame, bgr, cv::COLOR_GRAY2BGR);
  auto arrow = [&](const st::TipPose& p, const cv::Scalar& colour) {
    const cv::Point2d a = g.toPixel(p.p_SceneTip);
    const cv::Point2d b(a.x + 25.0 * std::cos(p.theta_rad), a.y - 25.0 * std::sin(p.theta_rad));
    cv::circle(bgr, a, 5, colour, 1, cv::LINE_AA);
    cv::line(bgr, a, b, colour, 1, cv::LINE_AA);
  };
  arrow(truth, cv::Scalar(0, 200, 0));
  arrow(est.tip, cv::Scalar(0, 0, 255));
  if (hough.found) {
    cv::drawMarker(bgr, g.toPixel(hough.p_SceneTip), cv::Scalar(255, 200, 0), cv::MARKER_CROSS, 10,
                   1);
  }
  cv::putText(bgr, "green truth, red tracker (" + im::toString(est.status) + "), cyan Hough",
              cv::Point(8, 18), cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(255, 255, 255), 1,
              cv::LINE_AA);
  cv::imwrite(path, bgr);
}

/// What the accuracy sweep and the closed loop share.
struct Bench {
  ng::report::BenchArgs args;
  ng::scene::Scene scene;
  st::SteeringProblem problem;
  ng::robot::SteerableNeedleConfig needle_config;
  double delta_m = 0.0;
  int sequences = 0;
  int trials = 0;
  std::map<std::string, double> headline;
  bool better_than_hough_everywhere = true;
};

/// One setting's errors: the tracker's filtered tip, its raw detection, the Hough baseline.
struct SettingErrors {
  Errors tracker, detection, hough;
  int confident = 0, estimates = 0;
};

/// One frame of a sequence: the three methods against the truth, a CSV row, maybe an example.
void scoreFrame(const Bench& b, const Device& device, double noise, int seq, int step,
                const im::Frame& frame, const im::ImagerConfig& config,
                const im::TrackerConfig& tracker_config, im::TipTracker& tracker,
                const im::TipEstimate& predicted, const st::TipPose& truth, SettingErrors& e,
                ng::report::Table& frames_csv, bool& example_written) {
  im::SearchPrior prior;
  prior.tip = predicted.tip;
  prior.covariance = predicted.covariance;
  auto t0 = std::chrono::steady_clock::now();
  const im::TipEstimate est = tracker.onFrame(frame.image);
  e.tracker.seconds += secondsSince(t0);
  t0 = std::chrono::steady_clock::now();
  const im::Detection det = im::detectTip(frame.image, tracker_config, prior);
  e.detection.seconds += secondsSince(t0);
  t0 = std::chrono::steady_clock::now();
  const im::Detection hough = im::houghBaselineTip(frame.image, tracker_config, prior);
  e.hough.seconds += secondsSince(t0);
  ++e.tracker.attempts;
  ++e.detection.attempts;
  ++e.hough.attempts;
  ++e.estimates;
  e.confident += est.confident ? 1 : 0;
  const bool in_view = est.status != im::TrackStatus::kOutOfView;
  if (in_view) {
    e.tracker.add(est.tip.p_SceneTip, est.tip.theta_rad, truth);
  }
  if (det.found) {
    e.detection.add(det.p_SceneTip, det.theta_rad, truth);
  }
  if (hough.found) {
    e.hough.add(hough.p_SceneTip, hough.theta_rad, truth);
  }
  auto err = [&](bool ok, const ng::geometry::Point2& p, double theta, bool tip) {
    if (!ok) {
      return ng::report::Cell(std::string(""));
    }
    return ng::report::Cell(tip ? (p - truth.p_SceneTip).norm() * kMmPerM
                                : headingError(theta, truth.theta_rad) * kDegPerRad);
  };
  frames_csv.addRow({im::toString(device.modality), device.renderer(), noise, double(seq),
                     double(step), im::toString(est.status), double(est.confident ? 1 : 0),
                     err(in_view, est.tip.p_SceneTip, est.tip.theta_rad, true),
                     err(in_view, est.tip.p_SceneTip, est.tip.theta_rad, false),
                     err(det.found, det.p_SceneTip, det.theta_rad, true),
                     err(det.found, det.p_SceneTip, det.theta_rad, false),
                     err(hough.found, hough.p_SceneTip, hough.theta_rad, true),
                     err(hough.found, hough.p_SceneTip, hough.theta_rad, false)});
  if (!example_written && step >= 3 && est.status == im::TrackStatus::kTracked &&
      (noise == kUsNoise || noise == kFluoroNoise)) {
    example_written = true;
    writeExample(b.args.out_dir + "/example_" + im::toString(device.modality) +
                     (device.realistic() ? "_realistic" : "") + "_noise" +
                     std::to_string(int(std::lround(noise * 100))) + ".png",
                 frame.image, config.geometry, truth, est, hough);
  }
}

/// Section 1 for one (device, noise): seeded insertion sequences, every frame scored.
SettingErrors runSetting(const Bench& b, const Device& device, double noise,
                         ng::report::Table& frames_csv) {
  const im::ImagerConfig config = deviceConfig(b.scene, device, noise, kSequenceSeed);
  const im::FrameRenderer renderer(b.scene, config);
  const im::TrackerConfig tracker_config = im::trackerConfigFromScene(b.scene, config);
  ng::robot::SteerableNeedleConfig needle_config = b.needle_config;
  SettingErrors e;
  std::uint64_t frame_index = 0;
  bool example_written = false;
  std::mt19937_64 rng(kSequenceSeed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  for (int seq = 0; seq < b.sequences; ++seq) {
    ng::robot::EntryPose entry;
    entry.height_m = kEntryMinY_m + (kEntryMaxY_m - kEntryMinY_m) * u01(rng);
    entry.angle_rad = kEntryMaxAngle_rad * (2.0 * u01(rng) - 1.0);
    entry.bevel = u01(rng) < 0.5 ? st::Bevel::kLeft : st::Bevel::kRight;
    needle_config.seed = kSequenceSeed * 1000 + std::uint64_t(seq);
    ng::robot::SteerableNeedle needle(ng::steering::planarWorkspace(b.problem), needle_config,
                                      entry);
    im::TipTracker tracker(tracker_config);
    tracker.reset(needle.tip());
    std::uint32_t flips = 0;
    const int steps = 2 + int(u01(rng) * (kMaxSequenceSteps - 1));
    for (int step = 0; step < steps; ++step) {
      if (u01(rng) < kFlipProbability) {
        needle.flip();
        ++flips;
      }
      const auto moved = needle.insertTo(needle.insertedLength_m() + b.delta_m);
      const im::TipEstimate predicted =
          tracker.onDrive(needle.insertedLength_m(), needle.bevel(), flips);
      if (moved.outcome() != ng::robot::MotionOutcome::kMoved) {
        break;  // touched an obstacle or left the workspace: the sequence ends
      }
      const im::Frame frame = renderer.render(needle.pathPoints(0.5e-3), frame_index++);
      scoreFrame(b, device, noise, seq, step, frame, config, tracker_config, tracker, predicted,
                 needle.tip(), e, frames_csv, example_written);
    }
  }
  return e;
}

/// Section 1's rows, comparison with Hough and headline keys for one setting.
void recordSetting(Bench& b, const Device& device, double noise, const SettingErrors& e,
                   ng::report::Table& accuracy) {
  auto addRow = [&](const std::string& method, const Errors& err) {
    const double ms = err.attempts > 0 ? 1e3 * err.seconds / err.attempts : 0.0;
    accuracy.addRow(
        {im::toString(device.modality), device.renderer(), noise, method, double(err.attempts),
         err.attempts > 0 ? double(err.tip_mm.size()) / err.attempts : 0.0, within(err, kWithin_mm),
         ng::report::median(err.tip_mm), ng::report::quantile(err.tip_mm, 0.9),
         ng::report::median(err.heading_deg), ms, ms > 0.0 ? 1e3 / ms : 0.0});
  };
  addRow("tracker", e.tracker);
  addRow("detection", e.detection);
  addRow("hough", e.hough);
  const double ours = ng::report::median(e.detection.tip_mm);
  const double theirs = ng::report::median(e.hough.tip_mm);
  const double ours_found = double(e.detection.tip_mm.size()) / std::max(1, e.detection.attempts);
  const double theirs_found = double(e.hough.tip_mm.size()) / std::max(1, e.hough.attempts);
  // Better = a lower median error where found AND more frames within 1 mm of the truth
  // (a miss counts as outside): a detector cannot win by answering only easy frames. The
  // realistic renderer is reported apart (the comparison with Hough is made on the classic one).
  const double ours_within = within(e.detection, kWithin_mm);
  const double theirs_within = within(e.hough, kWithin_mm);
  if (!device.realistic() && !(ours < theirs && ours_within > theirs_within)) {
    b.better_than_hough_everywhere = false;
  }
  std::cout << "[tracking] " << im::toString(device.modality) << " (" << device.renderer()
            << ") noise " << noise << ": tracker median " << ng::report::median(e.tracker.tip_mm)
            << " mm / " << ng::report::median(e.tracker.heading_deg) << " deg, detection " << ours
            << " mm (found " << ours_found << ", within 1 mm " << ours_within << "), hough "
            << theirs << " mm (found " << theirs_found << ", within 1 mm " << theirs_within << "), "
            << 1e3 * e.tracker.seconds / std::max(1, e.tracker.attempts) << " ms/frame, confident "
            << double(e.confident) / std::max(1, e.estimates) << "\n";
  const std::string sx = device.suffix();
  if (device.modality == im::Modality::kUltrasound && noise == kUsNoise) {
    b.headline["tip_error_mm_median" + sx] = ng::report::median(e.tracker.tip_mm);
    b.headline["heading_error_deg_median" + sx] = ng::report::median(e.tracker.heading_deg);
    b.headline["detection_tip_error_mm_median" + sx] = ours;
    b.headline["hough_tip_error_mm_median" + sx] = theirs;
    b.headline["hough_heading_error_deg_median" + sx] = ng::report::median(e.hough.heading_deg);
    b.headline["confident_fraction" + sx] = double(e.confident) / std::max(1, e.estimates);
    const std::string fx = device.realistic() ? "_realistic" : "";
    b.headline["fps_640x480" + fx] =
        e.tracker.seconds > 0.0 ? e.tracker.attempts / e.tracker.seconds : 0.0;
    b.headline["hough_fps_640x480" + fx] =
        e.hough.seconds > 0.0 ? e.hough.attempts / e.hough.seconds : 0.0;
    if (device.realistic()) {
      b.headline["within_1mm_fraction_us_realistic"] = within(e.tracker, kWithin_mm);
    }
  }
  if (device.modality == im::Modality::kFluoroscopy && noise == kFluoroNoise) {
    b.headline["tip_error_mm_median_fluoro"] = ng::report::median(e.tracker.tip_mm);
    b.headline["heading_error_deg_median_fluoro"] = ng::report::median(e.tracker.heading_deg);
    b.headline["hough_tip_error_mm_median_fluoro"] = theirs;
  }
}

/// Section 1: every device over its noise sweep.
void runAccuracy(Bench& b) {
  ng::report::Table frames_csv(
      {"modality", "renderer", "noise_std", "sequence", "step", "status", "confident",
       "tracker_tip_mm", "tracker_heading_deg", "detection_tip_mm", "detection_heading_deg",
       "hough_tip_mm", "hough_heading_deg"},
      6);
  ng::report::Table accuracy(
      {"modality", "renderer", "noise_std", "method", "frames", "found_fraction",
       "within_1mm_fraction", "tip_error_mm_median", "tip_error_mm_p90", "heading_error_deg_median",
       "ms_per_frame", "fps"},
      6);
  const std::vector<Device> devices = {
      {im::Modality::kUltrasound, im::UltrasoundModel::kClassic},
      {im::Modality::kFluoroscopy, im::UltrasoundModel::kClassic},
      {im::Modality::kUltrasound, im::UltrasoundModel::kRealistic}};
  for (const Device& device : devices) {
    for (const double noise :
         device.modality == im::Modality::kUltrasound ? kNoiseLevels : kFluoroNoiseLevels) {
      recordSetting(b, device, noise, runSetting(b, device, noise, frames_csv), accuracy);
    }
  }
  frames_csv.writeCsv(b.args.out_dir + "/frames.csv");
  accuracy.writeCsv(b.args.out_dir + "/accuracy.csv");
}

/// Section 2: the same seeded trials from the best start with each kind of feedback.
void runClosedLoop(Bench& b, const st::PolicyTable& table, const st::BestStart& best) {
  ng::robot::EntryPose start;
  start.height_m = best.best.pose.p_SceneTip.y();
  start.angle_rad = best.best.pose.theta_rad;
  start.bevel = best.best.pose.bevel;
  ng::robot::SteerableNeedleConfig needle_config = b.needle_config;
  needle_config.seed = kTrialSeed;
  ng::robot::SteerableNeedle world(ng::steering::planarWorkspace(b.problem), needle_config, start);
  ng::report::Table loop_csv(
      {"feedback", "modality", "renderer", "noise_std", "trials", "successes", "success_rate",
       "ci_low", "ci_high", "tip_error_mm_median", "heading_error_deg_median",
       "unconfident_decisions", "frames_per_decision", "seconds"},
      6);
  struct Feedback {
    std::string name;
    Device device;
    double noise;
  };
  const Device us{im::Modality::kUltrasound, im::UltrasoundModel::kClassic};
  std::vector<Feedback> feedbacks = {{"ground_truth", us, 0.0}};
  for (const double noise : {0.05, 0.1, 0.2, 0.3}) {
    feedbacks.push_back({"image", us, noise});
  }
  feedbacks.push_back(
      {"image", {im::Modality::kFluoroscopy, im::UltrasoundModel::kClassic}, kFluoroNoise});
  feedbacks.push_back(
      {"image", {im::Modality::kUltrasound, im::UltrasoundModel::kRealistic}, kUsNoise});
  for (const Feedback& fb : feedbacks) {
    const bool image = fb.name == "image";
    // The whole workspace in view, as the imager node images it by default.
    im::ImagerConfig device = deviceConfig(b.scene, fb.device, fb.noise, kTrialSeed);
    device.geometry = im::fieldOfView(b.scene, kPixel_m);
    const im::FrameRenderer renderer(b.scene, device);
    im::TipTracker tracker(im::trackerConfigFromScene(b.scene, device));
    std::int64_t successes = 0;
    std::vector<double> tip_mm, heading_deg;
    int unconfident = 0, frames = 0, decisions = 0;
    std::uint64_t frame_index = 0;
    const auto t0 = std::chrono::steady_clock::now();
    for (int k = 0; k < b.trials; ++k) {
      const ng::procedures::GuidedTrial trial = ng::procedures::runGuidedTrial(
          world, start, b.delta_m, kTrialSeed * 100000 + std::uint64_t(k), table,
          image ? &renderer : nullptr, image ? &tracker : nullptr, frame_index);
      successes += trial.outcome == st::TrialOutcome::kReachedTarget ? 1 : 0;
      for (double e : trial.tip_errors_m)
        tip_mm.push_back(e * kMmPerM);
      for (double e : trial.heading_errors_rad)
        heading_deg.push_back(e * kDegPerRad);
      unconfident += trial.unconfident_decisions;
      frames += trial.frames;
      decisions += int(trial.tip_errors_m.size());
    }
    const double seconds = secondsSince(t0);
    const st::Interval ci = st::wilsonInterval(successes, b.trials);
    const double rate = double(successes) / b.trials;
    loop_csv.addRow({fb.name, image ? im::toString(fb.device.modality) : std::string("-"),
                     image ? fb.device.renderer() : std::string("-"), fb.noise, double(b.trials),
                     double(successes), rate, ci.low, ci.high, ng::report::median(tip_mm),
                     ng::report::median(heading_deg), double(unconfident),
                     decisions > 0 ? double(frames) / decisions : 0.0, seconds});
    std::cout << "[tracking] closed loop " << fb.name << " "
              << (image ? im::toString(fb.device.modality) + " (" + fb.device.renderer() + ")" : "")
              << " noise " << fb.noise << ": " << successes << "/" << b.trials << " = " << rate
              << " [" << ci.low << ", " << ci.high << "], tip error median "
              << ng::report::median(tip_mm) << " mm, " << unconfident << " unconfident, " << seconds
              << " s\n";
    const std::string fx = fb.device.realistic() ? "_realistic" : "";
    if (!image) {
      b.headline["closed_loop_success_truth"] = rate;
    } else if (fb.device.modality == im::Modality::kUltrasound && fb.noise == kUsNoise) {
      b.headline["closed_loop_success_tracked" + fx] = rate;
      b.headline["closed_loop_tracked" + fx + "_ci_low"] = ci.low;
      b.headline["closed_loop_tracked" + fx + "_ci_high"] = ci.high;
    }
  }
  loop_csv.writeCsv(b.args.out_dir + "/closed_loop.csv");
}

void writeSummary(const Bench& b, const st::BestStart& best) {
  std::ostringstream json;
  json << "{\n  \"bench\": \"tracking\",\n  \"scene\": \"" << b.scene.name
       << "\",\n  \"quick\": " << (b.args.quick ? "true" : "false") << ",\n  \"frame_size\": ["
       << kCols << ", " << kRows << "],\n  \"pixel_size_mm\": " << kPixel_m * kMmPerM
       << ",\n  \"default_us_noise_std\": " << kUsNoise
       << ",\n  \"default_fluoro_noise_std\": " << kFluoroNoise
       << ",\n  \"ultrasound_renderers\": [\"classic\", \"realistic\"]"
       << ",\n  \"sequences_per_setting\": " << b.sequences
       << ",\n  \"closed_loop_trials\": " << b.trials << ",\n  \"closed_loop_predicted_ps\": "
       << ng::report::jsonNumber(best.best.probability_of_success)
       << ",\n  \"detection_better_than_hough_every_level\": "
       << (b.better_than_hough_everywhere ? "true" : "false");
  for (const auto& [key, value] : b.headline) {
    json << ",\n  \"" << key << "\": " << ng::report::jsonNumber(value);
  }
  json << "\n}\n";
  ng::report::writeTextFile(b.args.out_dir + "/summary.json", json.str());
  ng::report::writeTextFile(
      b.args.out_dir + "/plot.json",
      R"json([{"csv": "accuracy.csv", "x": "noise_std", "y": "tip_error_mm_median", "group": "method", "filter": {"modality": "ultrasound", "renderer": "classic"},
  "title": "Ultrasound (classic renderer): median tip error vs noise (tracker, its raw detection, HoughLinesP)", "png": "tip_error_us.png"},
 {"csv": "accuracy.csv", "x": "noise_std", "y": "tip_error_mm_median", "group": "method", "filter": {"modality": "ultrasound", "renderer": "realistic"},
  "title": "Ultrasound (realistic renderer): median tip error vs noise", "png": "tip_error_us_realistic.png"},
 {"csv": "accuracy.csv", "x": "noise_std", "y": "tip_error_mm_median", "group": "method", "filter": {"modality": "fluoroscopy"}, "title": "Fluoroscopy: median tip error vs noise", "png": "tip_error_fluoro.png"},
 {"csv": "accuracy.csv", "x": "noise_std", "y": "heading_error_deg_median", "group": "method", "filter": {"modality": "ultrasound", "renderer": "classic"},
  "title": "Ultrasound (classic): median heading error vs noise", "png": "heading_error_us.png"},
 {"csv": "accuracy.csv", "x": "ms_per_frame", "y": "tip_error_mm_median", "group": "method", "points": true, "logy": true,
  "annotate": "noise_std", "title": "Speed against error: ms per 640x480 frame (one core) vs median tip error", "png": "speed_vs_error.png"},
 {"csv": "closed_loop.csv", "x": "noise_std", "y": "success_rate", "group": "renderer",
  "title": "Closed loop from the best start: success rate vs ultrasound noise (same seeded trials)", "png": "closed_loop.png"}]
)json");
  std::cout << json.str();
}

}  // namespace

int main(int argc, char** argv) {
  auto args = ng::report::parseBenchArgs(argc, argv, "bench_tracking");
  if (!args) {
    return 2;
  }
  if (args->scene == "prostate_sagittal") {
    args->scene = "steering_workspace";  // the bench's default scene
  }
  cv::setNumThreads(1);  // every figure is for one core
  Bench b;
  b.args = *args;
  b.scene = ng::scene::loadSceneSpec(args->scene);
  b.problem = st::problemFromScene(b.scene, "");
  b.delta_m = 2.0 * kPi * b.problem.params.radius_m / b.problem.params.orientations;
  b.needle_config.start_x_m = b.scene.steering->start_x_m;
  b.needle_config.min_height_m = b.scene.needle.min_height_m;
  b.needle_config.max_height_m = b.scene.needle.max_height_m;
  b.needle_config.sigma_insert_rad = b.problem.params.sigma_insert_rad;
  b.needle_config.sigma_flip_rad = b.problem.params.sigma_flip_rad;
  b.sequences = args->quick ? 25 : 120;
  b.trials = args->quick ? 40 : 300;

  runAccuracy(b);  // 1. accuracy over seeded insertion sequences
  const st::SteeringModel model(b.problem);
  const st::PolicyTable table = st::solveValueIteration(model);
  const st::BestStart best = table.bestStart(st::startOptionsFromScene(b.scene));
  if (!best) {
    std::cerr << "bench_tracking: no start state: " << best.message << "\n";
    return 1;
  }
  runClosedLoop(b, table, best);  // 2. closed loop
  writeSummary(b, best);
  return 0;
}
