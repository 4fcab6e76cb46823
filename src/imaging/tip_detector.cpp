// Single-frame needle-tip detector (tip_tracker.h, detectTip). Steps:
//  1. ridge filter (Gaussian + Hessian at the needle's scale, polarity by modality) in the
//     search window, candidates = ridge maxima across the line above an adaptive threshold;
//  2. RANSAC (fixed seed) of a circle of the needle's known radius from point pairs, the sense
//     from the prior's bevel (both without a prior), least-squares refit on the inliers; in
//     ultrasound a dimmer copy deeper than a brighter one is a reverberation echo;
//  3. the needle's centre line traced along the arc (sub-pixel lateral peaks, following kinks),
//     with its cross-line contrast (brighter than both sides: not an edge; not a line crossing
//     the arc) against the same statistic on parallel arcs (the background);
//  4. the tip: the change point of the contrast (bridges the gaps of a partly visible needle),
//     refined to the steepest descent of the end, minus the rounded end's radius;
//  5. kink-aware refit of the last few millimetres (a step's deflection or a flip kinks the
//     needle; the robot's lengths since them are hints), heading = tangent at the tip;
//  6. covariance from the fit residuals, the kink models' spread, the end's slope and floors.
//
// All geometry below is in "q" coordinates: pixel units with q = (col, -row), i.e. axes aligned
// with frame scene (+x right, +y up) so angles and the sense of rotation (bevel left =
// counter-clockwise) are the scene's. q -> scene: x = ox + (q.x + 0.5) ps, y = oy + (q.y - 0.5) ps.
#include <Eigen/Dense>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "detection_util.h"
#include "needle_guidance/imaging/tip_tracker.h"
#include "needle_guidance/math.h"
#include "ridge_filter.h"

namespace needle_guidance::imaging {
namespace {

using detail::fail;
using detail::fmt;
using detail::wrapAngle;

using Vec = Eigen::Vector2d;
constexpr double kDeg = kPi / 180.0;

// ---- frame validation -------------------------------------------------------------------
/// A frame whose grey levels span fewer than this has no usable contrast.
constexpr double kMinFrameContrast_grey = 4.0;

// ---- ridge filter -----------------------------------------------------------------------
/// Smoothing before the Hessian: half the needle's diameter, at least this [px].
constexpr double kMinSmoothing_px = 1.0;
constexpr double kSmoothingPerDiameter = 0.5;
/// Blob penalty of the ridge measure: R = -lambda_1 - kBlobPenalty |lambda_2| (bright ridge).
constexpr double kBlobPenalty = 0.5;
/// Candidate threshold: median + this many robust standard deviations of R in the window.
constexpr double kCandidateThresholdSigmas = 4.0;
/// ... and at least this fraction of the window's strong ridges (its kStrongRidgeQuantile), so
/// that a noise-free frame does not turn every faint gradient into a candidate.
constexpr double kRelativeCandidateThreshold = 0.2;
constexpr double kStrongRidgeQuantile = 0.995;
/// At most this many candidate points go into RANSAC (the strongest).
constexpr std::size_t kMaxCandidates = 1200;

// ---- RANSAC -----------------------------------------------------------------------------
constexpr int kRansacIterations = 400;
constexpr std::uint32_t kRansacSeed = 20240601u;
/// A sample pair must be at least this far apart (shorter chords give unstable centres) [m].
constexpr double kMinPairDistance_m = 1.5e-3;
/// Inlier band around the arc [px] and the largest angle between the ridge and the arc [rad].
constexpr double kInlierBand_px = 1.5;
constexpr double kMaxRidgeAngle_rad = 25.0 * kDeg;
/// Candidate weights are clipped at this quantile of the candidates' ridge strengths, so a few
/// very bright structures (tissue boundaries) do not outvote a long needle.
constexpr double kWeightClipQuantile = 0.9;
/// A fit needs at least this many inliers spanning at least kMinArcSpan_m.
constexpr int kMinInliers = 8;
constexpr double kMinArcSpan_m = 1.5e-3;
/// Ultrasound reverberation echoes: copies of the fitted arc moved towards the probe by
/// kEchoMinShift_m..kEchoMaxShift_m are tried; one scoring at least kEchoScoreRatio of the fit
/// is taken as the real needle (at most kMaxEchoMoves times).
constexpr double kEchoMinShift_m = 0.8e-3;
constexpr double kEchoMaxShift_m = 2.6e-3;
constexpr double kEchoScoreRatio = 0.6;
constexpr int kMaxEchoMoves = 3;
constexpr double kEchoShiftStep_px = 0.5;
/// Slack of the prior consistency checks beyond 3 sigma: lateral [m] and heading [rad].
constexpr double kPriorLateralSlack_m = 1e-3;
constexpr double kPriorHeadingSlack_rad = 30.0 * kDeg;

// ---- centre-line tracing ----------------------------------------------------------------
constexpr double kTraceStep_px = 0.5;
/// Lateral search around the predicted centre-line offset [px] and its sampling step [px].
constexpr double kLateralSearch_px = 2.5;
/// When the traced centre line is lost, the search widens to this [px] for up to
/// kRecoveryLength_px after the last reliable sample (a kink of up to ~25 degrees).
constexpr double kLateralSearchWide_px = 5.0;
constexpr double kRecoveryLength_px = 5.0;
constexpr double kLateralStep_px = 0.5;
/// The side samples of the cross-line contrast lie this far beyond the needle's radius [px].
constexpr double kSideDistanceExtra_px = 1.5;
/// The lateral offset is extrapolated linearly from the good samples of the last this long [px].
constexpr double kOffsetHistory_px = 6.0;
/// A trace sample is not the needle if the structure there is line-like (anisotropy above
/// kCrossingLineLikeness) and runs more than kMaxCrossingAngle_rad off the traced line.
constexpr double kCrossingLineLikeness = 0.5;
constexpr double kMaxCrossingAngle_rad = 30.0 * kDeg;
/// Largest slope of the tracked offset (the centre line's angle to the arc, tan) [px/px].
constexpr double kMaxOffsetSlope = 0.6;
/// A sample is "visible needle" (the change-point detector's threshold) when its contrast is
/// above this quantile of the background's and above the background's median by
/// kVisibleFraction of the shaft's contrast; samples above kReliableFraction of it steer the
/// tracing of the centre line.
constexpr double kBackgroundQuantile = 0.9;
constexpr double kVisibleFraction = 0.12;
constexpr double kReliableFraction = 0.4;
/// The shaft must stand out from the background's level by this factor of it.
constexpr double kMinContrastOverBackground = 0.5;
/// Background statistic: lateral offsets of the parallel arcs [px] and their sampling step [px].
constexpr std::array<double, 4> kBackgroundOffsets_px = {-9.0, 9.0, -15.0, 15.0};
constexpr double kBackgroundStep_px = 2.0;
/// The walk goes this far beyond the inliers (with a prior: to 3 sigma + margin past the
/// predicted tip, at least kMaxGap_m beyond the inliers) [m].
constexpr double kMaxGap_m = 2.5e-3;
constexpr double kNoPriorLookahead_m = 20e-3;
/// At least this much visible needle within kPlateauSearch_m before the tip [m].
constexpr double kMinTipRun_m = 0.8e-3;
/// The plateau level before the end is the largest running median (window kPlateauWindow_px)
/// over the last kPlateauSearch_m of the visible run.
constexpr double kPlateauWindow_px = 3.0;
constexpr double kPlateauSearch_m = 2.5e-3;
/// The end's edge is the steepest descent of the contrast within this distance of its
/// half-maximum [px].
constexpr double kEdgeSearch_px = 3.0;
/// The needle's end is rounded (a half disc of the needle's radius): its tip point is this many
/// radii behind the half-maximum of the end's contrast.
constexpr double kTipRoundingRadii = 1.4;
/// The last visible sample must be this far from the edge of the filtered region [px] (else the
/// needle may continue beyond it).
constexpr double kEdgeClearance_px = 6.0;
/// The tip is where the contrast falls below this fraction of the reference level.
constexpr double kTipLevelFraction = 0.5;
/// Sampling stays this far inside the filtered region [px].
constexpr double kTraceBorder_px = 3.0;

// ---- local refit near the tip -----------------------------------------------------------
/// Centre-line points up to this far behind the tip are used [m] (less than one step delta,
/// so at most one kink at a step's start lies inside) ...
constexpr double kLocalFitLength_m = 7.0e-3;
/// ... but not the last this long, where the contrast fades [m].
constexpr double kLocalFitTipExclusion_m = 0.6e-3;
/// Kink search: the tip arc is at least this long, the arc before it too [m].
constexpr double kMinTipArc_m = 1.5e-3;
constexpr double kMinArcBeforeKink_m = 1.5e-3;
constexpr double kKinkStep_m = 0.25e-3;
/// Centre-line samples this close to a kink are not fitted (the blur rounds the corner) [m].
constexpr double kKinkBlurExclusion_m = 0.5e-3;
/// Prior probability of a kink inside the fitted span (it is almost one step long, and every
/// step starts with a deflection).
constexpr double kKinkPrior = 0.5;
/// The robot's lengths since the last flip and since the step's start place those kinks to
/// within this [m]; a step's start then gets this prior probability.
constexpr double kKinkHintTolerance_m = 0.75e-3;
constexpr double kStepHintPrior = 0.7;
/// How many consecutive trace samples count as one independent residual (the image is
/// smoothed over a few pixels, samples are 0.5 px apart).
constexpr double kResidualCorrelationSamples = 10.0;
constexpr int kGaussNewtonIterations = 8;

// ---- covariance -------------------------------------------------------------------------
/// Model-error floors added to every detection's covariance: lateral and along position [px]
/// and heading [rad] (pixelisation, kinks, the half-maximum's bias).
constexpr double kPositionFloor_px = 0.3;
constexpr double kHeadingFloor_rad = 0.6 * kDeg;
constexpr double kMinAlongStd_px = 0.35;
constexpr double kMaxAlongStd_px = 15.0;
/// Floor of the centre line's residual standard deviation [px]: the sub-pixel centre line is not
/// better than this whatever the noise (pixelisation, the blur rounding kinks); it also sets how
/// sharply the kink models are told apart.
constexpr double kMinResidualStd_px = 0.25;

// ---- small functions --------------------------------------------------------------------
Vec leftNormal(const Vec& v) {
  return {-v.y(), v.x()};
}

bool finitePose(const Vec& p, double theta) {
  return std::isfinite(p.x()) && std::isfinite(p.y()) && std::isfinite(theta);
}

/// q coordinates of a scene point, and back.
Vec sceneToQ(const ImageGeometry& g, const Point2& p) {
  const cv::Point2d px = g.toPixel(p);
  return {px.x, -px.y};
}
Point2 qToScene(const ImageGeometry& g, const Vec& q) {
  return g.toScene(cv::Point2d(q.x(), -q.y()));
}

/// Filtered images of the (padded) search region, needle polarity made bright.
struct RidgeImages {
  cv::Rect region;     ///< filtered region in frame pixels (the window plus padding)
  cv::Rect window;     ///< the search window in frame pixels
  cv::Mat smooth;      ///< CV_32F smoothed, bright needle
  cv::Mat ridge;       ///< CV_32F ridge strength R >= 0
  cv::Mat normal_c;    ///< CV_32F cross-line unit vector, column component (image axes)
  cv::Mat normal_r;    ///< CV_32F cross-line unit vector, row component (image axes)
  cv::Mat anisotropy;  ///< CV_32F (|l1| - |l2|) / (|l1| + |l2|): 1 for a line, 0 for a blob

