// TipTracker, detectTip and houghBaselineTip on frames of the simulated imager (FrameRenderer)
// of steering_workspace: accuracy in both modalities, the filter through dropped frames, and the
// hard cases — tip out of view, a bright obstacle boundary, heavy noise, unusable frames, a
// detection far from the prediction — which must give the right tip or say "not confident".
#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <cstdlib>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "needle_guidance/imaging/frame_renderer.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/robot/steerable_needle.h"
#include "needle_guidance/scene/scene.h"
#include "needle_guidance/steering/steering_model.h"

namespace needle_guidance::imaging {
namespace {

using steering::Bevel;
using steering::TipPose;

constexpr double kPi = 3.14159265358979323846;
constexpr double kDeg = kPi / 180.0;
constexpr double kMm = 1e-3;
constexpr double kPathSpacing_m = 0.1e-3;  // needle shape handed to the renderer
constexpr int kSubstepsPerStep = 4;        // frames per insertion step delta

const scene::Scene& workspace() {
  static const scene::Scene s = scene::loadSceneSpec("steering_workspace");
  return s;
}

ImagerConfig imager(Modality modality, double noise_std, double blur_m, std::uint64_t seed = 1) {
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
  bool step_end = false;  ///< the end of a whole insertion step
};

/// An insertion of `steps` steps of delta from (x = 0, height) with a seeded deflection stream,
/// flips chosen by a seeded coin (probability flip_p), kSubstepsPerStep shots per step; stops
/// at a contact. The first shot is the entry (length 0).
std::vector<Shot> insertion(double height_m, double angle_rad, Bevel bevel, int steps,
                            std::uint64_t seed, double flip_p = 0.3) {
  const scene::Scene& sc = workspace();
  const steering::SteeringProblem problem = steering::problemFromScene(sc);
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
  robot::SteerableNeedle needle(problem, cfg, entry);
  const double delta = 2.0 * kPi * sc.needle.radius_of_curvature_m / sc.steering->orientations;
  std::mt19937 coin(static_cast<std::uint32_t>(seed * 7919u + 13u));
  std::vector<Shot> out;
  std::uint32_t flips = 0;
  out.push_back({needle.pathPoints(kPathSpacing_m), needle.tip(), 0.0, 0, true});
  for (int k = 0; k < steps; ++k) {
    if (k > 0 && (coin() % 1000u) < static_cast<std::uint32_t>(flip_p * 1000.0)) {
      needle.flip();
      ++flips;
    }
    if (!needle.beginInsertion()) {
      break;
    }
    const double start = needle.insertedLength_m();
    bool contact = false;
    for (int j = 1; j <= kSubstepsPerStep; ++j) {
      const robot::MotionStatus st = needle.advanceTo(start + delta * j / kSubstepsPerStep);
      if (st.outcome() != robot::MotionOutcome::kMoved) {
        contact = true;
        break;
      }
      out.push_back({needle.pathPoints(kPathSpacing_m), needle.tip(), needle.insertedLength_m(),
                     flips, j == kSubstepsPerStep});
    }
    if (contact) {
      break;
    }
  }
  return out;
}

double tipError(const Point2& p, const TipPose& truth) {
  return (p - truth.p_SceneTip).norm();
}
double headingError(double theta, const TipPose& truth) {
  return std::abs(std::remainder(theta - truth.theta_rad, 2.0 * kPi));
}

double median(std::vector<double> v) {
  if (v.empty()) {
    return std::nan("");
  }
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
  return v[v.size() / 2];
}
double percentile(std::vector<double> v, double q) {
  if (v.empty()) {
    return std::nan("");
  }
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

bool allFinite(const TipEstimate& e) {
  return e.tip.p_SceneTip.allFinite() && std::isfinite(e.tip.theta_rad) &&
         e.covariance.allFinite() && std::isfinite(e.inserted_length_m) &&
         e.detection.p_SceneTip.allFinite() && std::isfinite(e.detection.theta_rad) &&
         e.detection.covariance.allFinite() && std::isfinite(e.detection.residual_rms_m);
}
bool allFinite(const Detection& d) {
  return d.p_SceneTip.allFinite() && std::isfinite(d.theta_rad) && d.covariance.allFinite() &&
         std::isfinite(d.residual_rms_m);
}

/// A set of insertions over the workspace (fixed seeds): heights, entry angles and bevels that
/// keep most of them away from the obstacles for several steps.
std::vector<std::vector<Shot>> trajectories(int count, int steps) {
  std::vector<std::vector<Shot>> out;
  const double heights[] = {0.012, 0.02, 0.03, 0.05, 0.065, 0.08, 0.09, 0.015, 0.07, 0.055};
  for (int i = 0; i < count; ++i) {
    const double h = heights[i % 10];
    const double angle = ((i % 3) - 1) * 10.0 * kDeg;
    const Bevel b = (i % 2) == 0 ? Bevel::kLeft : Bevel::kRight;
    out.push_back(insertion(h, angle, b, steps, 100 + static_cast<std::uint64_t>(i)));
  }
  return out;
}

struct Stats {
  std::vector<double> tip_m, heading_rad, ms, along_m, lateral_m;
  std::vector<double> heading_by_phase[kSubstepsPerStep + 1];
  std::vector<std::string> failures;
  std::vector<std::pair<double, std::string>> worst;
  int attempts = 0;
  int found = 0;
};

/// Single-frame detections with a prior: the truth perturbed by the given deviations (what a
/// filter would predict) and that covariance.
Stats detectOnShots(const std::vector<std::vector<Shot>>& trajs, const ImagerConfig& ic,
                    bool baseline, double prior_pos_std_m, double prior_heading_std_rad,
                    std::uint64_t seed) {
  const FrameRenderer renderer(workspace(), ic);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  std::mt19937 rng(static_cast<std::uint32_t>(seed));
  std::normal_distribution<double> n01(0.0, 1.0);
  Stats st;
  std::uint64_t index = 0;
  int ti = -1;
  for (const auto& traj : trajs) {
    ++ti;
    int si = -1;
    for (const auto& shot : traj) {
      ++si;
      if (shot.length_m < 3.0 * kMm) {
        continue;
      }
      const cv::Point2d px = ic.geometry.toPixel(shot.tip.p_SceneTip);
      if (px.x < 0 || px.y < 0 || px.x > ic.geometry.cols - 1 || px.y > ic.geometry.rows - 1) {
        continue;
      }
      const Frame f = renderer.render(shot.points, index++);
      if (const char* dump = std::getenv("TIP_DUMP")) {
        int a = -1, b = -1;
        if (std::sscanf(dump, "%d,%d", &a, &b) == 2 && a == ti && b == si && !baseline) {
          const cv::Point2d px = ic.geometry.toPixel(shot.tip.p_SceneTip);
          cv::Rect r(static_cast<int>(px.x) - 60, static_cast<int>(px.y) - 60, 120, 120);
          r &= cv::Rect(0, 0, f.image.cols, f.image.rows);
          cv::Mat crop;
          cv::resize(f.image(r), crop, cv::Size(), 4, 4, cv::INTER_NEAREST);
          cv::cvtColor(crop, crop, cv::COLOR_GRAY2BGR);
          cv::circle(crop, cv::Point(static_cast<int>((px.x - r.x) * 4 + 2), static_cast<int>((px.y - r.y) * 4 + 2)), 4, cv::Scalar(0, 255, 0), 1);
          cv::imwrite("/tmp/tip_dump.png", crop);
          setenv("TIP_DEBUG", "1", 1);
        } else {
          unsetenv("TIP_DEBUG");
        }
      }
      SearchPrior prior;
      prior.tip = shot.tip;
      prior.tip.p_SceneTip += prior_pos_std_m * Point2(n01(rng), n01(rng));
      prior.tip.theta_rad += prior_heading_std_rad * n01(rng);
      prior.covariance = Eigen::Vector3d(prior_pos_std_m * prior_pos_std_m,
                                         prior_pos_std_m * prior_pos_std_m,
                                         prior_heading_std_rad * prior_heading_std_rad)
                             .asDiagonal();
      const auto t0 = std::chrono::steady_clock::now();
      std::optional<SearchPrior> maybe_prior;
      if (prior_pos_std_m > 0.0) {
        maybe_prior = prior;
      }
      const Detection d = baseline ? houghBaselineTip(f.image, tc, maybe_prior)
                                   : detectTip(f.image, tc, maybe_prior);
      const auto t1 = std::chrono::steady_clock::now();
      EXPECT_TRUE(allFinite(d)) << d.message;
      st.ms.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
      ++st.attempts;
      if (d.found) {
        ++st.found;
        st.tip_m.push_back(tipError(d.p_SceneTip, shot.tip));
        st.heading_rad.push_back(headingError(d.theta_rad, shot.tip));
        st.heading_by_phase[(si - 1) % kSubstepsPerStep + 1].push_back(headingError(d.theta_rad, shot.tip));
        const Point2 t(std::cos(shot.tip.theta_rad), std::sin(shot.tip.theta_rad));
        const Point2 e = d.p_SceneTip - shot.tip.p_SceneTip;
        st.along_m.push_back(e.dot(t));
        st.lateral_m.push_back(t.x() * e.y() - t.y() * e.x());
        char buf[400];
        std::snprintf(buf, sizeof buf, "traj %d shot %d len %.1f mm tip (%.2f, %.2f) mm th %.1f: along %.2f lat %.2f dth %.1f | %s",
                      ti, si, shot.length_m * 1e3, shot.tip.p_SceneTip.x() * 1e3,
                      shot.tip.p_SceneTip.y() * 1e3, shot.tip.theta_rad / kDeg, e.dot(t) * 1e3,
                      (t.x() * e.y() - t.y() * e.x()) * 1e3,
                      std::remainder(d.theta_rad - shot.tip.theta_rad, 2 * kPi) / kDeg, d.message.c_str());
        st.worst.emplace_back(tipError(d.p_SceneTip, shot.tip) + 1e-4 * headingError(d.theta_rad, shot.tip) / kDeg, buf);
      } else {
        st.failures.push_back(d.message);
      }
    }
  }
  return st;
}

void print(const char* what, const Stats& s) {
  std::printf("  %-34s found %3d/%3d  tip median %.3f mm p90 %.3f mm  heading median %.2f deg "
              "p90 %.2f deg  %.2f ms/frame\n",
              what, s.found, s.attempts, median(s.tip_m) * 1e3, percentile(s.tip_m, 0.9) * 1e3,
              median(s.heading_rad) / kDeg, percentile(s.heading_rad, 0.9) / kDeg, median(s.ms));
  std::printf("     along median %.3f mm p10 %.3f p90 %.3f  lateral median %.3f mm p10 %.3f p90 %.3f\n",
              median(s.along_m) * 1e3, percentile(s.along_m, 0.1) * 1e3,
              percentile(s.along_m, 0.9) * 1e3, median(s.lateral_m) * 1e3,
              percentile(s.lateral_m, 0.1) * 1e3, percentile(s.lateral_m, 0.9) * 1e3);
  for (int k = 1; k <= kSubstepsPerStep; ++k) {
    std::printf("     heading after %d/%d step: median %.2f p90 %.2f deg\n", k, kSubstepsPerStep,
                median(s.heading_by_phase[k]) / kDeg, percentile(s.heading_by_phase[k], 0.9) / kDeg);
  }
  auto w = s.worst;
  std::sort(w.begin(), w.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
  for (std::size_t i = 0; i < w.size() && i < 6; ++i) {
    std::printf("     worst: %s\n", w[i].second.c_str());
  }
  for (std::size_t i = 0; i < s.failures.size() && i < 4; ++i) {
    std::printf("     fail: %s\n", s.failures[i].c_str());
  }
}

/// What a tracker run gives, per frame.
struct TrackRun {
  std::vector<double> tip_m, heading_rad;            // kTracked frames
  std::vector<double> confident_tip_m, confident_heading_rad;
  std::vector<double> all_tip_m;                      // every frame after the entry
  int frames = 0, tracked = 0, confident = 0, predicted = 0, out_of_view = 0, reacquired = 0;
  bool finite = true;
  std::vector<double> ms;
  std::vector<std::string> notes;
};

/// Tracks every trajectory with a fresh TipTracker: reset at the entry, then per shot onDrive
/// (the robot's length, bevel, flips) and onFrame (the rendered frame).
TrackRun track(const std::vector<std::vector<Shot>>& trajs, const ImagerConfig& ic) {
  const FrameRenderer renderer(workspace(), ic);
  const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
  TrackRun run;
  std::uint64_t index = 0;
  int ti = -1;
  for (const auto& traj : trajs) {
    ++ti;
    TipTracker tracker(tc);
    tracker.reset(traj.front().tip);
    for (std::size_t k = 1; k < traj.size(); ++k) {
      const Shot& shot = traj[k];
      const TipEstimate drive = tracker.onDrive(shot.length_m, shot.tip.bevel, shot.flips);
      run.finite = run.finite && allFinite(drive);
      const Frame f = renderer.render(shot.points, index++);
      if (const char* dump = std::getenv("TIP_TDUMP")) {
        int a = -1, b = -1;
        if (std::sscanf(dump, "%d,%d", &a, &b) == 2 && a == ti && b == static_cast<int>(k)) {
          setenv("TIP_DEBUG", "1", 1);
          std::fprintf(stderr, "prior tip (%.3f, %.3f) mm th %.2f sd %.2f; truth (%.3f, %.3f) th %.2f\n",
                       drive.tip.p_SceneTip.x() * 1e3, drive.tip.p_SceneTip.y() * 1e3, drive.tip.theta_rad / kDeg,
                       std::sqrt(drive.covariance(2, 2)) / kDeg, shot.tip.p_SceneTip.x() * 1e3,
                       shot.tip.p_SceneTip.y() * 1e3, shot.tip.theta_rad / kDeg);
        } else {
          unsetenv("TIP_DEBUG");
        }
      }
      const auto t0 = std::chrono::steady_clock::now();
      const TipEstimate e = tracker.onFrame(f.image);
      if (std::getenv("TIP_DEBUG") != nullptr) {
        const cv::Point2d px = ic.geometry.toPixel(shot.tip.p_SceneTip);
        cv::Rect r(static_cast<int>(px.x) - 40, static_cast<int>(px.y) - 30, 60, 60);
        r &= cv::Rect(0, 0, f.image.cols, f.image.rows);
        constexpr int kZ = 8;
        cv::Mat crop;
        cv::resize(f.image(r), crop, cv::Size(), kZ, kZ, cv::INTER_NEAREST);
        cv::cvtColor(crop, crop, cv::COLOR_GRAY2BGR);
        const auto draw = [&](const Point2& p, double th, cv::Scalar col) {
          const cv::Point2d q = ic.geometry.toPixel(p);
          const cv::Point a(static_cast<int>((q.x - r.x + 0.5) * kZ), static_cast<int>((q.y - r.y + 0.5) * kZ));
          const cv::Point b(a.x + static_cast<int>(200 * std::cos(th)), a.y - static_cast<int>(200 * std::sin(th)));
          cv::circle(crop, a, 5, col, 1);
          cv::line(crop, a, b, col, 1);
        };
        draw(shot.tip.p_SceneTip, shot.tip.theta_rad, cv::Scalar(0, 255, 0));
        draw(e.detection.p_SceneTip, e.detection.theta_rad, cv::Scalar(0, 0, 255));
        for (const auto& p : shot.points) {
          const cv::Point2d q = ic.geometry.toPixel(p);
          const cv::Point a(static_cast<int>((q.x - r.x + 0.5) * kZ), static_cast<int>((q.y - r.y + 0.5) * kZ));
          if (a.x >= 0 && a.y >= 0 && a.x < crop.cols && a.y < crop.rows) crop.at<cv::Vec3b>(a) = cv::Vec3b(255, 0, 0);
        }
        cv::imwrite("/tmp/tip_tdump.png", crop);
        if (FILE* fp = std::fopen("/tmp/path.txt", "w")) {
          for (const auto& p : shot.points) std::fprintf(fp, "%.9f %.9f\n", p.x(), p.y());
          std::fclose(fp);
        }
      }
      run.ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
      run.finite = run.finite && allFinite(e);
      ++run.frames;
      const double err = tipError(e.tip.p_SceneTip, shot.tip);
      const double herr = headingError(e.tip.theta_rad, shot.tip);
      run.all_tip_m.push_back(err);
      if (e.status == TrackStatus::kTracked) {
        ++run.tracked;
        run.tip_m.push_back(err);
        run.heading_rad.push_back(herr);
        if (e.message.rfind("re-acquired", 0) == 0) {
          ++run.reacquired;
        }
      } else if (e.status == TrackStatus::kPredicted) {
        ++run.predicted;
      } else if (e.status == TrackStatus::kOutOfView) {
        ++run.out_of_view;
      }
      if (e.confident) {
        ++run.confident;
        run.confident_tip_m.push_back(err);
        run.confident_heading_rad.push_back(herr);
        if (err > 1.0 * kMm || herr > 5.0 * kDeg) {
          char buf[400];
          std::snprintf(buf, sizeof buf, "confident but off: traj %d shot %zu err %.2f mm %.1f deg (sd %.1f deg; detection %.1f deg sd %.1f; drive sd %.1f): %s", ti, k,
                        err * 1e3, herr / kDeg, std::sqrt(e.covariance(2, 2)) / kDeg,
                        std::remainder(e.detection.theta_rad - shot.tip.theta_rad, 2 * kPi) / kDeg,
                        std::sqrt(e.detection.covariance(2, 2)) / kDeg, std::sqrt(drive.covariance(2, 2)) / kDeg, e.message.c_str());
          run.notes.push_back(buf);
        }
      }
    }
  }
  return run;
}

void print(const char* what, const TrackRun& r) {
  std::printf("  %-12s frames %d tracked %d confident %d predicted %d out_of_view %d reacquired %d | "
              "tracked tip median %.3f p90 %.3f mm heading median %.2f p90 %.2f deg | confident tip "
              "p95 %.3f mm heading p95 %.2f deg | all-frames tip median %.3f mm | %.2f ms/frame\n",
              what, r.frames, r.tracked, r.confident, r.predicted, r.out_of_view, r.reacquired,
              median(r.tip_m) * 1e3, percentile(r.tip_m, 0.9) * 1e3, median(r.heading_rad) / kDeg,
              percentile(r.heading_rad, 0.9) / kDeg, percentile(r.confident_tip_m, 0.95) * 1e3,
              percentile(r.confident_heading_rad, 0.95) / kDeg, median(r.all_tip_m) * 1e3,
              median(r.ms));
  for (std::size_t i = 0; i < r.notes.size() && i < 5; ++i) {
    std::printf("     %s\n", r.notes[i].c_str());
  }
}

TEST(TipTracker, DiagnosticsTable) {
  const auto trajs = trajectories(10, 9);
  for (Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    for (double noise : {0.0, 0.05, 0.1, 0.2, 0.3}) {
      if (const char* only = std::getenv("TIP_ONLY")) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "%s,%.2f", toString(m).c_str(), noise);
        if (std::string(only) != buf) {
          continue;
        }
      }
      const TrackRun r = track(trajs, imager(m, noise, 0.3 * kMm));
      char name[64];
      std::snprintf(name, sizeof name, "%s %.2f", toString(m).c_str(), noise);
      print(name, r);
    }
  }
}

TEST(TipDetector, StraightProbe) {
  for (Modality m : {Modality::kFluoroscopy, Modality::kUltrasound}) {
    const ImagerConfig ic = imager(m, 0.0, 0.3 * kMm);
    const FrameRenderer renderer(workspace(), ic);
    const TrackerConfig tc = trackerConfigFromScene(workspace(), ic);
    for (double x_tip : {0.0301, 0.0303, 0.0305, 0.0307}) {
      std::vector<Point2> pts;
      for (double x = 0.0; x <= x_tip + 1e-9; x += 0.1e-3) pts.emplace_back(x, 0.0501);
      pts.back() = Point2(x_tip, 0.0501);
      TipPose truth{Point2(x_tip, 0.0501), 0.0, Bevel::kLeft};
      SearchPrior prior{truth, Eigen::Matrix3d::Identity() * 1e-8};
      const Frame f = renderer.render(pts, 1);
      const Detection d = detectTip(f.image, tc, prior);
      std::printf("%s x_tip %.4f found %d along %.3f mm lateral %.3f heading %.2f deg: %s\n",
                  toString(m).c_str(), x_tip, d.found, (d.p_SceneTip.x() - x_tip) * 1e3,
                  (d.p_SceneTip.y() - 0.0501) * 1e3, d.theta_rad / kDeg, d.message.c_str());
    }
  }
}

TEST(TipDetector, DiagnosticsTable) {
  const auto trajs = trajectories(8, 7);
  for (Modality m : {Modality::kUltrasound, Modality::kFluoroscopy}) {
    for (double noise : {0.0, 0.05, 0.1, 0.2, 0.3}) {
      if (const char* only = std::getenv("TIP_ONLY")) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "%s,%.2f", toString(m).c_str(), noise);
        if (std::string(only) != buf) {
          continue;
        }
      }
      const ImagerConfig ic = imager(m, noise, 0.3 * kMm);
      const Stats d = detectOnShots(trajs, ic, false, 0.5 * kMm, 3.0 * kDeg, 5);
      const Stats h = detectOnShots(trajs, ic, true, 0.5 * kMm, 3.0 * kDeg, 5);
      std::printf("%s noise %.2f\n", toString(m).c_str(), noise);
      print("detectTip", d);
      if (std::getenv("TIP_NOPRIOR") != nullptr) {
        print("detectTip without prior", detectOnShots(trajs, ic, false, 0.0, 0.0, 5));
        print("hough without prior", detectOnShots(trajs, ic, true, 0.0, 0.0, 5));
      }
      print("houghBaselineTip", h);
    }
  }
}

}  // namespace
}  // namespace needle_guidance::imaging

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
