// TipTracker, detectTip and houghBaselineTip on frames of the simulated imager (FrameRenderer)
// of steering_workspace: accuracy in both modalities and against the Hough baseline, the filter
// through dropped frames, and the hard cases — the tip leaving the field of view, a bright
// obstacle boundary crossing or running alongside the needle, heavy noise, unusable frames, a
// detection far from the prediction, a filter that started from a wrong pose — which must give
// the right tip or say "not confident", and never a NaN. Timings are printed, not asserted.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iterator>
#include <limits>
#include <opencv2/core.hpp>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/continuous_workspace.h"

namespace needle_guidance::imaging {
namespace {

using steering::Bevel;
using steering::TipPose;

constexpr double kDeg = kPi / 180.0;
constexpr double kMm = 1e-3;

// ---- the setting ----
constexpr double kPathSpacing_m = 0.1e-3;  // needle shape handed to the renderer
constexpr int kSubstepsPerStep = 4;        // frames per insertion step delta
constexpr double kDefaultNoise = 0.1;      // the ultrasound device's default
constexpr double kDefaultBlur_m = 0.3e-3;

// ---- targets and tolerances ----
constexpr double kMedianTipTol_m = 0.5e-3;            // median tip error
constexpr double kMedianHeadingTol_rad = 3.0 * kDeg;  // median heading error
constexpr double kMinFoundFraction = 0.9;             // single-frame detections found
constexpr double kMinTrackedFraction = 0.8;           // tracker frames with a fused detection
// Confident estimates: 95th percentiles of their errors, and the bound every one of them must
// keep in the hard cases (3 x the configured confident standard deviations).
constexpr double kConfidentTipP95Tol_m = 0.6e-3;
constexpr double kConfidentHeadingP95Tol_rad = 4.0 * kDeg;
constexpr double kConfidentTipBound_m = 1.5e-3;
constexpr double kConfidentHeadingBound_rad = 6.0 * kDeg;

const scene::Scene& workspace() {
  static const scene::Scene s = scene::loadSceneSpec("steering_workspace");
  return s;
}

double stepLength() {
  return 2.0 * kPi * workspace().needle.radius_of_curvature_m / workspace().steering->orientations;
}

ImagerConfig imager(Modality modality, double noise_std, double blur_m = kDefaultBlur_m,
                    std::uint64_t seed = 1) {
  ImagerConfig c = imagerConfigFromScene(workspace(), seed);
  c.modality = modality;
  c.noise_std = noise_std;
  c.blur_sigma_m = blur_m;
  c.drop_probability = 0.0;
  return c;
}

/// One moment of an insertion: the needle's shape and true tip, and what the robot knows.
struct Shot {
  std::vector<Point2> points;
  TipPose tip;
  double length_m = 0.0;
  std::uint32_t flips = 0;
};

/// A seeded insertion by the steerable needle of the robot (deflections drawn at every step's
/// start, flips by a seeded coin), kSubstepsPerStep shots per step; stops at a contact. The
/// first shot is the entry (length 0).
std::vector<Shot> insertion(double height_m, double angle_rad, Bevel bevel, int steps,
                            std::uint64_t seed, double flip_probability = 0.3) {
  const scene::Scene& sc = workspace();
  robot::SteerableNeedleConfig cfg;
  cfg.start_x_m = 0.0;
  cfg.min_height_m = sc.needle.min_height_m;
  cfg.max_height_m = sc.needle.max_height_m;
  cfg.sigma_insert_rad = sc.steering->sigma_insert_rad;
  cfg.sigma_flip_rad = sc.steering->sigma_flip_rad;
  cfg.seed = seed;
  robot::EntryPose entry;
  entry.height_m = height_m;
  entry.angle_rad = angle_rad;
  entry.bevel = bevel;
  robot::SteerableNeedle needle(steering::planarWorkspace(steering::problemFromScene(sc)), cfg,
                                entry);
  std::mt19937 coin(static_cast<std::uint32_t>(seed * 7919u + 13u));
  std::vector<Shot> out;
  std::uint32_t flips = 0;
  out.push_back({needle.pathPoints(kPathSpacing_m), needle.tip(), 0.0, 0});
  for (int k = 0; k < steps; ++k) {
    if (k > 0 && static_cast<double>(coin() % 1000u) < flip_probability * 1000.0) {
      needle.flip();
      ++flips;
    }
    if (!needle.beginInsertion()) {
      break;
    }
    const double start = needle.insertedLength_m();
    for (int j = 1; j <= kSubstepsPerStep; ++j) {
      if (needle.advanceTo(start + stepLength() * j / kSubstepsPerStep).outcome() !=
          robot::MotionOutcome::kMoved) {
        return out;
      }
      out.push_back(
          {needle.pathPoints(kPathSpacing_m), needle.tip(), needle.insertedLength_m(), flips});
    }
  }
  return out;
}

/// An exact insertion without the robot (no contact checks, so it may cross obstacles): from
/// `entry`, step k traces an arc of one step length with bevels[k] after the deflection
/// betas[k]; kSubstepsPerStep shots per step.
std::vector<Shot> syntheticInsertion(const TipPose& entry, const std::vector<Bevel>& bevels,
                                     const std::vector<double>& betas) {
  const double r = workspace().needle.radius_of_curvature_m;
  std::vector<Shot> out;
  std::vector<Point2> points{entry.p_SceneTip};
  out.push_back({points, entry, 0.0, 0});
  TipPose pose = entry;
  std::uint32_t flips = 0;
  double length = 0.0;
  for (std::size_t k = 0; k < bevels.size(); ++k) {
    if (bevels[k] != pose.bevel) {
      ++flips;
    }
    TipPose start = pose;
    start.bevel = bevels[k];
    start.theta_rad += k < betas.size() ? betas[k] : 0.0;
    const int pieces = static_cast<int>(std::ceil(stepLength() / kPathSpacing_m));
    for (int i = 1; i <= pieces; ++i) {
      const double s = stepLength() * i / pieces;
      pose = steering::advanceTip(start, steering::Control::kInsert, 0.0, s, r);
      points.push_back(pose.p_SceneTip);
      if (i % (pieces / kSubstepsPerStep) == 0 || i == pieces) {
        out.push_back({points, pose, length + s, flips});
      }
    }
    length += stepLength();
  }
  return out;
}

/// The insertions most tests use (fixed seeds): entries over the workspace's height, both
/// bevels, three entry angles.
const std::vector<std::vector<Shot>>& trajectories() {
  static const std::vector<std::vector<Shot>> t = [] {
    const double heights[] = {0.012, 0.02, 0.03, 0.05, 0.065, 0.08, 0.09, 0.015};
    std::vector<std::vector<Shot>> out;
    out.reserve(std::size(heights));
    for (int i = 0; i < 8; ++i) {
      out.push_back(insertion(heights[i], ((i % 3) - 1) * 10.0 * kDeg,
                              i % 2 == 0 ? Bevel::kLeft : Bevel::kRight, 7,
                              100 + static_cast<std::uint64_t>(i)));
    }
    return out;
  }();
  return t;
}

double tipError(const Point2& p, const TipPose& truth) {
  return (p - truth.p_SceneTip).norm();
}
double headingError(double theta, const TipPose& truth) {
  return std::abs(std::remainder(theta - truth.theta_rad, 2.0 * kPi));
}
// NaN for an empty sample, so that a test over no frames fails instead of passing.
double median(const std::vector<double>& v) {
  return v.empty() ? std::nan("") : upperMedian(v);
}
double percentile(const std::vector<double>& v, double q) {
  return v.empty() ? std::nan("") : orderStatistic(v, q);
}
bool inFrame(const ImageGeometry& g, const Point2& p) {
  const cv::Point2d px = g.toPixel(p);
  return px.x >= 0.0 && px.y >= 0.0 && px.x <= g.cols - 1 && px.y <= g.rows - 1;
}

bool allFinite(const Detection& d) {
  return d.p_SceneTip.allFinite() && std::isfinite(d.theta_rad) && d.covariance.allFinite() &&
         std::isfinite(d.residual_rms_m);
}
bool allFinite(const TipEstimate& e) {
  return e.tip.p_SceneTip.allFinite() && std::isfinite(e.tip.theta_rad) &&
         e.covariance.allFinite() && std::isfinite(e.inserted_length_m) && allFinite(e.detection);
}
/// Symmetric with positive eigenvalues.
bool positiveDefinite(const Eigen::Matrix3d& m) {
  if (!m.allFinite() ||
      (m - m.transpose()).cwiseAbs().maxCoeff() > 1e-12 * m.cwiseAbs().maxCoeff()) {
    return false;
  }
  return Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(m).eigenvalues().minCoeff() > 0.0;
}

// ---- single-frame detections ----

struct DetectionStats {
  std::vector<double> tip_m, heading_rad, ms;
  int attempts = 0;
  int found = 0;
  bool finite = true;
};

/// Detections on every in-view shot (past the first 3 mm) with a prior: the truth perturbed by
/// the given standard deviations (as a filter would predict it), with that covariance.
DetectionStats detectAll(const std::vector<std::vector<Shot>>& trajs, const ImagerConfig& ic,
                         bool baseline, double prior_pos_std_m, double prior_heading_std_rad,
                         std::size_t max_trajectories = 100) {
  const FrameRenderer renderer(workspace(), ic);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  std::mt19937 rng(5);
  std::normal_distribution<double> n01(0.0, 1.0);
  DetectionStats st;
  std::uint64_t index = 0;
  for (std::size_t t = 0; t < trajs.size() && t < max_trajectories; ++t) {
    for (const Shot& shot : trajs[t]) {
      if (shot.length_m < 3.0 * kMm || !inFrame(ic.geometry, shot.tip.p_SceneTip)) {
        continue;
      }
      const Frame f = renderer.render(shot.points, index++);
      SearchPrior prior;
      prior.tip = shot.tip;
      prior.tip.p_SceneTip += prior_pos_std_m * Point2(n01(rng), n01(rng));
      prior.tip.theta_rad += prior_heading_std_rad * n01(rng);
      prior.covariance =
          Eigen::Vector3d(prior_pos_std_m * prior_pos_std_m, prior_pos_std_m * prior_pos_std_m,
                          prior_heading_std_rad * prior_heading_std_rad)
              .asDiagonal();
      const auto t0 = std::chrono::steady_clock::now();
      const Detection d =
          baseline ? houghBaselineTip(f.image, tc, prior) : detectTip(f.image, tc, prior);
      st.ms.push_back(
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
      st.finite = st.finite && allFinite(d) && (!d.found || positiveDefinite(d.covariance));
      ++st.attempts;
      if (d.found) {
        ++st.found;
        st.tip_m.push_back(tipError(d.p_SceneTip, shot.tip));
        st.heading_rad.push_back(headingError(d.theta_rad, shot.tip));
      }
    }
  }
  return st;
}

void print(const std::string& what, const DetectionStats& s) {
  std::printf(
      "  %-40s found %3d/%3d  tip median %.3f p90 %.3f mm  heading median %.2f p90 %.2f deg"
      "  %.2f ms\n",
      what.c_str(), s.found, s.attempts, median(s.tip_m) * 1e3, percentile(s.tip_m, 0.9) * 1e3,
      median(s.heading_rad) / kDeg, percentile(s.heading_rad, 0.9) / kDeg, median(s.ms));
}

TEST(TrackerConfigTest, FromSceneAndValidation) {
  const ImagerConfig ic = imager(Modality::kUltrasound, kDefaultNoise);
  const TrackerConfig c = trackerConfigFromScene(workspace(), ic);
  EXPECT_DOUBLE_EQ(c.radius_of_curvature_m, 0.05);
  EXPECT_NEAR(c.step_length_m, 2.0 * kPi * 0.05 / 40.0, 1e-15);
  EXPECT_NEAR(c.sigma_insert_rad, 5.0 * kDeg, 1e-12);
  EXPECT_NEAR(c.sigma_flip_rad, 10.0 * kDeg, 1e-12);
  EXPECT_EQ(c.modality, Modality::kUltrasound);
  EXPECT_EQ(c.geometry.cols, ic.geometry.cols);
  EXPECT_EQ(c.geometry.rows, ic.geometry.rows);
  EXPECT_DOUBLE_EQ(c.needle_diameter_m, ic.needle_diameter_m);
  EXPECT_NO_THROW(c.validate());

  TrackerConfig bad = c;
  bad.radius_of_curvature_m = 0.0;
  EXPECT_THROW(bad.validate(), std::invalid_argument);
  bad = c;
  bad.sigma_insert_rad = std::nan("");
  EXPECT_THROW(bad.validate(), std::invalid_argument);
  bad = c;
  bad.gate_chi2 = -1.0;
  EXPECT_THROW(bad.validate(), std::invalid_argument);
  bad = c;
  bad.geometry.pixel_size_m = 0.0;
  EXPECT_THROW(bad.validate(), std::invalid_argument);
  EXPECT_THROW(TipTracker{bad}, std::invalid_argument);
  try {
    bad = c;
    bad.step_length_m = -1.0;
    bad.validate();
    FAIL() << "validate() accepted a negative step length";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("step_length_m"), std::string::npos) << e.what();
  }
  // A scene without a steering section has no needle model for the tracker.
  const scene::Scene prostate = scene::loadSceneSpec("prostate_sagittal");
  EXPECT_THROW(trackerConfigFromScene(prostate, ic), std::invalid_argument);

  EXPECT_EQ(toString(TrackStatus::kUninitialized), "uninitialized");
  EXPECT_EQ(toString(TrackStatus::kEntry), "entry");
  EXPECT_EQ(toString(TrackStatus::kTracked), "tracked");
  EXPECT_EQ(toString(TrackStatus::kPredicted), "predicted");
  EXPECT_EQ(toString(TrackStatus::kOutOfView), "out_of_view");
  EXPECT_EQ(toString(TrackStatus::kBadFrame), "bad_frame");
}

TEST(TipDetectorTest, AccurateOnRenderedFramesInBothModalities) {
  for (const Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    const DetectionStats s =
        detectAll(trajectories(), imager(m, kDefaultNoise), false, 0.5 * kMm, 3.0 * kDeg);
    print("detectTip " + toString(m) + " noise 0.1", s);
    EXPECT_TRUE(s.finite);
    EXPECT_GE(s.found, kMinFoundFraction * s.attempts) << toString(m);
    EXPECT_LE(median(s.tip_m), kMedianTipTol_m) << toString(m);
    EXPECT_LE(median(s.heading_rad), kMedianHeadingTol_rad) << toString(m);
  }
}

TEST(TipDetectorTest, BeatsTheHoughBaselineAtEveryNoiseLevel) {
  constexpr std::size_t kTrajectories = 4;
  for (const Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    for (const double noise : {0.0, 0.05, 0.1, 0.2, 0.3}) {
      const ImagerConfig ic = imager(m, noise);
      const DetectionStats d =
          detectAll(trajectories(), ic, false, 0.5 * kMm, 3.0 * kDeg, kTrajectories);
      const DetectionStats h =
          detectAll(trajectories(), ic, true, 0.5 * kMm, 3.0 * kDeg, kTrajectories);
      char name[64];
      std::snprintf(name, sizeof name, "%s noise %.2f", toString(m).c_str(), noise);
      print(std::string("detectTip ") + name, d);
      print(std::string("houghBaselineTip ") + name, h);
      EXPECT_TRUE(d.finite && h.finite) << name;
      EXPECT_LT(median(d.tip_m), median(h.tip_m)) << name;
      EXPECT_LT(median(d.heading_rad), median(h.heading_rad)) << name;
      EXPECT_GE(d.found, kMinFoundFraction * d.attempts) << name;
    }
  }
}

TEST(TipDetectorTest, WithoutPriorFindsTheNeedleInFluoroscopy) {
  // Acquisition: the whole frame, both curvature senses. (In ultrasound the obstacles' straight
  // bright boundaries compete with the needle without a prior; the tracker always has one.)
  const ImagerConfig ic = imager(Modality::kFluoroscopy, 0.02, 0.2e-3);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  const FrameRenderer renderer(workspace(), ic);
  std::vector<double> err;
  for (std::size_t t = 0; t < 3; ++t) {
    for (std::size_t k = 8; k < trajectories()[t].size(); k += 4) {
      const Shot& shot = trajectories()[t][k];
      const Detection d = detectTip(renderer.render(shot.points, k).image, tc, std::nullopt);
      EXPECT_TRUE(allFinite(d));
      if (d.found) {
        err.push_back(tipError(d.p_SceneTip, shot.tip));
      }
    }
  }
  ASSERT_GE(err.size(), 5u);
  EXPECT_LE(median(err), kMedianTipTol_m);
}

TEST(TipDetectorTest, UnusableFramesAreRefusedWithTheReason) {
  const ImagerConfig ic = imager(Modality::kUltrasound, kDefaultNoise);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  const cv::Size size = ic.geometry.size();
  SearchPrior prior;
  prior.tip = {Point2(0.02, 0.05), 0.0, Bevel::kLeft};
  prior.covariance = Eigen::Matrix3d::Identity() * 1e-6;
  struct Case {
    cv::Mat frame;
    const char* reason;
  };
  const std::vector<Case> cases = {
      {cv::Mat(), "empty"},
      {cv::Mat(size, CV_16UC1, cv::Scalar(1000)), "CV_8UC1"},
      {cv::Mat(size, CV_8UC3, cv::Scalar(10, 200, 30)), "CV_8UC1"},
      {cv::Mat(cv::Size(size.width + 1, size.height), CV_8UC1, cv::Scalar(0)),
       "calibration expects"},
      {cv::Mat(size, CV_8UC1, cv::Scalar(0)), "no contrast"},
      {cv::Mat(size, CV_8UC1, cv::Scalar(128)), "no contrast"},
  };
  for (const Case& c : cases) {
    for (const bool baseline : {false, true}) {
      for (const bool with_prior : {false, true}) {
        const std::optional<SearchPrior> p =
            with_prior ? std::optional<SearchPrior>(prior) : std::nullopt;
        const Detection d = baseline ? houghBaselineTip(c.frame, tc, p) : detectTip(c.frame, tc, p);
        EXPECT_FALSE(d.found) << c.reason;
        EXPECT_NE(d.message.find(c.reason), std::string::npos) << d.message;
        EXPECT_TRUE(allFinite(d));
      }
    }
  }
  // A usable frame without a needle: not found, no NaN.
  const FrameRenderer renderer(workspace(), ic);
  const Detection d = detectTip(renderer.render({}, 0).image, tc, prior);
  EXPECT_FALSE(d.found) << d.message;
  EXPECT_TRUE(allFinite(d));
  // A prior far outside the frame: an empty window, not found.
  SearchPrior outside = prior;
  outside.tip.p_SceneTip = Point2(1.0, 1.0);
  const Detection o = detectTip(renderer.render({}, 0).image, tc, outside);
  EXPECT_FALSE(o.found);
  EXPECT_TRUE(allFinite(o));
  // A non-finite prior does not produce NaN either.
  SearchPrior nan_prior = prior;
  nan_prior.tip.theta_rad = std::nan("");
  EXPECT_TRUE(allFinite(detectTip(renderer.render({}, 0).image, tc, nan_prior)));
}

// ---- the tracker ----

struct TrackRun {
  std::vector<double> tracked_tip_m, tracked_heading_rad;
  std::vector<double> confident_tip_m, confident_heading_rad;
  std::vector<TipEstimate> estimates;  // per frame
  std::vector<TipPose> truths;
  int frames = 0, tracked = 0, confident = 0;
  bool finite = true;
  bool pd = true;
  std::vector<double> ms;
};

/// A fresh TipTracker per trajectory: reset at the entry, then per shot onDrive (the robot's
/// length, bevel, flips) and onFrame (the rendered frame).
TrackRun track(const std::vector<std::vector<Shot>>& trajs, const ImagerConfig& ic,
               std::size_t max_trajectories = 100) {
  const FrameRenderer renderer(workspace(), ic);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  TrackRun run;
  std::uint64_t index = 0;
  for (std::size_t t = 0; t < trajs.size() && t < max_trajectories; ++t) {
    TipTracker tracker(tc);
    tracker.reset(trajs[t].front().tip);
    for (std::size_t k = 1; k < trajs[t].size(); ++k) {
      const Shot& shot = trajs[t][k];
      const TipEstimate drive = tracker.onDrive(shot.length_m, shot.tip.bevel, shot.flips);
      run.finite = run.finite && allFinite(drive);
      const Frame f = renderer.render(shot.points, index++);
      const auto t0 = std::chrono::steady_clock::now();
      const TipEstimate e = tracker.onFrame(f.image);
      run.ms.push_back(
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
      run.finite = run.finite && allFinite(e);
      run.pd = run.pd && positiveDefinite(e.covariance);
      ++run.frames;
      run.estimates.push_back(e);
      run.truths.push_back(shot.tip);
      const double err = tipError(e.tip.p_SceneTip, shot.tip);
      const double herr = headingError(e.tip.theta_rad, shot.tip);
      if (e.status == TrackStatus::kTracked) {
        ++run.tracked;
        run.tracked_tip_m.push_back(err);
        run.tracked_heading_rad.push_back(herr);
      }
      if (e.confident) {
        ++run.confident;
        run.confident_tip_m.push_back(err);
        run.confident_heading_rad.push_back(herr);
      }
    }
  }
  return run;
}

void print(const std::string& what, const TrackRun& r) {
  std::printf(
      "  %-28s frames %3d tracked %3d confident %3d | tracked: tip median %.3f p90 %.3f mm, "
      "heading median %.2f p90 %.2f deg | confident: tip p95 %.3f mm, heading p95 %.2f deg"
      " | %.2f ms/frame\n",
      what.c_str(), r.frames, r.tracked, r.confident, median(r.tracked_tip_m) * 1e3,
      percentile(r.tracked_tip_m, 0.9) * 1e3, median(r.tracked_heading_rad) / kDeg,
      percentile(r.tracked_heading_rad, 0.9) / kDeg, percentile(r.confident_tip_m, 0.95) * 1e3,
      percentile(r.confident_heading_rad, 0.95) / kDeg, median(r.ms));
}

/// Every confident estimate of the run is within the hard-case bounds; all finite.
void expectRightOrNotConfident(const TrackRun& r, const std::string& what) {
  EXPECT_TRUE(r.finite) << what;
  EXPECT_TRUE(r.pd) << what;
  for (std::size_t i = 0; i < r.estimates.size(); ++i) {
    const TipEstimate& e = r.estimates[i];
    if (!e.confident) {
      continue;
    }
    EXPECT_LE(tipError(e.tip.p_SceneTip, r.truths[i]), kConfidentTipBound_m)
        << what << " frame " << i << ": " << e.message;
    EXPECT_LE(headingError(e.tip.theta_rad, r.truths[i]), kConfidentHeadingBound_rad)
        << what << " frame " << i << ": " << e.message;
  }
}

TEST(TipTrackerTest, TracksInsertionsInBothModalities) {
  for (const Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    const TrackRun r = track(trajectories(), imager(m, kDefaultNoise));
    print(toString(m) + " noise 0.1", r);
    EXPECT_TRUE(r.finite);
    EXPECT_TRUE(r.pd);
    EXPECT_GE(r.tracked, kMinTrackedFraction * r.frames) << toString(m);
    EXPECT_LE(median(r.tracked_tip_m), kMedianTipTol_m) << toString(m);
    EXPECT_LE(median(r.tracked_heading_rad), kMedianHeadingTol_rad) << toString(m);
    EXPECT_LE(percentile(r.confident_tip_m, 0.95), kConfidentTipP95Tol_m) << toString(m);
    EXPECT_LE(percentile(r.confident_heading_rad, 0.95), kConfidentHeadingP95Tol_rad)
        << toString(m);
    for (const TipEstimate& e : r.estimates) {
      // `confident` only for image-confirmed poses within the configured deviations.
      if (e.confident) {
        EXPECT_EQ(e.status, TrackStatus::kTracked);
        EXPECT_LE(std::sqrt(e.covariance(2, 2)), 0.035 + 1e-12);
      }
    }
  }
}

TEST(TipTrackerTest, PredictsThroughDroppedFramesAndIsNotConfident) {
  const ImagerConfig ic = imager(Modality::kUltrasound, kDefaultNoise);
  const FrameRenderer renderer(workspace(), ic);
  TipTracker tracker(trackerConfigFromScene(workspace(), ic));
  const std::vector<Shot>& traj = trajectories()[7];  // the longest
  ASSERT_GE(traj.size(), 25u);
  tracker.reset(traj.front().tip);
  constexpr std::size_t kFirstDropped = 9, kLastDropped = 15;  // 1.5 steps without images
  bool confident_before = false;
  double prev_pos_var = 0.0;
  for (std::size_t k = 1; k < traj.size(); ++k) {
    const Shot& shot = traj[k];
    tracker.onDrive(shot.length_m, shot.tip.bevel, shot.flips);
    const bool drop = k >= kFirstDropped && k <= kLastDropped;
    const TipEstimate e = tracker.onFrame(drop ? cv::Mat() : renderer.render(shot.points, k).image);
    ASSERT_TRUE(allFinite(e));
    if (k == kFirstDropped - 1) {
      confident_before = e.confident;
    }
    if (drop) {
      EXPECT_EQ(e.status, TrackStatus::kBadFrame) << k;
      EXPECT_FALSE(e.confident) << k;
      EXPECT_NE(e.message.find("empty"), std::string::npos) << e.message;
      // The prediction follows the needle: within 3 sigma of its own covariance (chi-square,
      // 2 dof, 99.9 %), and its uncertainty grows.
      const Eigen::Vector2d d = e.tip.p_SceneTip - shot.tip.p_SceneTip;
      const double m2 = d.dot(e.covariance.topLeftCorner<2, 2>().ldlt().solve(d));
      EXPECT_LE(m2, 13.8) << k;
      const double pos_var = e.covariance.topLeftCorner<2, 2>().trace();
      EXPECT_GT(pos_var, prev_pos_var) << k;
      prev_pos_var = pos_var;
    } else {
      prev_pos_var = e.covariance.topLeftCorner<2, 2>().trace();
    }
    if (k == kLastDropped + 4) {
      EXPECT_EQ(e.status, TrackStatus::kTracked) << e.message;
      EXPECT_LE(tipError(e.tip.p_SceneTip, shot.tip), kMedianTipTol_m);
    }
  }
  EXPECT_TRUE(confident_before);
}

TEST(TipTrackerTest, TipOutsideTheFieldOfViewIsOutOfViewAndNotConfident) {
  // A 60 mm wide field of view in the middle of the workspace (x 20..80 mm): the needle enters
  // at x = 0, outside it, comes into view, and leaves it again on the right.
  ImagerConfig ic = imager(Modality::kFluoroscopy, 0.05, 0.2e-3);
  ic.geometry = fieldOfView(workspace(), 0.2e-3, 300, 500);
  const TipPose entry{Point2(0.0, 0.015), 0.0, Bevel::kLeft};
  constexpr int kSteps = 13;
  std::vector<Bevel> bevels;
  bevels.reserve(kSteps);
  for (int k = 0; k < kSteps; ++k) {
    bevels.push_back(k % 2 == 0 ? Bevel::kLeft : Bevel::kRight);
  }
  const std::vector<std::vector<Shot>> trajs = {syntheticInsertion(entry, bevels, {})};
  const TrackRun r = track(trajs, ic);
  print("field of view 60 mm", r);
  expectRightOrNotConfident(r, "out of view");
  int out_before = 0, tracked_inside = 0, out_after = 0;
  for (std::size_t i = 0; i < r.estimates.size(); ++i) {
    const TipEstimate& e = r.estimates[i];
    const double x = r.truths[i].p_SceneTip.x();
    if (x < 0.019) {
      EXPECT_EQ(e.status, TrackStatus::kOutOfView) << i << " " << e.message;
      EXPECT_FALSE(e.confident);
      out_before += 1;
    } else if (x > 0.081) {
      EXPECT_EQ(e.status, TrackStatus::kOutOfView) << i << " " << e.message;
      EXPECT_FALSE(e.confident);
      out_after += 1;
    } else if (x > 0.03 && x < 0.075) {
      tracked_inside += e.status == TrackStatus::kTracked ? 1 : 0;
    }
  }
  EXPECT_GE(out_before, 6);
  EXPECT_GE(out_after, 3);
  EXPECT_GE(tracked_inside, 15);
}

TEST(TipTrackerTest, BrightObstacleBoundaryIsRightOrNotConfident) {
  const ImagerConfig ic = imager(Modality::kUltrasound, kDefaultNoise);
  // Across: the needle crosses lower_wall's left edge (x = 30 mm, y 22..52 mm) at y = 40 mm and
  // runs on inside the obstacle. Alongside: in the channel, 1.5 mm above lower_wall's top edge
  // (y = 52 mm) and in its acoustic shadow, with upper_wall's edge (58 mm) above; the needle's
  // reverberation echoes fall in between.
  const std::vector<Bevel> alternate = {Bevel::kLeft, Bevel::kRight, Bevel::kLeft, Bevel::kRight,
                                        Bevel::kLeft, Bevel::kRight, Bevel::kLeft, Bevel::kRight};
  const std::vector<double> betas = {0.0,      2 * kDeg,  -3 * kDeg, 1 * kDeg,
                                     2 * kDeg, -2 * kDeg, 0.0,       1 * kDeg};
  const std::vector<std::vector<Shot>> across = {
      syntheticInsertion({Point2(0.0, 0.040), 0.0, Bevel::kLeft}, alternate, betas)};
  const std::vector<std::vector<Shot>> alongside = {
      syntheticInsertion({Point2(0.0, 0.0535), 0.0, Bevel::kLeft}, alternate, {})};
  const TrackRun a = track(across, ic);
  const TrackRun b = track(alongside, ic);
  print("boundary across", a);
  print("boundary alongside", b);
  expectRightOrNotConfident(a, "across");
  expectRightOrNotConfident(b, "alongside");
  // Not everything is given up: the needle is tracked over most of both insertions.
  EXPECT_GE(a.tracked, a.frames / 2);
  EXPECT_GE(b.tracked, b.frames / 2);
}

TEST(TipTrackerTest, HeavyNoiseIsRightOrNotConfident) {
  for (const Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    for (const double noise : {0.3, 0.6}) {
      const TrackRun r = track(trajectories(), imager(m, noise), 4);
      char name[64];
      std::snprintf(name, sizeof name, "%s noise %.1f", toString(m).c_str(), noise);
      print(name, r);
      expectRightOrNotConfident(r, name);
    }
  }
}

TEST(TipTrackerTest, UnusableFramesLeaveTheStateUnchanged) {
  const ImagerConfig ic = imager(Modality::kUltrasound, kDefaultNoise);
  const FrameRenderer renderer(workspace(), ic);
  TipTracker tracker(trackerConfigFromScene(workspace(), ic));
  const std::vector<Shot>& traj = trajectories()[3];
  ASSERT_GE(traj.size(), 9u);
  tracker.reset(traj.front().tip);
  std::size_t k = 1;
  for (; k <= 8; ++k) {
    tracker.onDrive(traj[k].length_m, traj[k].tip.bevel, traj[k].flips);
    tracker.onFrame(renderer.render(traj[k].points, k).image);
  }
  const TipEstimate before = tracker.estimate();
  ASSERT_EQ(before.status, TrackStatus::kTracked) << before.message;
  const cv::Size size = ic.geometry.size();
  const std::vector<std::pair<cv::Mat, const char*>> bad = {
      {cv::Mat(), "empty"},
      {cv::Mat(size, CV_8UC1, cv::Scalar(0)), "no contrast"},
      {cv::Mat(size, CV_16UC1, cv::Scalar(3000)), "CV_8UC1"},
      {cv::Mat(size, CV_8UC3, cv::Scalar(50, 60, 70)), "CV_8UC1"},
      {cv::Mat(cv::Size(640, 480), CV_8UC1, cv::Scalar(7)), "calibration expects"},
  };
  for (const auto& [frame, reason] : bad) {
    const TipEstimate e = tracker.onFrame(frame);
    EXPECT_EQ(e.status, TrackStatus::kBadFrame) << reason;
    EXPECT_FALSE(e.confident);
    EXPECT_NE(e.message.find(reason), std::string::npos) << e.message;
    EXPECT_EQ(e.tip.p_SceneTip, before.tip.p_SceneTip);
    EXPECT_EQ(e.tip.theta_rad, before.tip.theta_rad);
    EXPECT_EQ(e.covariance, before.covariance);
    EXPECT_EQ(e.inserted_length_m, before.inserted_length_m);
    EXPECT_TRUE(allFinite(e));
  }
  // The next good frame is tracked again.
  const TipEstimate again = tracker.onFrame(renderer.render(traj[k - 1].points, 99).image);
  EXPECT_EQ(again.status, TrackStatus::kTracked) << again.message;
}

TEST(TipTrackerTest, DetectionFarFromThePredictionIsGatedOut) {
  const ImagerConfig ic = imager(Modality::kFluoroscopy, kDefaultNoise);
  const FrameRenderer renderer(workspace(), ic);
  TipTracker tracker(trackerConfigFromScene(workspace(), ic));
  const std::vector<Shot>& traj = trajectories()[3];
  ASSERT_GE(traj.size(), 14u);
  tracker.reset(traj.front().tip);
  for (std::size_t k = 1; k <= 12; ++k) {
    tracker.onDrive(traj[k].length_m, traj[k].tip.bevel, traj[k].flips);
    tracker.onFrame(renderer.render(traj[k].points, k).image);
  }
  ASSERT_TRUE(tracker.estimate().confident) << tracker.estimate().message;
  // The next frame shows the needle 1.5 mm higher and 1 mm deeper than it is (e.g. a
  // registration error): a clean detection, but far from the prediction.
  const Shot& shot = traj[13];
  const TipEstimate predicted = tracker.onDrive(shot.length_m, shot.tip.bevel, shot.flips);
  std::vector<Point2> moved = shot.points;
  for (Point2& p : moved) {
    p += Point2(1.0e-3, 1.5e-3);
  }
  const TipEstimate e = tracker.onFrame(renderer.render(moved, 13).image);
  EXPECT_TRUE(e.detection.found) << e.detection.message;
  EXPECT_EQ(e.status, TrackStatus::kPredicted);
  EXPECT_FALSE(e.confident);
  EXPECT_NE(e.message.find("gated out"), std::string::npos) << e.message;
  EXPECT_EQ(e.tip.p_SceneTip, predicted.tip.p_SceneTip);
  EXPECT_EQ(e.covariance, predicted.covariance);
  // The true frame at the same moment is fused.
  const TipEstimate ok = tracker.onFrame(renderer.render(shot.points, 14).image);
  EXPECT_EQ(ok.status, TrackStatus::kTracked) << ok.message;
  EXPECT_LE(tipError(ok.tip.p_SceneTip, shot.tip), kMedianTipTol_m);
}

TEST(TipTrackerTest, ConsistentlyRejectedDetectionsReacquireNotConfident) {
  // The tracker is told a wrong entry (3 mm too high, confidently): every detection disagrees
  // with its prediction, but they agree with each other as the needle advances.
  const ImagerConfig ic = imager(Modality::kFluoroscopy, 0.05, 0.2e-3);
  const FrameRenderer renderer(workspace(), ic);
  TipTracker tracker(trackerConfigFromScene(workspace(), ic));
  const std::vector<Shot>& traj = trajectories()[3];
  TipPose wrong = traj.front().tip;
  wrong.p_SceneTip.y() += 3e-3;
  tracker.reset(wrong);
  int gated = 0;
  int reacquired_at = -1;
  for (std::size_t k = 1; k < traj.size(); ++k) {
    tracker.onDrive(traj[k].length_m, traj[k].tip.bevel, traj[k].flips);
    const TipEstimate e = tracker.onFrame(renderer.render(traj[k].points, k).image);
    ASSERT_TRUE(allFinite(e));
    if (e.message.find("gated out") != std::string::npos) {
      ++gated;
      EXPECT_FALSE(e.confident);
    }
    if (e.message.rfind("re-acquired", 0) == 0) {
      reacquired_at = static_cast<int>(k);
      EXPECT_EQ(e.status, TrackStatus::kTracked);
      EXPECT_FALSE(e.confident) << "never confident on the re-acquisition itself";
    }
    if (reacquired_at < 0 && e.confident) {
      ADD_FAILURE() << "confident while the filter is 3 mm off, frame " << k << ": " << e.message;
    }
  }
  EXPECT_GE(gated, TipTracker::kReacquireAfter - 1);
  ASSERT_GT(reacquired_at, 0);
  const TipEstimate& last = tracker.estimate();
  EXPECT_LE(tipError(last.tip.p_SceneTip, traj.back().tip), kMedianTipTol_m) << last.message;
  EXPECT_TRUE(last.confident) << last.message;
}

TEST(TipTrackerTest, DriveInputsEntryAndRetraction) {
  const ImagerConfig ic = imager(Modality::kFluoroscopy, kDefaultNoise);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  TipTracker tracker(tc);
  EXPECT_EQ(tracker.estimate().status, TrackStatus::kUninitialized);
  EXPECT_FALSE(tracker.estimate().confident);
  const TipPose entry{Point2(0.0, 0.05), 0.1, Bevel::kLeft};
  tracker.reset(entry);
  EXPECT_EQ(tracker.estimate().status, TrackStatus::kEntry);
  EXPECT_TRUE(tracker.estimate().confident);
  // Nothing inserted: a frame leaves the guide's pose.
  const FrameRenderer renderer(workspace(), ic);
  const TipEstimate at_entry = tracker.onFrame(renderer.render({}, 0).image);
  EXPECT_EQ(at_entry.status, TrackStatus::kEntry);
  EXPECT_EQ(at_entry.tip.p_SceneTip, entry.p_SceneTip);
  // Bad lengths are ignored and said so.
  for (const double bad : {std::nan(""), -1e-3, std::numeric_limits<double>::infinity(), 1e300}) {
    const TipEstimate e = tracker.onDrive(bad, Bevel::kLeft, 0);
    EXPECT_NE(e.message.find("ignored"), std::string::npos) << e.message;
    EXPECT_EQ(e.tip.p_SceneTip, entry.p_SceneTip);
    EXPECT_TRUE(allFinite(e));
  }
  // One step: along the left arc, heading + delta / r, heading variance + sigma_i^2.
  const double delta = tc.step_length_m;
  const TipEstimate one = tracker.onDrive(delta, Bevel::kLeft, 0);
  const TipPose expected =
      steering::advanceTip(entry, steering::Control::kInsert, 0.0, delta, tc.radius_of_curvature_m);
  EXPECT_NEAR((one.tip.p_SceneTip - expected.p_SceneTip).norm(), 0.0, 1e-12);
  EXPECT_NEAR(one.tip.theta_rad, expected.theta_rad, 1e-12);
  EXPECT_EQ(one.status, TrackStatus::kPredicted);
  EXPECT_FALSE(one.confident);
  EXPECT_NEAR(one.covariance(2, 2), 0.005 * 0.005 + tc.sigma_insert_rad * tc.sigma_insert_rad,
              1e-9);
  // A flip, then half a step: the flip's sigma enters whole at the start of the step.
  const TipEstimate flipped_in_place = tracker.onDrive(delta, Bevel::kRight, 1);
  EXPECT_EQ(flipped_in_place.tip.p_SceneTip, one.tip.p_SceneTip);
  const TipEstimate half = tracker.onDrive(1.5 * delta, Bevel::kRight, 1);
  EXPECT_NEAR(half.covariance(2, 2) - one.covariance(2, 2), tc.sigma_flip_rad * tc.sigma_flip_rad,
              1e-9);
  EXPECT_LT(half.tip.theta_rad, one.tip.theta_rad);  // bevel right: clockwise
  // Back to zero: the guide's pose again, known.
  const TipEstimate back = tracker.onDrive(0.0, Bevel::kRight, 1);
  EXPECT_EQ(back.status, TrackStatus::kEntry);
  EXPECT_EQ(back.tip.p_SceneTip, entry.p_SceneTip);
  EXPECT_TRUE(back.confident);
  // Retracting part way goes back along the arc.
  tracker.onDrive(delta, Bevel::kLeft, 1);
  const TipEstimate partial = tracker.onDrive(0.5 * delta, Bevel::kLeft, 1);
  const TipPose half_expected = steering::advanceTip(entry, steering::Control::kInsert, 0.0,
                                                     0.5 * delta, tc.radius_of_curvature_m);
  EXPECT_NEAR((partial.tip.p_SceneTip - half_expected.p_SceneTip).norm(), 0.0, 1e-9);
  EXPECT_TRUE(allFinite(partial));
}

TEST(TipTrackerTest, AcquiresWithoutAnEntryButNotConfidently) {
  const ImagerConfig ic = imager(Modality::kFluoroscopy, 0.02, 0.2e-3);
  const FrameRenderer renderer(workspace(), ic);
  TipTracker tracker(trackerConfigFromScene(workspace(), ic));
  const std::vector<Shot>& traj = trajectories()[7];
  ASSERT_GE(traj.size(), 17u);
  const TipEstimate blank = tracker.onFrame(renderer.render({}, 0).image);
  EXPECT_EQ(blank.status, TrackStatus::kUninitialized);
  EXPECT_FALSE(blank.confident);
  const Shot& shot = traj[12];
  tracker.onDrive(shot.length_m, shot.tip.bevel, shot.flips);
  const TipEstimate first = tracker.onFrame(renderer.render(shot.points, 1).image);
  ASSERT_EQ(first.status, TrackStatus::kTracked) << first.message;
  EXPECT_FALSE(first.confident);
  EXPECT_LE(tipError(first.tip.p_SceneTip, shot.tip), kMedianTipTol_m);
  for (std::size_t k = 13; k < 17; ++k) {
    tracker.onDrive(traj[k].length_m, traj[k].tip.bevel, traj[k].flips);
    tracker.onFrame(renderer.render(traj[k].points, k).image);
  }
  EXPECT_LE(tipError(tracker.estimate().tip.p_SceneTip, traj[16].tip), kMedianTipTol_m);
}

/// Timings on one core (printed, not asserted): 640 x 480 frames at 0.2 mm, and the scene's grid.
}  // namespace
}  // namespace needle_guidance::imaging

TEST(MotionModelTest, AutoTakesTheDriveWhenThereAndTheAxisOtherwise) {
  namespace im = needle_guidance::imaging;
  using im::MotionModel;
  EXPECT_EQ(im::chooseMotionModel(MotionModel::kAuto, true), MotionModel::kDrive);
  EXPECT_EQ(im::chooseMotionModel(MotionModel::kAuto, false), MotionModel::kAxis);
  // A stated model is kept whatever is available.
  EXPECT_EQ(im::chooseMotionModel(MotionModel::kAxis, true), MotionModel::kAxis);
  EXPECT_EQ(im::chooseMotionModel(MotionModel::kDrive, false), MotionModel::kDrive);
  for (const auto m : {MotionModel::kAuto, MotionModel::kDrive, MotionModel::kAxis}) {
    EXPECT_EQ(im::motionModelFromString(im::toString(m)), m);
  }
  EXPECT_FALSE(im::motionModelFromString("robot").has_value());
}

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