  /// Bilinear sample of `m` at q; false outside the region shrunk by `border` pixels.
  bool sample(const cv::Mat& m, const Vec& q, double border, double& out) const {
    const double c = q.x() - region.x;
    const double r = -q.y() - region.y;
    if (!(c >= border && r >= border && c <= region.width - 1 - border &&
          r <= region.height - 1 - border)) {
      return false;
    }
    const int c0 = std::min(static_cast<int>(c), region.width - 2);
    const int r0 = std::min(static_cast<int>(r), region.height - 2);
    const double fc = c - c0;
    const double fr = r - r0;
    const float* a = m.ptr<float>(r0);
    const float* b = m.ptr<float>(r0 + 1);
    out = (1 - fr) * ((1 - fc) * a[c0] + fc * a[c0 + 1]) + fr * ((1 - fc) * b[c0] + fc * b[c0 + 1]);
    return true;
  }
  /// Cross-line direction at the pixel nearest q, in q axes (unit), and how line-like it is.
  Vec normalAt(const Vec& q, double& line_likeness) const {
    const int c = std::clamp(static_cast<int>(std::lround(q.x() - region.x)), 0, region.width - 1);
    const int r =
        std::clamp(static_cast<int>(std::lround(-q.y() - region.y)), 0, region.height - 1);
    line_likeness = anisotropy.at<float>(r, c);
    return {normal_c.at<float>(r, c), -normal_r.at<float>(r, c)};
  }
};

RidgeImages filterRegion(const cv::Mat& frame, const cv::Rect& window, Modality modality,
                         double smoothing_px) {
  RidgeImages out;
  out.window = window;
  // The window plus a margin for the filters and the centre-line sampling; beyond the frame's
  // edges the frame is mirrored, so a needle running along an edge can still be traced (a tip
  // found in the mirrored part is refused later).
  const int pad = static_cast<int>(std::ceil(3.0 * smoothing_px)) + 3;
  out.region =
      cv::Rect(window.x - pad, window.y - pad, window.width + 2 * pad, window.height + 2 * pad);
  const cv::Rect inside = out.region & cv::Rect(0, 0, frame.cols, frame.rows);
  cv::Mat roi8;
  cv::copyMakeBorder(frame(inside), roi8, inside.y - out.region.y,
                     out.region.br().y - inside.br().y, inside.x - out.region.x,
                     out.region.br().x - inside.br().x,
                     cv::BORDER_REFLECT_101 | cv::BORDER_ISOLATED);
  cv::Mat roi;
  roi8.convertTo(roi, CV_32F);
  if (modality == Modality::kFluoroscopy) {
    roi = 255.0f - roi;  // dark needle on a bright background -> bright ridge
  }
  detail::HessianRidge h =
      detail::hessianRidge(roi, smoothing_px, kBlobPenalty, cv::BORDER_REPLICATE);
  out.smooth = h.smooth;
  out.ridge = h.strength;
  out.normal_c.create(out.smooth.size(), CV_32F);
  out.normal_r.create(out.smooth.size(), CV_32F);
  out.anisotropy.create(out.smooth.size(), CV_32F);
  for (int r = 0; r < out.smooth.rows; ++r) {
    const float* l1 = h.lambda_across.ptr<float>(r);  // most negative: across a bright line
    const float* l2 = h.lambda_along.ptr<float>(r);
    const float* hd = h.half_diff.ptr<float>(r);
    const float* b = h.dxy.ptr<float>(r);
    float* nc = out.normal_c.ptr<float>(r);
    float* nr = out.normal_r.ptr<float>(r);
    float* an = out.anisotropy.ptr<float>(r);
    for (int k = 0; k < out.smooth.cols; ++k) {
      const float sum = std::abs(l1[k]) + std::abs(l2[k]);
      an[k] = sum > 0.0f ? (std::abs(l1[k]) - std::abs(l2[k])) / sum : 0.0f;
      // Eigenvector of l1: (b, l1 - Ixx) or (l1 - Iyy, b), whichever is better conditioned;
      // l1 - Ixx = -root - half_diff and l1 - Iyy = -root + half_diff.
      const float root = 0.5f * (l2[k] - l1[k]);
      float vx = b[k];
      float vy = -root - hd[k];
      const float wx = -root + hd[k];
      const float wy = b[k];
      if (vx * vx + vy * vy < wx * wx + wy * wy) {
        vx = wx;
        vy = wy;
      }
      const float n = std::sqrt(vx * vx + vy * vy);
      if (n > 0.0f) {
        nc[k] = vx / n;
        nr[k] = vy / n;
      } else {
        nc[k] = 0.0f;
        nr[k] = 1.0f;
      }
    }
  }
  return out;
}

struct Candidate {
  Vec q;                  ///< position [px, q axes]
  Vec along;              ///< unit direction of the ridge (sign arbitrary)
  double weight = 0.0;    ///< RANSAC weight: strength clipped and normalised, in (0, 1]
  double strength = 0.0;  ///< ridge strength R
};

/// Ridge points of the window: local maxima of R across the line above an adaptive threshold,
/// the strongest kMaxCandidates of them (ties broken by position: deterministic).
std::vector<Candidate> ridgeCandidates(const RidgeImages& ri) {
  const int x0 = ri.window.x - ri.region.x;
  const int y0 = ri.window.y - ri.region.y;
  std::vector<double> values;
  values.reserve(static_cast<std::size_t>(ri.window.area()));
  for (int r = y0; r < y0 + ri.window.height; ++r) {
    const float* rr = ri.ridge.ptr<float>(r);
    for (int c = x0; c < x0 + ri.window.width; ++c) {
      values.push_back(rr[c]);
    }
  }
  const double med = upperMedian(values);
  std::vector<double> dev(values.size());
  for (std::size_t i = 0; i < values.size(); ++i) {
    dev[i] = std::abs(values[i] - med);
  }
  const double mad_std = 1.4826 * upperMedian(dev);
  const double strong = orderStatistic(values, kStrongRidgeQuantile);
  const double threshold = std::max(
      {med + kCandidateThresholdSigmas * mad_std, kRelativeCandidateThreshold * strong, 1e-3});

  std::vector<Candidate> out;
  for (int r = std::max(y0, 1); r < std::min(y0 + ri.window.height, ri.ridge.rows - 1); ++r) {
    const float* rr = ri.ridge.ptr<float>(r);
    for (int c = std::max(x0, 1); c < std::min(x0 + ri.window.width, ri.ridge.cols - 1); ++c) {
      const float v = rr[c];
      if (v < threshold) {
        continue;
      }
      const float nc = ri.normal_c.at<float>(r, c);
      const float nr = ri.normal_r.at<float>(r, c);
      const int dc = static_cast<int>(std::lround(nc));
      const int dr = static_cast<int>(std::lround(nr));
      if (ri.ridge.at<float>(r + dr, c + dc) > v || ri.ridge.at<float>(r - dr, c - dc) > v) {
        continue;  // not the centre of the line
      }
      Candidate cand;
      cand.q = Vec(c + ri.region.x, -(r + ri.region.y));
      cand.along = leftNormal(Vec(nc, -nr));  // the normal in q axes is (nc, -nr)
      cand.weight = v;
      cand.strength = v;
      out.push_back(cand);
    }
  }
  if (out.size() > kMaxCandidates) {
    std::stable_sort(out.begin(), out.end(),
                     [](const Candidate& a, const Candidate& b) { return a.weight > b.weight; });
    out.resize(kMaxCandidates);
  }
  std::vector<double> w;
  w.reserve(out.size());
  for (const auto& c : out) {
    w.push_back(c.weight);
  }
  const double clip = std::max(orderStatistic(w, kWeightClipQuantile), 1e-9);
  for (auto& c : out) {
    c.weight = std::min(c.weight, clip) / clip;
  }
  return out;
}

/// A circle of the known radius traversed in the insertion direction: side +1 = bevel left
/// (counter-clockwise), -1 = right.
struct Arc {
  Vec centre = Vec::Zero();
  double side = 1.0;
};

/// Unit tangent of the arc at q, in the direction of travel.
Vec tangentAt(const Arc& arc, const Vec& q) {
  return arc.side * leftNormal((q - arc.centre).normalized());
}

/// What the prior says, in q axes.
struct PriorQ {
  Vec tip = Vec::Zero();
  Vec dir = Vec(1.0, 0.0);
  double side = 1.0;
  double pos_sigma3_px = 0.0;
  double heading_sigma3_rad = 0.0;
};

bool consistentWithPrior(const Arc& arc, const PriorQ& pr, double radius_px, double ps) {
  const Vec d = pr.tip - arc.centre;
  const double dist = d.norm();
  if (std::abs(dist - radius_px) > pr.pos_sigma3_px + kPriorLateralSlack_m / ps) {
    return false;
  }
  const Vec on = arc.centre + radius_px * d / std::max(dist, 1e-9);
  const Vec t = tangentAt(arc, on);
  const double dtheta = std::acos(std::clamp(t.dot(pr.dir), -1.0, 1.0));
  return dtheta <= pr.heading_sigma3_rad + kPriorHeadingSlack_rad;
}

/// Weighted Gauss-Newton of the centre of a circle of known radius through points.
/// Returns false if it does not converge to a finite centre.
bool refineCentre(const std::vector<Vec>& pts, const std::vector<double>& w, double radius_px,
                  Vec& centre, double* rss = nullptr, Eigen::Matrix2d* normal = nullptr) {
  if (pts.size() < 3) {
    return false;
  }
  Vec c = centre;
  Eigen::Matrix2d jtj = Eigen::Matrix2d::Zero();
  double sum = 0.0;
  for (int it = 0; it < kGaussNewtonIterations; ++it) {
    jtj.setZero();
    Vec jtr = Vec::Zero();
    sum = 0.0;
    for (std::size_t i = 0; i < pts.size(); ++i) {
      const Vec d = pts[i] - c;
      const double n = d.norm();
      if (n < 1e-9) {
        continue;
      }
      const double res = n - radius_px;
      const Vec j = -d / n;  // d res / d centre
      jtj += w[i] * j * j.transpose();
      jtr += w[i] * j * res;
      sum += w[i] * res * res;
    }
    // Along the chord the centre is poorly determined for short arcs; a tiny damping keeps
    // the step finite without biasing converged fits.
    const Eigen::Matrix2d damped = jtj + 1e-9 * Eigen::Matrix2d::Identity();
    const Vec step = damped.ldlt().solve(-jtr);
    if (!std::isfinite(step.x()) || !std::isfinite(step.y())) {
      return false;
    }
    c += step;
    if (step.norm() < 1e-6) {
      break;
    }
  }
  if (!std::isfinite(c.x()) || !std::isfinite(c.y())) {
    return false;
  }
  centre = c;
  if (rss != nullptr) {
    double s = 0.0;
    for (std::size_t i = 0; i < pts.size(); ++i) {
      const double res = (pts[i] - c).norm() - radius_px;
      s += w[i] * res * res;
    }
    *rss = s;
  }
  if (normal != nullptr) {
    *normal = jtj;
  }
  return true;
}

struct RansacResult {
  bool ok = false;
  Arc arc;
  double score = 0.0;
  std::vector<int> inliers;
};

std::vector<int> inliersOf(const Arc& arc, const std::vector<Candidate>& cands, double radius_px) {
  std::vector<int> out;
  const double cos_max = std::cos(kMaxRidgeAngle_rad);
  for (std::size_t i = 0; i < cands.size(); ++i) {
    const Vec d = cands[i].q - arc.centre;
    const double n = d.norm();
    if (std::abs(n - radius_px) > kInlierBand_px) {
      continue;
    }
    const Vec t = leftNormal(d / n);
    if (std::abs(t.dot(cands[i].along)) < cos_max) {
      continue;
    }
    out.push_back(static_cast<int>(i));
  }
  return out;
}

struct RansacResult;
void refitOnInliers(RansacResult& best, const std::vector<Candidate>& cands, double radius_px);

/// Sum of the weights of the candidates on the arc (within the band, ridge along the arc).
double arcScore(const Arc& arc, const std::vector<Candidate>& cands, double radius_px) {
  const double cos_max = std::cos(kMaxRidgeAngle_rad);
  const double band2_lo = (radius_px - kInlierBand_px) * (radius_px - kInlierBand_px);
  const double band2_hi = (radius_px + kInlierBand_px) * (radius_px + kInlierBand_px);
  double score = 0.0;
  for (const auto& c : cands) {
    const Vec dk = c.q - arc.centre;
    const double n2 = dk.squaredNorm();
    if (n2 < band2_lo || n2 > band2_hi) {
      continue;
    }
    const Vec t = leftNormal(dk) / std::sqrt(n2);
    if (std::abs(t.dot(c.along)) < cos_max) {
      continue;
    }
    score += c.weight;
  }
  return score;
}

/// Median raw ridge strength of the candidates on the arc (0 if none).
double arcBrightness(const Arc& arc, const std::vector<Candidate>& cands, double radius_px) {
  std::vector<double> v;
  for (int k : inliersOf(arc, cands, radius_px)) {
    v.push_back(cands[static_cast<std::size_t>(k)].strength);
  }
  return upperMedian(v);
}

RansacResult ransacArc(const std::vector<Candidate>& cands, double radius_px, double ps,
                       const std::optional<PriorQ>& prior) {
  RansacResult best;
  const int n = static_cast<int>(cands.size());
  if (n < kMinInliers) {
    return best;
  }
  std::mt19937 rng(kRansacSeed);
  const double min_pair_px = kMinPairDistance_m / ps;
  const double max_pair_px = 1.6 * radius_px;
  const double cos_max = std::cos(kMaxRidgeAngle_rad);
  for (int it = 0; it < kRansacIterations; ++it) {
    const int i = static_cast<int>(rng() % static_cast<std::uint32_t>(n));
    const int j = static_cast<int>(rng() % static_cast<std::uint32_t>(n));
    Vec a = cands[i].q;
    Vec b = cands[j].q;
    Vec chord = b - a;
    const double d = chord.norm();
    if (d < min_pair_px || d > max_pair_px) {
      continue;
    }
    // Orient the chord along the insertion direction.
    const Vec hint = prior ? prior->dir : Vec(1.0, 0.0);
    if (chord.dot(hint) < 0.0) {
      std::swap(a, b);
      chord = -chord;
    }
    const Vec u = chord / d;
    const double h = std::sqrt(std::max(0.0, radius_px * radius_px - 0.25 * d * d));
    const Vec mid = 0.5 * (a + b);
    for (double side : {1.0, -1.0}) {
      if (prior && side != prior->side) {
        continue;
      }
      Arc arc{mid + side * h * leftNormal(u), side};
      if (prior && !consistentWithPrior(arc, *prior, radius_px, ps)) {
        continue;
      }
      // Both sample points must look like the arc locally.
      const Vec ta = leftNormal((a - arc.centre) / radius_px);
      const Vec tb = leftNormal((b - arc.centre) / radius_px);
      if (std::abs(ta.dot(cands[i].along)) < cos_max &&
          std::abs(ta.dot(cands[j].along)) < cos_max) {
        continue;
      }
      if (std::abs(tb.dot(cands[j].along)) < cos_max &&
          std::abs(tb.dot(cands[i].along)) < cos_max) {
        continue;
      }
      const double score = arcScore(arc, cands, radius_px);
      if (score > best.score) {
        best.score = score;
        best.arc = arc;
        best.ok = true;
      }
    }
  }
  if (!best.ok) {
    return best;
  }
  refitOnInliers(best, cands, radius_px);
  return best;
}

/// Ultrasound: reverberation echoes repeat the needle deeper (+y, away from the probe on the
/// lower face), dimmer. If a copy of the fitted arc moved towards the probe by one echo spacing
/// also scores well, the fit was an echo: move to that copy (repeatedly).
void preferShallowestCopy(RansacResult& fit, const std::vector<Candidate>& cands, double radius_px,
                          double ps, const std::optional<PriorQ>& prior, int& moves) {
  moves = 0;
  for (int round = 0; round < kMaxEchoMoves; ++round) {
    double best_score = 0.0;
    Arc best_arc;
    const int shifts =
        static_cast<int>((kEchoMaxShift_m - kEchoMinShift_m) / ps / kEchoShiftStep_px);
    for (int i = 0; i <= shifts; ++i) {
      const double shift = kEchoMinShift_m / ps + i * kEchoShiftStep_px;
      Arc moved = fit.arc;
      moved.centre.y() -= shift;
      if (prior && !consistentWithPrior(moved, *prior, radius_px, ps)) {
        continue;
      }
      const double score = arcScore(moved, cands, radius_px);
      if (score > best_score) {
        best_score = score;
        best_arc = moved;
      }
    }
    if (best_score < kEchoScoreRatio * fit.score) {
      return;
    }
    // An echo is dimmer than the needle that makes it: the copy must be at least as bright
    // (a tissue boundary running alongside, dimmer than the needle, does not qualify).
    if (arcBrightness(best_arc, cands, radius_px) < arcBrightness(fit.arc, cands, radius_px)) {
      return;
    }
    fit.arc = best_arc;
    fit.score = best_score;
    refitOnInliers(fit, cands, radius_px);
    ++moves;
  }
}

void refitOnInliers(RansacResult& best, const std::vector<Candidate>& cands, double radius_px) {
  // Least-squares refit on the inliers, twice (the inlier set moves with the centre).
  for (int pass = 0; pass < 2; ++pass) {
    best.inliers = inliersOf(best.arc, cands, radius_px);
    std::vector<Vec> pts;
    std::vector<double> w;
    for (int k : best.inliers) {
      pts.push_back(cands[static_cast<std::size_t>(k)].q);
      w.push_back(cands[static_cast<std::size_t>(k)].weight);
    }
    Vec c = best.arc.centre;
    if (refineCentre(pts, w, radius_px, c)) {
      best.arc.centre = c;
    }
  }
  best.inliers = inliersOf(best.arc, cands, radius_px);
  best.score = arcScore(best.arc, cands, radius_px);
}

/// One sample of the centre-line trace.
struct TraceSample {
  double s = 0.0;         ///< arc length along the coarse arc from its reference point [px]
  double offset = 0.0;    ///< lateral offset of the centre line (outward normal) [px]
  double contrast = 0.0;  ///< cross-line contrast of the needle there [grey]; 0 if not line-like
  bool inside = false;    ///< sampled inside the filtered region
};

/// Traces the needle's centre line along the coarse arc.
class Tracer {
public:
  Tracer(const RidgeImages& ri, const Arc& arc, double radius_px, const Vec& reference,
         double side_distance_px)
      : ri_(ri), arc_(arc), radius_px_(radius_px), side_px_(side_distance_px) {
    const Vec d = reference - arc.centre;
    phi_ref_ = std::atan2(d.y(), d.x());
  }

  double sOf(const Vec& q) const {
    const Vec d = q - arc_.centre;
    return arc_.side * radius_px_ * wrapAngle(std::atan2(d.y(), d.x()) - phi_ref_);
  }
  Vec base(double s) const {
    const double phi = phi_ref_ + arc_.side * s / radius_px_;
    return arc_.centre + radius_px_ * Vec(std::cos(phi), std::sin(phi));
  }
  Vec outward(double s) const {
    const double phi = phi_ref_ + arc_.side * s / radius_px_;
    return {std::cos(phi), std::sin(phi)};
  }
  Vec point(double s, double offset) const { return base(s) + offset * outward(s); }

  /// The contrast profile across the line at s around `predicted_offset`.
  /// `slope` is d offset / d s of the tracked centre line (its direction relative to the arc).
  TraceSample sampleAt(double s, double predicted_offset, double slope = 0.0,
                       double half_range_px = kLateralSearch_px) const {
    TraceSample out;
    out.s = s;
    out.offset = predicted_offset;
    const Vec b = base(s);
    const Vec n = outward(s);
    constexpr int kMaxHalf = static_cast<int>(kLateralSearchWide_px / kLateralStep_px);
    const int half = std::min(kMaxHalf, static_cast<int>(half_range_px / kLateralStep_px));
    std::array<double, 2 * kMaxHalf + 1> v{};
    for (int k = -half; k <= half; ++k) {
      const double o = predicted_offset + k * kLateralStep_px;
      double val = 0.0;
      if (!ri_.sample(ri_.smooth, b + o * n, kTraceBorder_px + side_px_, val)) {
        return out;  // outside: inside = false
      }
      const int index = k + half;
      v[static_cast<std::size_t>(index)] = val;
    }
    out.inside = true;
    int best = 0;
    for (int k = 1; k < 2 * half + 1; ++k) {
      if (v[static_cast<std::size_t>(k)] > v[static_cast<std::size_t>(best)]) {
        best = k;
      }
    }
    double frac = 0.0;
    if (best > 0 && best < 2 * half) {
      const auto b0 = static_cast<std::size_t>(best);
      const double ym = v[b0 - 1];
      const double y0 = v[b0];
      const double yp = v[b0 + 1];
      const double den = ym - 2.0 * y0 + yp;
      if (den < 0.0) {
        frac = std::clamp(0.5 * (ym - yp) / den, -0.5, 0.5);
      }
    }
    const double o_peak = predicted_offset + (best - half + frac) * kLateralStep_px;
    const Vec pc = b + o_peak * n;
    double centre = 0.0;
    double left = 0.0;
    double right = 0.0;
    if (!ri_.sample(ri_.smooth, pc, kTraceBorder_px, centre) ||
        !ri_.sample(ri_.smooth, pc - side_px_ * n, kTraceBorder_px, left) ||
        !ri_.sample(ri_.smooth, pc + side_px_ * n, kTraceBorder_px, right)) {
      out.inside = false;
      return out;
    }
    out.offset = o_peak;
    // Line-like: brighter than BOTH sides (a step edge is not), and the Hessian's cross-line
    // direction along the arc's normal (a structure crossing the arc is not the needle).
    double contrast = std::min(centre - left, centre - right);
    // The tracked line's normal: the arc's, turned by the offset's slope. A clearly line-like
    // structure across it is something else crossing the needle's path (a blob, e.g. the tip's
    // bright echo, has no direction and passes).
    double line_likeness = 0.0;
    const Vec nh = ri_.normalAt(pc, line_likeness);
    const Vec line_normal = (n - slope * tangentAt(arc_, b)).normalized();
    if (line_likeness > kCrossingLineLikeness &&
        std::abs(nh.dot(line_normal)) < std::cos(kMaxCrossingAngle_rad)) {
      contrast = 0.0;
    }
    out.contrast = std::max(0.0, contrast);
    return out;
  }

  /// Walks from s0 in steps of `step` (sign = direction) until `s_stop` or the region's edge,
  /// following the centre line's offset. Visibility threshold `visible` [grey].
  std::vector<TraceSample> walk(double s0, double s_stop, double step, double visible,
                                bool& hit_edge) const {
    std::vector<TraceSample> out;
    hit_edge = false;
    const int history = std::max(2, static_cast<int>(kOffsetHistory_px / std::abs(step)));
    std::vector<std::pair<double, double>> good;  // (s, offset) of recent visible samples
    for (double s = s0; step > 0 ? s <= s_stop : s >= s_stop; s += step) {
      double predicted = 0.0;
      double slope = 0.0;
      if (good.size() >= 2) {
        // Linear extrapolation of the recent visible offsets (least squares).
        double ms = 0.0;
        double mo = 0.0;
        for (const auto& g : good) {
          ms += g.first;
          mo += g.second;
        }
        ms /= static_cast<double>(good.size());
        mo /= static_cast<double>(good.size());
        double sso = 0.0;
        double sss = 0.0;
        for (const auto& g : good) {
          sso += (g.first - ms) * (g.second - mo);
          sss += (g.first - ms) * (g.first - ms);
        }
        slope = sss > 0.0 ? std::clamp(sso / sss, -kMaxOffsetSlope, kMaxOffsetSlope) : 0.0;
        predicted = mo + slope * (s - ms);
      } else if (good.size() == 1) {
        predicted = good.front().second;
      }
      TraceSample t = sampleAt(s, predicted, slope);
      if (!t.inside) {
        hit_edge = true;
        break;
      }
      if (t.contrast < visible && !good.empty() &&
          std::abs(s - good.back().first) <= kRecoveryLength_px) {
        // Lost just now (a kink turned the needle out of the narrow search): look wider, and
        // if the needle is there, follow it from there with a fresh history.
        const TraceSample wide = sampleAt(s, predicted, 0.0, kLateralSearchWide_px);
        if (wide.inside && wide.contrast >= visible) {
          t = wide;
          good.clear();
        }
      }
      if (t.contrast >= visible) {
        good.emplace_back(t.s, t.offset);
        if (static_cast<int>(good.size()) > history) {
          good.erase(good.begin());
        }
      }
      out.push_back(t);
    }
    return out;
  }

private:
  const RidgeImages& ri_;
  Arc arc_;
  double radius_px_;
  double side_px_;
  double phi_ref_ = 0.0;
};

struct LocalFit {
  bool ok = false;
  Arc arc;
  double rss = 0.0;
  int n = 0;
  Eigen::Matrix2d normal = Eigen::Matrix2d::Zero();  ///< J^T W J of the centre
  double weight_sum = 0.0;
  /// Covariance of the centre per unit residual variance: (J^T W J)^-1, or for a fit
  /// constrained through a point, its rank-one heading part plus the point's uncertainty.
  Eigen::Matrix2d centre_cov_unit = Eigen::Matrix2d::Identity() * 1e6;
};

LocalFit fitSpan(const std::vector<Vec>& pts, const std::vector<double>& w,
                 const std::vector<double>& s, double s_lo, double s_hi, const Arc& start,
                 double radius_px) {
  LocalFit f;
  std::vector<Vec> p;
  std::vector<double> ww;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (s[i] >= s_lo && s[i] <= s_hi) {
      p.push_back(pts[i]);
      ww.push_back(w[i]);
      f.weight_sum += w[i];
    }
  }
  f.n = static_cast<int>(p.size());
  if (f.n < 4) {
    return f;
  }
  f.arc = start;
  f.ok = refineCentre(p, ww, radius_px, f.arc.centre, &f.rss, &f.normal);
  if (f.ok) {
    const Eigen::Matrix2d inv = (f.normal + 1e-9 * Eigen::Matrix2d::Identity()).inverse();
    if (inv.allFinite()) {
      f.centre_cov_unit = inv;
    }
  }
  return f;
}

/// The tip arc after a kink, continuous with the arc before it: through the kink point kink_point,
/// only its heading phi there is free (Gauss-Newton in phi). `point_var_unit` is kink_point's
/// variance per unit residual variance (from the fit before the kink).
LocalFit fitThroughPoint(const std::vector<Vec>& pts, const std::vector<double>& w,
                         const std::vector<double>& s, double s_lo, double s_hi,
                         const Vec& kink_point, double phi0, double side, double radius_px,
                         double point_var_unit) {
  LocalFit f;
  std::vector<Vec> p;
  std::vector<double> ww;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (s[i] >= s_lo && s[i] <= s_hi) {
      p.push_back(pts[i]);
      ww.push_back(w[i]);
      f.weight_sum += w[i];
    }
  }
  f.n = static_cast<int>(p.size());
  if (f.n < 3) {
    return f;
  }
  const auto centre_of = [&](double phi) {
    return Vec(kink_point + side * radius_px * Vec(-std::sin(phi), std::cos(phi)));
  };
  double phi = phi0;
  double jtj = 0.0;
  for (int it = 0; it < kGaussNewtonIterations; ++it) {
    const Vec c = centre_of(phi);
    const Vec dc = side * radius_px * Vec(-std::cos(phi), -std::sin(phi));
    jtj = 0.0;
    double jtr = 0.0;
    for (std::size_t i = 0; i < p.size(); ++i) {
      const Vec d = p[i] - c;
      const double n = d.norm();
      if (n < 1e-9) {
        continue;
      }
      const double res = n - radius_px;
      const double j = -(d / n).dot(dc);
      jtj += ww[i] * j * j;
      jtr += ww[i] * j * res;
    }
    if (!(jtj > 0.0)) {
      return f;
    }
    const double step = std::clamp(-jtr / jtj, -0.2, 0.2);
    phi += step;
    if (std::abs(step) < 1e-9) {
      break;
    }
  }
  if (!std::isfinite(phi)) {
    return f;
  }
  f.arc = {centre_of(phi), side};
  f.rss = 0.0;
  for (std::size_t i = 0; i < p.size(); ++i) {
    const double res = (p[i] - f.arc.centre).norm() - radius_px;
    f.rss += ww[i] * res * res;
  }
  const Vec dc = side * radius_px * Vec(-std::cos(phi), -std::sin(phi));
  f.centre_cov_unit = dc * dc.transpose() / jtj + point_var_unit * Eigen::Matrix2d::Identity();
  f.ok = true;
  return f;
}

/// The start of a fit of the other sense: mirror the centre through the local arc point.
Arc mirrored(const Arc& arc, const Vec& through, double radius_px) {
  const Vec d = (through - arc.centre).normalized();
  return {through + radius_px * d, -arc.side};
}

}  // namespace

std::string frameProblem(const cv::Mat& frame, const ImageGeometry& geometry) {
  if (frame.empty()) {
    return "empty frame (dropped)";
  }
  if (frame.type() != CV_8UC1) {
    std::ostringstream s;
    s << "frame encoding is not 8-bit single-channel (CV_8UC1): depth " << frame.depth() << ", "
      << frame.channels() << " channel(s)";
    return s.str();
  }
  if (frame.cols != geometry.cols || frame.rows != geometry.rows) {
    std::ostringstream s;
    s << "frame is " << frame.cols << "x" << frame.rows << " px, the calibration expects "
      << geometry.cols << "x" << geometry.rows;
    return s.str();
  }
  double lo = 0.0;
  double hi = 0.0;
  cv::minMaxLoc(frame, &lo, &hi);
  if (hi - lo < kMinFrameContrast_grey) {
    std::ostringstream s;
    s << "frame has no contrast (grey levels " << lo << ".." << hi << ")";
    return s.str();
  }
  return "";
}

cv::Rect searchWindow(const TrackerConfig& config, const std::optional<SearchPrior>& prior) {
  const ImageGeometry& g = config.geometry;
  const cv::Rect frame(0, 0, std::max(g.cols, 0), std::max(g.rows, 0));
  if (!prior) {
    return frame;
  }
  const Eigen::Matrix3d& cov = prior->covariance;
  const auto& tip = prior->tip;
  if (!cov.allFinite() || !finitePose(tip.p_SceneTip, tip.theta_rad)) {
    return frame;
  }
  const Eigen::Matrix2d pos =
      0.5 * (cov.topLeftCorner<2, 2>() + cov.topLeftCorner<2, 2>().transpose());
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(pos);
  const double pos_sigma = std::sqrt(std::max(0.0, es.eigenvalues().maxCoeff()));
  const double heading_sigma = std::sqrt(std::max(0.0, cov(2, 2)));
  const double base_radius = 3.0 * pos_sigma + config.search_margin_m;
  double x0 = std::numeric_limits<double>::infinity();
  double y0 = x0;
  double x1 = -x0;
  double y1 = -x0;
  constexpr int kBackSamples = 4;
  // Back along the predicted arc: reverse heading, mirrored bevel traces the same circle.
  needle_model::TipPose back{tip.p_SceneTip, tip.theta_rad + kPi, needle_model::flipped(tip.bevel)};
  for (int k = 0; k <= kBackSamples; ++k) {
    const double dist = kSearchBackLength_m * k / kBackSamples;
    const Point2 p = k == 0 ? tip.p_SceneTip
                            : needle_model::advanceTip(back, needle_model::Control::kInsert, 0.0,
                                                       dist, config.radius_of_curvature_m)
                                  .p_SceneTip;
    const double rad = base_radius + dist * std::min(3.0 * heading_sigma, 1.0);
    x0 = std::min(x0, p.x() - rad);
    x1 = std::max(x1, p.x() + rad);
    y0 = std::min(y0, p.y() - rad);
    y1 = std::max(y1, p.y() + rad);
  }
  if (!(std::isfinite(x0) && std::isfinite(x1) && std::isfinite(y0) && std::isfinite(y1))) {
    return frame;
  }
  const cv::Point2d a = g.toPixel(Point2(x0, y1));  // top-left
  const cv::Point2d b = g.toPixel(Point2(x1, y0));  // bottom-right
  const double big = 1e7;
  const int c0 = static_cast<int>(std::floor(std::clamp(a.x, -big, big)));
  const int r0 = static_cast<int>(std::floor(std::clamp(a.y, -big, big)));
  const int c1 = static_cast<int>(std::ceil(std::clamp(b.x, -big, big)));
  const int r1 = static_cast<int>(std::ceil(std::clamp(b.y, -big, big)));
  if (c1 < c0 || r1 < r0) {
    return {};
  }
  return cv::Rect(c0, r0, c1 - c0 + 1, r1 - r0 + 1) & frame;
}

namespace {

/// What the numbered steps of one detection share; each step reads what the earlier ones left
/// and returns an empty string, or why the detection fails.
struct DetectState {
  DetectState(const TrackerConfig& c, const std::optional<SearchPrior>& p)
      : config(c), prior(p), g(c.geometry) {}
  DetectState(const DetectState&) = delete;  // the tracer refers to ri
  DetectState& operator=(const DetectState&) = delete;
  const TrackerConfig& config;
  const std::optional<SearchPrior>& prior;
  const ImageGeometry& g;
  double ps = 0.0, radius_px = 0.0, diameter_px = 0.0, smoothing_px = 0.0;
  cv::Rect window;
  std::optional<PriorQ> pq;
  // 1-2. ridge candidates and the arc
  RidgeImages ri;
  std::vector<Candidate> cands;
  RansacResult rs;
  int echo_moves = 0;
  std::optional<Tracer> tracer;
  std::vector<double> inlier_s;
  // 3. contrast levels
  double shaft_level = 0.0, s_mid = 0.0, s_stop = 0.0, background_level = 0.0;
  double visible = 0.0, reliable = 0.0;
  std::vector<double> background;
  // 4. the tip along the arc
  std::vector<TraceSample> fwd;
  std::size_t change = 0;
  std::vector<double> tip_levels;
  double tip_level = 0.0, run_start_s = 0.0, s_tip = 0.0, slope_per_px = 0.0;
  // 5. centre-line points behind the tip
  std::vector<TraceSample> pts_s;
  std::vector<Vec> pts;
  std::vector<double> w, ss;
  // 6. the arc models and the chosen one
  struct Model {
    LocalFit tip_arc;
    double total_rss = 0.0;
    int params = 2;
    double kink_s = std::numeric_limits<double>::quiet_NaN();
    double log_prior = 0.0;
    double unseen_deflection_var = 0.0;  ///< heading variance of a deflection not yet visible
    double log_w = 0.0;
    Vec p = Vec::Zero();
    double theta = 0.0;
  };
  std::vector<Model> models;
  Vec along_point = Vec::Zero();
  double s_lo = 0.0, s_hi = 0.0, tip_side = 0.0, sigma2 = 0.0;
  double flip_kink = 0.0, step_kink = 0.0;
  std::size_t map = 0;
  Vec tip_q = Vec::Zero();
  double theta = 0.0;
  Eigen::Matrix3d model_spread = Eigen::Matrix3d::Zero();
  // 7. covariance
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();

  /// The tip pose on `arc` at the tip's point along the needle.
  void tipPose(const Arc& arc, Vec& p, double& th) const {
    const Vec d = along_point - arc.centre;
    p = arc.centre + radius_px * d / d.norm();
    const Vec t = arc.side * leftNormal(d / d.norm());
    th = std::atan2(t.y(), t.x());
  }
};

/// Step 0: the configuration, the frame, the search window and its contrast; the prior in
/// pixel coordinates.
std::string checkInputs(const cv::Mat& frame, DetectState& st) {
  const TrackerConfig& config = st.config;
  const ImageGeometry& g = st.g;
  if (!(std::isfinite(g.pixel_size_m) && g.pixel_size_m > 0.0 && g.rows > 0 && g.cols > 0) ||
      !(std::isfinite(config.radius_of_curvature_m) && config.radius_of_curvature_m > 0.0)) {
    return "invalid tracker configuration (pixel grid or radius of curvature)";
  }
  const std::string problem = frameProblem(frame, g);
  if (!problem.empty()) {
    return problem;
  }
  const double ps = g.pixel_size_m;
  st.ps = ps;
  st.radius_px = config.radius_of_curvature_m / ps;
  st.window = searchWindow(config, st.prior);
  const int min_window_px = static_cast<int>(std::ceil(kMinArcSpan_m / ps)) + 4;
  if (st.window.width < min_window_px || st.window.height < 4) {
    return "search window outside the frame or too small";
  }
  double lo = 0.0;
  double hi = 0.0;
  cv::minMaxLoc(frame(st.window), &lo, &hi);
  if (hi - lo < kMinFrameContrast_grey) {
    return "no contrast in the search window";
  }
  if (st.prior) {
    const SearchPrior& prior = *st.prior;
    PriorQ p;
    p.tip = sceneToQ(g, prior.tip.p_SceneTip);
    p.dir = Vec(std::cos(prior.tip.theta_rad), std::sin(prior.tip.theta_rad));
    p.side = prior.tip.bevel == needle_model::Bevel::kLeft ? 1.0 : -1.0;
    const Eigen::Matrix2d pos = prior.covariance.topLeftCorner<2, 2>();
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(0.5 * (pos + pos.transpose()));
    p.pos_sigma3_px = 3.0 * std::sqrt(std::max(0.0, es.eigenvalues().maxCoeff())) / ps;
    p.heading_sigma3_rad = std::min(3.0 * std::sqrt(std::max(0.0, prior.covariance(2, 2))), kPi);
    st.pq = p;
  }
  return "";
}

/// Steps 1-2: ridge filter and candidates; RANSAC arc of the known radius (the prior's sense,
/// or both); the tracer along it and the inliers' arc lengths.
std::string fitNeedleArc(const cv::Mat& frame, DetectState& st) {
  const TrackerConfig& config = st.config;
  const double ps = st.ps;
  st.diameter_px = config.needle_diameter_m / ps;
  st.smoothing_px = std::max(kMinSmoothing_px, kSmoothingPerDiameter * st.diameter_px);
  st.ri = filterRegion(frame, st.window, config.modality, st.smoothing_px);
  st.cands = ridgeCandidates(st.ri);
  const std::vector<Candidate>& cands = st.cands;
  if (static_cast<int>(cands.size()) < kMinInliers) {
    return "too few ridge points in the search window (" + std::to_string(cands.size()) + ")";
  }
  RansacResult& rs = st.rs;
  rs = ransacArc(cands, st.radius_px, ps, st.pq);
  if (rs.ok && config.modality == Modality::kUltrasound) {
    preferShallowestCopy(rs, cands, st.radius_px, ps, st.pq, st.echo_moves);
  }
  if (!rs.ok || static_cast<int>(rs.inliers.size()) < kMinInliers) {
    return "no arc of the needle's radius found (" + std::to_string(rs.ok ? rs.inliers.size() : 0) +
           " inliers of " + std::to_string(cands.size()) + " ridge points)";
  }
  // Reference point of the arc length s: the inliers' mean.
  Vec mean = Vec::Zero();
  for (int k : rs.inliers) {
    mean += cands[static_cast<std::size_t>(k)].q;
  }
  mean /= static_cast<double>(rs.inliers.size());
  st.tracer.emplace(st.ri, rs.arc, st.radius_px, mean,
                    0.5 * st.diameter_px + st.smoothing_px + kSideDistanceExtra_px);
  for (int k : rs.inliers) {
    st.inlier_s.push_back(st.tracer->sOf(cands[static_cast<std::size_t>(k)].q));
  }
  std::sort(st.inlier_s.begin(), st.inlier_s.end());
  const double span_px = st.inlier_s.back() - st.inlier_s.front();
  if (span_px * ps < kMinArcSpan_m) {
    return "arc inliers span only " + fmt(span_px * ps * 1e3, 2) + " mm";
  }
  // Without a prior the insertion direction is the sense whose tangent points along +x at the
  // inliers' middle; RANSAC oriented every chord that way already, so the sense is the arc's.
  return "";
}

/// Step 3: contrast levels of the shaft (at the inliers) and of the background (the same
/// statistic on arcs parallel to the fit, off the needle; the median over several offsets, so
/// an echo or boundary along one of them does not matter).
std::string contrastLevels(DetectState& st) {
  const Tracer& tracer = *st.tracer;
  const std::vector<double>& inlier_s = st.inlier_s;
  const double ps = st.ps;
  std::vector<double> inlier_contrast;
  for (std::size_t k = 0; k < inlier_s.size();
       k += std::max<std::size_t>(1, inlier_s.size() / 40)) {
    const TraceSample t = tracer.sampleAt(inlier_s[k], 0.0);
    if (t.inside && t.contrast > 0.0) {
      inlier_contrast.push_back(t.contrast);
    }
  }
  st.shaft_level = upperMedian(inlier_contrast);
  st.s_mid = inlier_s[inlier_s.size() / 2];
  st.s_stop = inlier_s.back() + (st.pq ? kMaxGap_m : kNoPriorLookahead_m) / ps;
  if (st.pq) {
    const double s_prior = tracer.sOf(st.pq->tip);
    st.s_stop =
        std::max(st.s_stop, s_prior + st.pq->pos_sigma3_px + st.config.search_margin_m / ps);
  }
  std::vector<double>& background = st.background;
  for (double off : kBackgroundOffsets_px) {
    const int count = static_cast<int>((st.s_stop - inlier_s.front()) / kBackgroundStep_px);
    for (int i = 0; i <= count; ++i) {
      const TraceSample t = tracer.sampleAt(inlier_s.front() + i * kBackgroundStep_px, off);
      if (t.inside) {
        background.push_back(t.contrast);
      }
    }
  }
  st.background_level = upperMedian(background);
  const double shaft_level = st.shaft_level, background_level = st.background_level;
  if (!(shaft_level > 0.0) || background.size() < 8 ||
      shaft_level - background_level <
          kMinContrastOverBackground * std::max(background_level, 1.0)) {
    return "the fitted arc does not stand out from the background (shaft " + fmt(shaft_level, 1) +
           ", background " + fmt(background_level, 1) + " grey)";
  }
  // A sample is needle-like above `visible` (the change point's threshold); only samples above
  // the higher `reliable` steer the tracing (so it does not wander off along noise).
  st.visible = std::max(orderStatistic(background, kBackgroundQuantile),
                        background_level + kVisibleFraction * (shaft_level - background_level));
  st.reliable = background_level + kReliableFraction * (shaft_level - background_level);
  return "";
}

/// Step 4a: walk forward from the inliers' middle to beyond the expected tip; the tip is the
/// change point of the contrast (the last sample of the largest partial sum of contrast -
/// visible): gaps of the partly visible needle are bridged when more needle follows, a short
/// bright structure after a gap is not. Then the plateau just before the end: the largest
/// running median over the last stretch (the tip may echo brighter than the shaft, and the
/// shaft's brightness varies along it).
std::string changePointAndPlateau(DetectState& st) {
  const double ps = st.ps;
  bool fwd_edge = false;
  st.fwd = st.tracer->walk(st.s_mid, st.s_stop, kTraceStep_px, st.reliable, fwd_edge);
  const std::vector<TraceSample>& fwd = st.fwd;
  if (fwd.size() < 4) {
    return "the fitted arc leaves the search region";
  }
  std::size_t change = 0;
  double sum = 0.0;
  double best_sum = -std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < fwd.size(); ++i) {
    sum += fwd[i].contrast - st.visible;
    if (sum > best_sum) {
      best_sum = sum;
      change = i;
    }
  }
  st.change = change;
  if (fwd_edge && (fwd.back().s - fwd[change].s) < kEdgeClearance_px) {
    return "the needle runs out of the search region (tip not inside it)";
  }
  std::vector<double>& tip_levels = st.tip_levels;
  int visible_count = 0;
  for (std::size_t i = change + 1; i-- > 0;) {
    if (fwd[change].s - fwd[i].s > kPlateauSearch_m / ps) {
      break;
    }
    tip_levels.push_back(fwd[i].contrast);
    visible_count += fwd[i].contrast >= st.visible ? 1 : 0;
  }
  if (visible_count * kTraceStep_px * ps < kMinTipRun_m) {
    return "too little visible needle before the tip (" +
           fmt(visible_count * kTraceStep_px * ps * 1e3, 2) + " mm)";
  }
  double tip_level = upperMedian(tip_levels);
  const std::size_t half_window = static_cast<std::size_t>(kPlateauWindow_px / kTraceStep_px / 2.0);
  for (std::size_t i = change + 1; i-- > half_window;) {
    if (fwd[change].s - fwd[i].s > kPlateauSearch_m / ps) {
      break;
    }
    if (i + half_window > change) {
      continue;
    }
    std::vector<double> win;
    for (std::size_t k = i - half_window; k <= i + half_window; ++k) {
      win.push_back(fwd[k].contrast);
    }
    tip_level = std::max(tip_level, upperMedian(win));
  }
  st.tip_level = tip_level;
  return "";
}

/// Step 4b: the tip where the contrast falls through kTipLevelFraction of the plateau over the
/// background, then refined to the steepest descent of the (lightly smoothed) contrast near it:
/// the end's edge, whatever the level the tip's brighter echo or the shaft reaches.
void tipAtEdge(DetectState& st) {
  const std::vector<TraceSample>& fwd = st.fwd;
  st.run_start_s = std::min(fwd.front().s, st.inlier_s.front());
  const std::size_t last_run = st.change;
  const double half =
      st.background_level + kTipLevelFraction * (st.tip_level - st.background_level);
  std::size_t last_above = last_run;
  while (last_above + 1 < fwd.size() && fwd[last_above + 1].contrast >= half &&
         fwd[last_above + 1].s - fwd[last_run].s < 2.0 * st.diameter_px + 2.0) {
    ++last_above;
  }
  while (last_above > 0 && fwd[last_above].contrast < half) {
    --last_above;
  }
  double s_tip = fwd[last_above].s;
  double slope_per_px = 0.0;
  if (last_above + 1 < fwd.size()) {
    const double g0 = fwd[last_above].contrast;
    const double g1 = fwd[last_above + 1].contrast;
    const double ds = fwd[last_above + 1].s - fwd[last_above].s;
    if (g0 > g1) {
      s_tip += ds * std::clamp((g0 - half) / (g0 - g1), 0.0, 1.0);
      slope_per_px = (g0 - g1) / ds;
    }
  }
  const double s_half = s_tip;
  constexpr std::array<double, 5> kSmooth = {1.0, 2.0, 3.0, 2.0, 1.0};
  const auto smoothed = [&](std::size_t i) {
    double sum = 0.0;
    double wsum = 0.0;
    for (std::size_t k = 0; k < kSmooth.size(); ++k) {
      const auto j = static_cast<std::ptrdiff_t>(i + k) - 2;
      if (j >= 0 && j < static_cast<std::ptrdiff_t>(fwd.size())) {
        sum += kSmooth[k] * fwd[static_cast<std::size_t>(j)].contrast;
        wsum += kSmooth[k];
      }
    }
    return sum / wsum;
  };
  std::vector<std::size_t> idx;
  std::vector<double> deriv;
  for (std::size_t i = 2; i + 2 < fwd.size(); ++i) {
    if (std::abs(fwd[i].s - s_half) > kEdgeSearch_px) {
      continue;
    }
    idx.push_back(i);
    deriv.push_back((smoothed(i + 2) - smoothed(i - 2)) / (fwd[i + 2].s - fwd[i - 2].s));
  }
  if (deriv.size() >= 3) {
    const auto k =
        static_cast<std::size_t>(std::min_element(deriv.begin(), deriv.end()) - deriv.begin());
    if (deriv[k] < 0.0) {
      double frac = 0.0;
      if (k > 0 && k + 1 < deriv.size()) {
        const double den = deriv[k - 1] - 2.0 * deriv[k] + deriv[k + 1];
        if (den > 0.0) {
          frac = std::clamp(0.5 * (deriv[k - 1] - deriv[k + 1]) / den, -0.5, 0.5);
        }
      }
      s_tip = fwd[idx[k]].s + frac * kTraceStep_px;
      slope_per_px = -deriv[k];
    }
  }
  st.s_tip = s_tip;
  st.slope_per_px = slope_per_px;
}

/// Step 5: centre-line points behind the tip: the forward walk, plus a backward walk if needed.
std::string centreLinePoints(DetectState& st) {
  const double ps = st.ps;
  const double s_tip = st.s_tip;
  const double fit_len_px = kLocalFitLength_m / ps;
  std::vector<TraceSample>& pts_s = st.pts_s;
  for (const auto& t : st.fwd) {
    if (t.s <= s_tip && t.s >= s_tip - fit_len_px) {
      pts_s.push_back(t);
    }
  }
  if (st.s_mid > s_tip - fit_len_px) {
    bool back_edge = false;
    std::vector<TraceSample> bwd = st.tracer->walk(st.s_mid - kTraceStep_px, s_tip - fit_len_px,
                                                   -kTraceStep_px, st.reliable, back_edge);
    pts_s.insert(pts_s.end(), bwd.begin(), bwd.end());
  }
  const double exclusion_px = kLocalFitTipExclusion_m / ps;
  for (const auto& t : pts_s) {
    if (t.contrast < st.visible || t.s > s_tip - exclusion_px) {
      continue;
    }
    st.pts.push_back(st.tracer->point(t.s, t.offset));
    const double rel = std::min(1.0, t.contrast / std::max(st.tip_level, 1e-9));
    st.w.push_back(rel * rel);
    st.ss.push_back(t.s);
  }
  if (st.pts.size() < 6) {
    return "too few centre-line points behind the tip (" + std::to_string(st.pts.size()) + ")";
  }
  return "";
}

/// Step 6 (one model): a kink at sk: the arc before it (either sense, or forced), and the tip
/// arc through the kink point with a free heading there (the deflection). Too few samples after
/// the kink (a flip just now): the tip arc continues the tangent and the flip's deflection,
/// unseen, is added to the heading variance.
void addKinkModel(DetectState& st, double sk, int before_side_required, double prior_mass) {
  const std::vector<Vec>& pts = st.pts;
  const std::vector<double>& w = st.w;
  const std::vector<double>& ss = st.ss;
  const double radius_px = st.radius_px, s_lo = st.s_lo, s_hi = st.s_hi;
  const double tip_side = st.tip_side;
  const Arc start = st.rs.arc;
  const double blur_gap_px = kKinkBlurExclusion_m / st.ps;
  // The image blur rounds the corner: samples within kKinkBlurExclusion_m of it are left out.
  const Arc mirror = mirrored(start, st.tracer->point(sk, 0.0), radius_px);
  LocalFit before;
  if (before_side_required == 0 || before_side_required == static_cast<int>(start.side)) {
    before = fitSpan(pts, w, ss, s_lo, sk - blur_gap_px, start, radius_px);
  }
  if (before_side_required == 0 || before_side_required == static_cast<int>(mirror.side)) {
    const LocalFit before_m = fitSpan(pts, w, ss, s_lo, sk - blur_gap_px, mirror, radius_px);
    if (!before.ok || (before_m.ok && before_m.rss < before.rss)) {
      before = before_m;
    }
  }
  if (!before.ok) {
    return;
  }
  Vec near = Vec::Zero();
  int count = 0;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (std::abs(ss[i] - sk) <= 2.0) {
      near += pts[i];
      ++count;
    }
  }
  // The kink point: the centre line there (the arc before it is least certain at its end).
  const Vec kink_point = count > 0 ? Vec(near / count) : st.tracer->point(sk, 0.0);
  const Vec dk = (kink_point - before.arc.centre).normalized();
  const Vec t_before = before.arc.side * leftNormal(dk);
  const LocalFit free_tip =
      fitSpan(pts, w, ss, sk + blur_gap_px, s_hi, Arc{start.centre, tip_side}, radius_px);
  const Vec t0 = free_tip.ok ? tangentAt(free_tip.arc, kink_point) : t_before;
  DetectState::Model m;
  m.tip_arc =
      fitThroughPoint(pts, w, ss, sk + blur_gap_px, s_hi, kink_point, std::atan2(t0.y(), t0.x()),
                      tip_side, radius_px, 1.0 / std::max(before.weight_sum, 1.0));
  if (!m.tip_arc.ok) {
    const double phi = std::atan2(t_before.y(), t_before.x());
    m.tip_arc.arc = {kink_point + tip_side * radius_px * Vec(-std::sin(phi), std::cos(phi)),
                     tip_side};
    m.tip_arc.ok = true;
    m.tip_arc.rss = 0.0;
    m.tip_arc.n = 0;
    m.tip_arc.weight_sum = 0.0;
    m.tip_arc.centre_cov_unit = before.centre_cov_unit;
    m.unseen_deflection_var = st.config.sigma_flip_rad * st.config.sigma_flip_rad;
  }
  // Same data as the single arc: the samples around the corner count with the nearer arc.
  m.total_rss = m.tip_arc.rss + before.rss;
  for (std::size_t i = 0; i < pts.size(); ++i) {
    if (std::abs(ss[i] - sk) < blur_gap_px && ss[i] >= s_lo && ss[i] <= s_hi) {
      const double rb = (pts[i] - before.arc.centre).norm() - radius_px;
      const double rt = (pts[i] - m.tip_arc.arc.centre).norm() - radius_px;
      m.total_rss += w[i] * std::min(rb * rb, rt * rt);
    }
  }
  m.params = 3;
  m.kink_s = sk;
  m.log_prior = std::log(prior_mass);
  st.models.push_back(m);
}

/// Step 6 (models): one arc over the whole span, or a kink (the deflection at the start of an
/// insertion step, or a flip) at s_k with the tip arc after it, where the robot says the kinks
/// are (the prior's lengths since the flip and the step) or anywhere.
std::string arcModels(DetectState& st) {
  const double ps = st.ps;
  const double diameter_px = st.diameter_px;
  st.s_tip -= kTipRoundingRadii * 0.5 * diameter_px;
  const double s_tip = st.s_tip;
  {
    // The centre line's offset at the tip: that of the last visible samples.
    std::vector<double> o;
    for (const auto& t : st.pts_s) {
      if (t.contrast >= st.visible && t.s <= s_tip && t.s >= s_tip - 2.0 * diameter_px) {
        o.push_back(t.offset);
      }
    }
    st.along_point = st.tracer->point(s_tip, o.empty() ? 0.0 : upperMedian(o));
  }
  st.s_lo = *std::min_element(st.ss.begin(), st.ss.end());
  st.s_hi = s_tip + kTipRoundingRadii * 0.5 * diameter_px;
  {
    DetectState::Model m;
    m.tip_arc = fitSpan(st.pts, st.w, st.ss, st.s_lo, st.s_hi, st.rs.arc, st.radius_px);
    if (!m.tip_arc.ok) {
      return "local arc refit did not converge";
    }
    m.total_rss = m.tip_arc.rss;
    m.log_prior = std::log(1.0 - kKinkPrior);
    st.models.push_back(m);
  }
  st.tip_side = st.models.front().tip_arc.arc.side;
  const double min_tip_arc_px = kMinTipArc_m / ps;
  const double min_before_px = kMinArcBeforeKink_m / ps;
  const double tol_px = kKinkHintTolerance_m / ps;
  const auto hinted_at = [&](double length_m) {
    return st.pq && std::isfinite(length_m) && length_m >= 0.0
               ? s_tip - length_m / ps
               : std::numeric_limits<double>::quiet_NaN();
  };
  st.flip_kink = hinted_at(st.prior ? st.prior->length_since_flip_m : 0.0);
  st.step_kink = hinted_at(st.prior ? st.prior->length_since_step_m : 0.0);
  const double flip_kink = st.flip_kink, step_kink = st.step_kink;
  const double kink_lo = st.s_lo + min_before_px;
  if (std::isfinite(flip_kink) && flip_kink + tol_px >= kink_lo) {
    // The flip is inside the span: the needle before it curves the other way. Only kinks at
    // the flip (within the tolerance) and no single arc.
    st.models.clear();
    std::vector<double> locations;
    const int steps = static_cast<int>(2.0 * tol_px / (kKinkStep_m / ps));
    for (int i = 0; i <= steps; ++i) {
      const double sk = flip_kink - tol_px + i * kKinkStep_m / ps;
      if (sk >= kink_lo) {
        locations.push_back(std::min(sk, st.s_hi));
      }
    }
    for (double sk : locations) {
      addKinkModel(st, sk, -static_cast<int>(st.tip_side),
                   1.0 / static_cast<double>(locations.size()));
    }
    if (st.models.empty()) {
      return "no arc fits before the bevel flip";
    }
    return "";
  }
  // Kinks anywhere (a deflection at each step's start; the needle before it of either sense
  // unless the prior says the last flip is before the span); near the step's start if the
  // robot's steps are known.
  const int before_side =
      st.pq && std::isfinite(st.prior->length_since_flip_m) ? static_cast<int>(st.tip_side) : 0;
  std::vector<double> locations;
  int near_hint = 0;
  const int steps = static_cast<int>((st.s_hi - min_tip_arc_px - kink_lo) / (kKinkStep_m / ps));
  for (int i = 0; i <= steps; ++i) {
    const double sk = st.s_hi - min_tip_arc_px - i * kKinkStep_m / ps;
    locations.push_back(sk);
    near_hint += std::abs(sk - step_kink) <= tol_px ? 1 : 0;
  }
  const double hint_mass = near_hint > 0 ? kStepHintPrior : 0.0;
  st.models.front().log_prior = std::log((1.0 - hint_mass) * (1.0 - kKinkPrior));
  const int others = static_cast<int>(locations.size()) - near_hint;
  for (double sk : locations) {
    const bool at_hint = std::abs(sk - step_kink) <= tol_px;
    const double mass =
        at_hint ? hint_mass / near_hint : (1.0 - hint_mass) * kKinkPrior / std::max(1, others);
    addKinkModel(st, sk, before_side, mass);
  }
  return "";
}

/// Step 6 (choice): each model's weight is its likelihood (residuals, counted as
/// n / kResidualCorrelationSamples independent ones, with a BIC penalty for the tip arc's two
/// extra parameters) times its prior; the estimate is the most probable model's and the spread
/// of the models' tip poses is added to its covariance, so a kink that cannot be told apart
/// (just behind the tip) shows as heading uncertainty rather than as a confident wrong heading.
std::string chooseModel(DetectState& st) {
  const ImageGeometry& g = st.g;
  const int n_points = static_cast<int>(st.pts.size());
  double best_rate = std::numeric_limits<double>::infinity();
  for (const auto& m : st.models) {
    best_rate = std::min(best_rate, m.total_rss / std::max(1, n_points - m.params - 1));
  }
  st.sigma2 = std::max(best_rate, kMinResidualStd_px * kMinResidualStd_px);
  const double n_eff = std::max(1.0, n_points / kResidualCorrelationSamples);
  double max_log_w = -std::numeric_limits<double>::infinity();
  for (std::size_t i = 0; i < st.models.size(); ++i) {
    DetectState::Model& m = st.models[i];
    const bool kink = std::isfinite(m.kink_s);
    m.log_w = -0.5 * m.total_rss / (st.sigma2 * kResidualCorrelationSamples) -
              (kink ? std::log(n_eff) : 0.0) + m.log_prior;
    st.tipPose(m.tip_arc.arc, m.p, m.theta);
    if (!finitePose(m.p, m.theta)) {
      m.log_w = -std::numeric_limits<double>::infinity();
    }
    if (m.log_w > max_log_w) {
      max_log_w = m.log_w;
      st.map = i;
    }
  }
  const DetectState::Model& chosen_model = st.models[st.map];
  st.tip_q = chosen_model.p;
  st.theta = chosen_model.theta;
  const Vec tip_q = st.tip_q;
  if (!finitePose(tip_q, st.theta)) {
    return "non-finite tip pose";
  }
  if (tip_q.x() < -0.5 || -tip_q.y() < -0.5 || tip_q.x() > g.cols - 0.5 ||
      -tip_q.y() > g.rows - 0.5) {
    return "the needle runs out of the frame (tip not inside it)";
  }
  double wsum = 0.0;
  for (const auto& m : st.models) {
    const double wm = std::exp(m.log_w - max_log_w);
    if (!(wm > 0.0)) {
      continue;
    }
    const Eigen::Vector3d d(m.p.x() - tip_q.x(), m.p.y() - tip_q.y(),
                            wrapAngle(m.theta - st.theta));
    st.model_spread += wm * d * d.transpose();
    if (m.unseen_deflection_var > 0.0) {
      // A heading change at the kink turns the tip arc about the kink point.
      const double h = std::max(0.0, st.s_tip - m.kink_s);
      const Eigen::Vector3d gr(-std::sin(m.theta) * h, std::cos(m.theta) * h, 1.0);
      st.model_spread += wm * m.unseen_deflection_var * gr * gr.transpose();
    }
    wsum += wm;
  }
  st.model_spread /= std::max(wsum, 1e-300);
  return "";
}

/// Step 7: covariance: the chosen fit's (residuals through the tip pose's dependence on the
/// arc's centre), the models' spread, the along-needle uncertainty of the end and floors.
std::string detectionCovariance(DetectState& st) {
  const LocalFit& chosen = st.models[st.map].tip_arc;
  const double ps = st.ps, theta = st.theta, s_tip = st.s_tip;
  const int dof = std::max(1, chosen.n - 2);
  // The residual variance: the chosen fit's own, but not below that of the best model over
  // all the points (a short tip arc's few residuals say little about the noise).
  const double res_var =
      std::max(chosen.rss / std::max(chosen.weight_sum, 1e-9) * chosen.n / dof, st.sigma2) *
      kResidualCorrelationSamples;
  const Eigen::Matrix2d cov_c = res_var * chosen.centre_cov_unit;  // sigma^2 (J^T W J)^-1
  Eigen::Matrix<double, 3, 2> jac;
  constexpr double kFiniteDiff_px = 0.01;
  for (int k = 0; k < 2; ++k) {
    Vec dc = Vec::Zero();
    dc[k] = kFiniteDiff_px;
    Vec p1, p0;
    double t1 = 0.0;
    double t0 = 0.0;
    st.tipPose(Arc{chosen.arc.centre + dc, chosen.arc.side}, p1, t1);
    st.tipPose(Arc{chosen.arc.centre - dc, chosen.arc.side}, p0, t0);
    jac.block<2, 1>(0, k) = (p1 - p0) / (2.0 * kFiniteDiff_px);
    jac(2, k) = wrapAngle(t1 - t0) / (2.0 * kFiniteDiff_px);
  }
  Eigen::Matrix3d cov_px = jac * cov_c * jac.transpose() + st.model_spread;
  // The fit ends before the tip (the exclusion at the end, or a stretch the needle is not
  // visible): a step's deflection may kink the needle in between, unseen. Its variance is
  // added with the probability that a step starts there (known from the prior's length since
  // the step, else the gap's share of a step length).
  {
    const double last_fitted = *std::max_element(st.ss.begin(), st.ss.end());
    const double gap_px = std::max(0.0, s_tip - last_fitted);
    double p_kink = std::min(1.0, gap_px * ps / st.config.step_length_m);
    if (std::isfinite(st.step_kink)) {
      p_kink = st.step_kink > last_fitted && st.step_kink <= s_tip ? 1.0 : 0.0;
    }
    const bool flip_in_gap =
        std::isfinite(st.flip_kink) && st.flip_kink > last_fitted && st.flip_kink <= s_tip;
    const double sigma = flip_in_gap ? st.config.sigma_flip_rad : st.config.sigma_insert_rad;
    if (gap_px > 0.0 && p_kink > 0.0 && sigma > 0.0) {
      const Eigen::Vector3d gr(-std::sin(theta) * gap_px, std::cos(theta) * gap_px, 1.0);
      cov_px += p_kink * sigma * sigma * gr * gr.transpose();
    }
  }
  // Along the needle: the half-maximum's noise over the contrast profile's slope.
  std::vector<double> dev;
  dev.reserve(st.tip_levels.size());
  for (double v : st.tip_levels) {
    dev.push_back(std::abs(v - st.tip_level));
  }
  const double contrast_noise = 1.4826 * upperMedian(dev);
  double along_std_px = st.slope_per_px > 0.0 ? contrast_noise / st.slope_per_px : kMaxAlongStd_px;
  along_std_px = std::clamp(along_std_px, kMinAlongStd_px, kMaxAlongStd_px);
  const Vec tdir(std::cos(theta), std::sin(theta));
  cov_px.topLeftCorner<2, 2>() += along_std_px * along_std_px * tdir * tdir.transpose();
  cov_px.topLeftCorner<2, 2>() +=
      kPositionFloor_px * kPositionFloor_px * Eigen::Matrix2d::Identity();
  cov_px(2, 2) += kHeadingFloor_rad * kHeadingFloor_rad;
  Eigen::Matrix3d cov = cov_px;
  cov.topLeftCorner<2, 2>() *= ps * ps;
  cov.block<2, 1>(0, 2) *= ps;
  cov.block<1, 2>(2, 0) *= ps;
  cov = 0.5 * (cov + cov.transpose());
  if (!cov.allFinite()) {
    return "non-finite detection covariance";
  }
  st.cov = cov;
  return "";
}

/// Step 8: consistency with the prior's direction, and the detection with its message.
Detection assembleDetection(const DetectState& st) {
  if (st.pq) {
    const double dtheta = std::abs(wrapAngle(st.theta - st.prior->tip.theta_rad));
    if (dtheta > st.pq->heading_sigma3_rad + kPriorHeadingSlack_rad) {
      return fail("detected heading " + fmt(st.theta / kDeg, 1) +
                  " deg inconsistent with the prior " + fmt(st.prior->tip.theta_rad / kDeg, 1) +
                  " deg");
    }
  }
  const LocalFit& chosen = st.models[st.map].tip_arc;
  const double kink_s = st.models[st.map].kink_s;
  const double ps = st.ps;
  Detection d;
  d.found = true;
  d.p_SceneTip = qToScene(st.g, st.tip_q);
  d.theta_rad = st.theta;
  d.covariance = st.cov;
  d.inliers = static_cast<int>(st.rs.inliers.size());
  d.residual_rms_m = std::sqrt(chosen.rss / std::max(chosen.weight_sum, 1e-9)) * ps;
  std::ostringstream msg;
  msg << "arc fit: " << d.inliers << " inliers of " << st.cands.size() << ", bevel "
      << (chosen.arc.side > 0 ? "left" : "right") << ", rms " << fmt(d.residual_rms_m * 1e3)
      << " mm, traced " << fmt((st.s_tip - st.run_start_s) * ps * 1e3, 1) << " mm, contrast "
      << fmt(st.tip_level - st.background_level, 0) << " over " << fmt(st.background_level, 0)
      << " grey";
  if (st.echo_moves > 0) {
    msg << ", moved off " << st.echo_moves << " reverberation echo(es)";
  }
  if (std::isfinite(kink_s)) {
    msg << ", kink " << fmt((st.s_tip - kink_s) * ps * 1e3, 1) << " mm behind the tip";
  }
  d.message = msg.str();
  return d;
}

/// The detector's steps in order (tip_tracker.h): the first that fails names why.
Detection detectTipUnguarded(const cv::Mat& frame, const TrackerConfig& config,
                             const std::optional<SearchPrior>& prior) {
  DetectState st(config, prior);
  std::string why = checkInputs(frame, st);
  if (why.empty())
    why = fitNeedleArc(frame, st);
  if (why.empty())
    why = contrastLevels(st);
  if (why.empty())
    why = changePointAndPlateau(st);
  if (why.empty()) {
    tipAtEdge(st);
    why = centreLinePoints(st);
  }
  if (why.empty())
    why = arcModels(st);
  if (why.empty())
    why = chooseModel(st);
  if (why.empty())
    why = detectionCovariance(st);
  return why.empty() ? assembleDetection(st) : fail(why);
}

}  // namespace

Detection detectTip(const cv::Mat& frame, const TrackerConfig& config,
                    const std::optional<SearchPrior>& prior) {
  // Never throws: an OpenCV or allocation failure on a strange input is a failed detection.
  try {
    return detectTipUnguarded(frame, config, prior);
  } catch (const std::exception& e) {
    return fail(std::string("detection failed: ") + e.what());
  }
}

}  // namespace needle_guidance::imaging
