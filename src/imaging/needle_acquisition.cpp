// Needle acquisition without a prior; see needle_acquisition.h for the steps.
#include "needle_guidance/imaging/needle_acquisition.h"
#include "needle_guidance/math.h"
#include "ridge_filter.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <opencv2/video/tracking.hpp>
#include <sstream>
#ifdef __GLIBC__
#include <malloc.h>
#endif
#include <stdexcept>
#include <vector>

namespace needle_guidance::imaging {

namespace {

/// Step 3: the strongest ridge pixels kept for the Hough transform (a thin needle covers well
/// under 1 % of a frame). 3 %, not 2 %: a shaft saturated and merged with its first
/// reverberation copies (realistic tuning sequences) has a weaker ridge at the filter's scale
/// than a thin one, about as strong as the speckle's, and at 2 % its trace broke in two.
/// (A hysteresis trace, Canny's, fixed those too but overshot faint tips.) The Hough transform
/// votes with the strongest 2 % only: its cost grows with the pixels voting, and a line
/// it finds is traced and refit on the 3 % anyway.
constexpr double kRidgeQuantile = 0.97;
constexpr double kHoughQuantile = 0.98;
/// Step 2: the ridge strength is -lambda_across - kBlobPenalty |lambda_along| (ridge_filter.h).
constexpr double kBlobPenalty = 1.0;
/// Step 3: the thresholds are at least this [grey levels / px^2] (a flat frame has no ridge).
constexpr float kMinRidgeThreshold = 2.5e-4F;
/// Step 3: at most kMaxHoughLines distinct Hough lines are examined, until kMaxCandidates
/// distinct segments are found; Hough lines closer than these are the same line.
constexpr int kMaxHoughLines = 64;
constexpr int kMaxCandidates = 24;
constexpr double kSameLineRho_px = 8.0;
constexpr double kSameLineTheta_rad = 4.0 * kPi / 180.0;
/// Sequence cue past the estimated tip: the signed motion map's mean from kAheadFrom_px to
/// kAheadTo_px beyond the tip along its direction (clear of the tip's own blur). A needle
/// whose tip is traced short keeps brightening the tissue there as it advances.
constexpr double kAheadFrom_px = 6.0, kAheadTo_px = 30.0;
/// The window of kAheadTo_px - kAheadFrom_px slides on up to kAheadReach_px beyond the tip: the
/// background model forgets an advance within a few frames, so a tip traced short by more than a
/// frame's advance (a shaft fading with depth) shows its brightening only this far ahead, where
/// the needle went last. When that brightening reaches kMinMotionRatio, the tip moves on along
/// its line to the motion's front (traced short: the needle is there, faint).
constexpr double kAheadReach_px = 60.0;
/// Step 4: a ridge pixel belongs to a line if within this many filter scales of it.
constexpr double kNearLineSigmas = 1.5;
/// Step 5: side bands from 3 to 10 filter scales from the line (outside the needle's own blur,
/// wide enough that an interface's step in echogenicity outweighs a reverberation copy).
/// Step 6: the tip is where the cross-line contrast falls below kTipLevel of the shaft's
/// level, its median along the traced segment (the needle fades towards its tip, and a streak
/// beyond it is fainter still). Chosen on the even frames of the in-vitro set (0.3-0.4 equally
/// good, 0.5 cuts fading tips short), checked on the odd ones.
constexpr double kTipLevel = 0.35;
constexpr double kShaftLevelQuantile = 0.5;
/// Step 6, arc model: the tip walk may go on this many max_gap_px past the traced end, while the
/// contrast stays above the tip level without a gap (the ridge of a tip fading out of the plane
/// drops under the threshold before its contrast drops under the level: the tuning arc
/// sequence's tip stopped 10-30 px short).
constexpr double kArcTipBeyondGaps = 2.0;
constexpr double kBandInnerSigmas = 3.0, kBandOuterSigmas = 10.0;
/// Step 4: two traced segments whose ends lie within this of each other are one structure (the
/// refit pulls the Hough lines through both shoulders of a thick layer onto the same ridge) [px].
constexpr double kSameSegment_px = 6.0;
/// Step 4: a straight segment lying along another (both its ends within kSameStructure_px of
/// the other's line and span, directions within kSameStructure_rad) is a part of the same
/// structure: a thick, long interface otherwise fills every candidate slot with its chords.
constexpr double kSameStructure_px = 10.0;
constexpr double kSameStructure_rad = 6.0 * kPi / 180.0;
/// Step 4: an end of a segment within this of the frame's border lies on the border [px].
constexpr double kBorderMargin_px = 3.0;
/// Step 5: power of the side symmetry in the score: an interface between media whose
/// echogenicity differs by half scores an eighth, a needle inside one medium nearly 1.
constexpr double kSymmetryPower = 3.0;
/// Step 6: the same power where the darker side is the deeper one (larger row), for the
/// acceptance of the best candidate only (not its ranking): the needle's own acoustic shadow
/// darkens the tissue beneath it, so that asymmetry is a needle's cue as much as an interface's.
/// A needle in textured in-vivo tissue with its shadow then passes min_evidence; an interface
/// still loses the ranking to a needle beside it.
constexpr double kShadowSymmetryPower = 1.0;
/// Sequence cue (SequenceTracker): a candidate moves if the frame difference against the
/// background model, averaged over the tip end of its segment (the last kMotionTipZone of it,
/// at least kMotionMinZone_px), is kMinMotionRatio times the frame's mean difference (noise,
/// speckle flicker). A needle advancing along its own axis changes the pixels at its tip while
/// still tissue, a still interface or a still wire does not; a moving probe changes everything,
/// and then no candidate stands out and the cue is silent.
constexpr double kMotionTipZone = 0.3;
constexpr double kMotionMinZone_px = 10.0;
constexpr double kMotionBeyondGaps = 2.0;  // the zone runs on this many max_gap_px past the end
constexpr double kMinMotionRatio = 3.0;
/// Motion-only tip (tipFromMotion): the motion map's level a blob is cut at, the share of the
/// frame's brightening above it the blob must hold, its peak and its area.
constexpr double kBlobLevel = 4.0;
constexpr int kBlobJoin_px = 4;
constexpr int kBlobSpeck_px = 20;
constexpr double kBlobDominance = 0.9;
/// The share a blob must hold when its front continues a moving track (agrees with the motion
/// model's prediction): moving tissue leaves residues of its motion over the frame (its borders,
/// edges of layers), and the needle's tip, already found, needs no dominance to be told from them.
constexpr double kBlobDominanceOnTrack = 0.5;
/// Before any track has moved: a blob holding kBlobDominanceChain of the change whose front
/// advanced kChainStepMin_px to kGateTip_px in each of the last kChainFrames - 1 frames, each step
/// along the blob's axis and the steps within kChainTurnCos of each other, is a needle being
/// inserted (a residue of moving tissue comes and goes, and its fronts do not advance in line).
constexpr double kBlobDominanceChain = 0.4;
constexpr int kChainFrames = 3;
constexpr double kChainStepMin_px = 3.0;
constexpr double kChainTurnCos = 0.94;  // 20 degrees
constexpr double kBlobPeak = 10.0;
constexpr int kBlobMinArea_px = 100;
/// A line whose tip lies within this of the blob's front is the needle seen [px] (the front lies
/// among the reverberation copies, up to 25 px from the shaft at 0.1 mm pixels).
constexpr double kBlobOnLine_px = 24.0;
/// A blob's front this far ahead of a line's tip along it: the tip was traced short [px].
constexpr double kBlobAhead_px = 10.0;
/// Background model: exponential average of the frames, this weight for the newest.
constexpr double kBackgroundRate = 0.3;
/// Step 5: a ridge pixel is aligned with the line if its orientation is within this [rad].
constexpr double kAlignedTolerance_rad = 15.0 * kPi / 180.0;
/// Imaging region (imaging_region.h), when the frame has a black margin: ridge pixels closer
/// than this many filter scales to the region's boundary are the boundary's own response (a
/// step from black to tissue reads as a bright line at the filter's scale) and are left out.
constexpr double kRegionInsetSigmas = 4.0;
/// A candidate that never goes farther than this from the region's boundary is the region's own
/// edge (a fan's straight side, the probe face's bright arc, the rim of a linear probe's
/// rectangle), never a needle [px]; a needle entering from that edge goes on into the image.
constexpr double kEdgeBand_px = 24.0;
/// A candidate in a bounded region whose two ends both lie within this share of the region's
/// width from its boundary, along the shaft, crosses the image: an interface (runsThroughRegion).
constexpr double kThroughReach = 0.15;
/// A needle reaches a convex fan no deeper than this share of the fan's depth (entersDeep).
constexpr double kMaxEntryDepth = 0.5;
/// A needle inserted through the skin reaches the skin (the row of the probe face's ends, in a
/// fan) within this share of the fan's width beside the face (reachesSkin): an
/// in-plane approach from the probe's end punctures the skin a few centimetres from it, well
/// inside this; a tissue interface a few degrees off the rows, traced back, meets that row
/// several fan widths away, or never.
constexpr double kSkinReach = 0.5;
/// A shaft anchored at the fan's entry (in a fan, the shaft rising to the skin
/// beside the probe, its traced tail within kAnchoredGap_px of the fan's boundary along it, its
/// ridge aligned with it on kAnchoredCoherence of its length) needs kAnchoredEvidence of
/// min_evidence only. A needle just inserted crosses the probe face's bright ring-down band,
/// whose depth gradient counts as noise against the shaft's contrast; a chance line of speckle
/// that starts at the fan's boundary and runs down from the skin beside the probe is rare, and
/// the motion still has to confirm the track before its tip is confident. The gap allowed is
/// the band along the boundary that holds the region's own edge response (kEdgeBand_px): the
/// shaft's first part inside the face's band is often not traced.
constexpr double kAnchoredGap_px = kEdgeBand_px;
constexpr double kAnchoredCoherence = 0.8;
constexpr double kAnchoredEvidence = 0.5;
/// The entry zone's round (examineEntryZone): the band along a fan's boundary, down to
/// kMaxEntryDepth of the fan, where a needle just inserted lies [px]: twice the band that holds
/// the region's own edge (kEdgeBand_px), so a shaft crossing it shows beyond that edge's response.
constexpr double kEntryZone_px = 2.0 * kEdgeBand_px;
/// A candidate entering the fan across its boundary (entersAcrossEdge): its shallower end within
/// kEnterStrip_px beyond the strip whose ridge is left out, its depth rising at
/// kEnterMinAngle_rad or more, its midpoint's depth within kEnterMidShare of the rise from
/// halfway, kEnterMinTraced_px of it traced (a shorter trace gives its axis to +-5 degrees or
/// worse, too loose to gate a track on).
constexpr double kEnterStrip_px = 3.0;
constexpr double kEnterMinAngle_rad = 8.0 * kPi / 180.0;
constexpr double kEnterMidShare = 0.15;
constexpr double kEnterMinTraced_px = kEdgeBand_px;
/// Priors (AcquisitionOptions::entry_point_px, entry_angle_rad): a candidate whose curve passes
/// farther than kPriorPoint_px from the stated entry point, or whose direction differs by more
/// than kPriorAngle_rad from the stated angle, is not the needle.
constexpr double kPriorPoint_px = 25.0;
constexpr double kPriorAngle_rad = 10.0 * kPi / 180.0;

/// Depth profile (flattenDepthProfile): a depth bin with fewer pixels of the fan than this keeps
/// its grey levels as they are (too few to tell its level from a needle's or a layer's).
constexpr int kProfileMinPixels = 24;
constexpr double kProfileMaxGain = 2.0;
constexpr double kProfileMinGain = 0.5;
/// The gain is smoothed over 2 kGainSmooth_px + 1 depths, the median over 2 kLevelSmooth_px + 1:
/// the ring-down band's level falls within a few pixels below the face, its spread does not.
constexpr int kGainSmooth_px = 16;
constexpr int kLevelSmooth_px = 2;

/// The Hessian ridge filter's output: strength (>= 0) and line direction per pixel.
struct RidgeMap {
  cv::Mat strength;              ///< CV_32F, bright-line strength
  cv::Mat dxy, half_diff;        ///< CV_32F, Hessian parts the line direction is computed from
  cv::Mat smooth;                ///< CV_32F, the frame smoothed at the filter scale
  float threshold = 0.0F;        ///< ridge pixels traced and refit (kRidgeQuantile)
  float hough_threshold = 0.0F;  ///< ridge pixels voting in the Hough transform
};

/// A straight line, or with kappa != 0 an arc of constant curvature (a steerable needle):
/// through `point` with tangent `dir` there, turning towards n = (-dir.y, dir.x) at kappa [1/px].
struct Line {
  cv::Point2d point;   ///< a point on the curve
  cv::Point2d dir;     ///< unit tangent at `point`
  double kappa = 0.0;  ///< signed curvature [1/px], 0 = straight
};

struct Candidate {
  Line line;
  double t0 = 0.0, t1 = 0.0;  ///< visible segment along line.dir from line.point
  NeedleSegment cues;
  double score = 0.0;
  double acceptance = 0.0;  ///< score with kShadowSymmetryPower when the shadow side is deeper
};

/// The point at arc length t from l.point.
cv::Point2d at(const Line& l, double t) {
  if (l.kappa == 0.0)
    return l.point + t * l.dir;
  const cv::Point2d n(-l.dir.y, l.dir.x);
  return l.point + (std::sin(l.kappa * t) / l.kappa) * l.dir +
         ((1.0 - std::cos(l.kappa * t)) / l.kappa) * n;
}

/// Unit tangent at arc length t.
cv::Point2d tangent(const Line& l, double t) {
  if (l.kappa == 0.0)
    return l.dir;
  const cv::Point2d n(-l.dir.y, l.dir.x);
  return std::cos(l.kappa * t) * l.dir + std::sin(l.kappa * t) * n;
}

/// Unit normal at arc length t (the tangent turned by +90 degrees in image coordinates).
cv::Point2d normal(const Line& l, double t) {
  const cv::Point2d d = tangent(l, t);
  return {-d.y, d.x};
}

float sample(const cv::Mat& m, cv::Point2d p) {
  // cvRound (one SSE instruction; halves to even) rather than std::lround, a libm call that
  // was a sixth of the acquisition's instructions (callgrind, track_frames on in-vitro frames).
  const int c = cvRound(p.x), r = cvRound(p.y);
  if (c < 0 || r < 0 || c >= m.cols || r >= m.rows)
    return 0.0F;
  return m.at<float>(r, c);
}

/// Step 2: the shared ridge filter (ridge_filter.h) at sigma on the frame as CV_32F, a blob
/// penalised by its whole larger eigenvalue.
RidgeMap ridgeFilter(const cv::Mat& grey32f, double sigma_px) {
  detail::HessianRidge h =
      detail::hessianRidge(grey32f, sigma_px, kBlobPenalty, cv::BORDER_DEFAULT);
  RidgeMap r;
  r.strength = h.strength;
  r.dxy = h.dxy;
  r.half_diff = h.half_diff;
  r.smooth = h.smooth;
  return r;
}

/// The ridge's line direction at p, in [-pi/2, pi/2] [rad].
double ridgeDirection(const RidgeMap& r, cv::Point2d p) {
  return 0.5 * std::atan2(2.0 * sample(r.dxy, p), 2.0 * sample(r.half_diff, p));
}

/// Step 3 (thresholds): the kRidgeQuantile and kHoughQuantile quantiles of the ridge strengths.
void ridgeThresholds(RidgeMap* ridge, const cv::Mat& mask) {
  const cv::Mat& strength = ridge->strength;
  std::vector<float> v;
  v.reserve(strength.total() / 4);
  for (int y = 0; y < strength.rows; y += 2) {
    const float* s = strength.ptr<float>(y);
    const std::uint8_t* inside = mask.empty() ? nullptr : mask.ptr<std::uint8_t>(y);
    for (int x = 0; x < strength.cols; x += 2) {
      if (!inside || inside[x])
        v.push_back(s[x]);
    }
  }
  if (v.empty())
    return;
  auto quantile = [&v](double q) {
    auto k = v.begin() + static_cast<long>(q * static_cast<double>(v.size() - 1));
    std::nth_element(v.begin(), k, v.end());
    return std::max(*k, kMinRidgeThreshold);
  };
  ridge->threshold = quantile(kRidgeQuantile);
  ridge->hough_threshold = quantile(kHoughQuantile);
}

void ridgeThresholds(RidgeMap* ridge, const ImagingRegion& region) {
  ridgeThresholds(ridge, region.bounded() ? region.mask : cv::Mat());
}

/// Step 3: whether Hough lines h and k are the same line within the frame: directions within
/// kSameLineTheta_rad and, where h passes nearest the frame's centre, k within kSameLineRho_px.
/// (Comparing rho alone fails for a segment far from the origin: a 2 degree turn about it moves
/// rho by tens of pixels, and one bright segment then fills every candidate slot.)
bool sameHoughLine(const cv::Vec2f& h, const cv::Vec2f& k, cv::Point2d centre) {
  double dt = std::abs(h[1] - k[1]);
  dt = std::min(dt, kPi - dt);
  if (dt >= kSameLineTheta_rad)
    return false;
  const cv::Point2d nh(std::cos(h[1]), std::sin(h[1])), nk(std::cos(k[1]), std::sin(k[1]));
  const cv::Point2d foot = centre + (h[0] - centre.dot(nh)) * nh;  // h's point nearest centre
  return std::abs(foot.dot(nk) - k[0]) < kSameLineRho_px;
}

/// Step 3: Hough lines on the strongest ridge pixels, strongest first, duplicates merged.
/// Step 3: the strongest ridge pixels that are also the ridge's crest across it (not weaker
/// than both neighbours along its normal): a thick interface votes with its centre line only,
/// not with the many chords through its width that would take every Hough line.
cv::Mat ridgeCrest(const RidgeMap& ridge) {
  cv::Mat crest(ridge.strength.size(), CV_8U, cv::Scalar(0));
  for (int y = 1; y + 1 < crest.rows; ++y) {
    const float* s = ridge.strength.ptr<float>(y);
    std::uint8_t* out = crest.ptr<std::uint8_t>(y);
    for (int x = 1; x + 1 < crest.cols; ++x) {
      if (s[x] <= ridge.hough_threshold)
        continue;
      const double a = ridgeDirection(ridge, cv::Point2d(x, y));
      const int dx = cvRound(-std::sin(a)), dy = cvRound(std::cos(a));  // the normal, rounded
      const float before = ridge.strength.at<float>(y - dy, x - dx);
      const float after = ridge.strength.at<float>(y + dy, x + dx);
      out[x] = s[x] >= before && s[x] >= after ? 255 : 0;
    }
  }
  return crest;
}

std::vector<Line> candidateLines(const RidgeMap& ridge, double min_length_px) {
  cv::Mat binary = ridgeCrest(ridge);
  std::vector<cv::Vec2f> hough;
  const int votes = std::max(10, static_cast<int>(0.5 * min_length_px));
  cv::HoughLines(binary, hough, 1.0, kPi / 180.0, votes);
  const cv::Point2d centre(0.5 * (binary.cols - 1), 0.5 * (binary.rows - 1));
  std::vector<cv::Vec2f> kept;
  for (const cv::Vec2f& h : hough) {
    bool same = false;
    for (const cv::Vec2f& k : kept)
      same = same || sameHoughLine(h, k, centre);
    if (!same)
      kept.push_back(h);
    if (static_cast<int>(kept.size()) >= kMaxHoughLines)
      break;
  }
  std::vector<Line> lines;
  for (const cv::Vec2f& k : kept) {
    const cv::Point2d n(std::cos(k[1]), std::sin(k[1]));
    lines.push_back({k[0] * n, cv::Point2d(-n.y, n.x)});
  }
  return lines;
}

/// Step 4: the parameter range of the line inside the frame.
bool lineSpan(const Line& l, cv::Size size, double* t_lo, double* t_hi) {
  if (l.kappa != 0.0) {
    // An arc: up to a frame diagonal (and a quarter of the circle) either way; the samples
    // outside the frame read 0.
    const double reach =
        std::min(std::hypot(size.width, size.height), 0.5 * kPi / std::abs(l.kappa));
    *t_lo = -reach;
    *t_hi = reach;
    return true;
  }
  double lo = -1e9, hi = 1e9;
  const double p[2] = {l.point.x, l.point.y}, d[2] = {l.dir.x, l.dir.y};
  const double mx[2] = {size.width - 1.0, size.height - 1.0};
  for (int i = 0; i < 2; ++i) {
    if (std::abs(d[i]) < 1e-12) {
      if (p[i] < 0 || p[i] > mx[i])
        return false;
      continue;
    }
    double a = (0 - p[i]) / d[i], b = (mx[i] - p[i]) / d[i];
    if (a > b)
      std::swap(a, b);
    lo = std::max(lo, a);
    hi = std::min(hi, b);
  }
  *t_lo = lo;
  *t_hi = hi;
  return hi > lo;
}

/// Step 4: the strongest run of ridge along the line (gaps up to max_gap bridged).
bool traceSegment(const RidgeMap& ridge, const Line& l, double sigma, double max_gap, double* t0,
                  double* t1, double* strength = nullptr) {
  double lo = 0, hi = 0;
  if (!lineSpan(l, ridge.strength.size(), &lo, &hi))
    return false;
  const int reach = std::max(1, static_cast<int>(std::lround(kNearLineSigmas * sigma)));
  double best = 0, run_sum = 0, run_start = lo, last_on = lo - 2 * max_gap;
  for (double t = lo; t <= hi; t += 1.0) {
    const cv::Point2d n = normal(l, t), p = at(l, t);
    float v = 0.0F;
    for (int k = -reach; k <= reach; ++k)
      v = std::max(v, sample(ridge.strength, p + k * n));
    if (v <= ridge.threshold)
      continue;
    if (t - last_on > max_gap) {
      run_sum = 0;
      run_start = t;
    }
    run_sum += v;
    last_on = t;
    if (run_sum > best) {
      best = run_sum;
      *t0 = run_start;
      *t1 = t;
    }
  }
  if (strength)
    *strength = best;
  return best > 0;
}

/// Step 4: weighted least-squares line through the ridge pixels near the segment.
Line refitLine(const RidgeMap& ridge, const Line& l, double t0, double t1, double sigma) {
  const cv::Point2d n(-l.dir.y, l.dir.x);
  const int reach = std::max(1, static_cast<int>(std::lround(kNearLineSigmas * sigma)));
  double sw = 0, sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
  for (double t = t0; t <= t1; t += 1.0) {
    for (int k = -reach; k <= reach; ++k) {
      const cv::Point2d p = at(l, t) + k * n;
      const double w = sample(ridge.strength, p) - ridge.threshold;
      if (w <= 0)
        continue;
      const double x = std::round(p.x), y = std::round(p.y);
      sw += w, sx += w * x, sy += w * y, sxx += w * x * x, syy += w * y * y, sxy += w * x * y;
    }
  }
  if (sw <= 0)
    return l;
  const double mx = sx / sw, my = sy / sw;
  const double cxx = sxx / sw - mx * mx, cyy = syy / sw - my * my, cxy = sxy / sw - mx * my;
  const double phi = 0.5 * std::atan2(2 * cxy, cxx - cyy);
  cv::Point2d dir(std::cos(phi), std::sin(phi));
  if (dir.dot(l.dir) < 0)
    dir = -dir;
  return {cv::Point2d(mx, my), dir};
}

/// Step 4 (arc of known radius 1 / |l.kappa|): the centre that minimises the weighted squared
/// distance of the ridge pixels near the arc from the circle (Gauss-Newton), re-expressed as an
/// arc through the point nearest the old segment's middle.
Line refitArc(const RidgeMap& ridge, const Line& l, double t0, double t1, double sigma) {
  const double radius = 1.0 / std::abs(l.kappa);
  const double tm = 0.5 * (t0 + t1);
  const cv::Point2d pm = at(l, tm);
  cv::Point2d c = pm + (1.0 / l.kappa) * normal(l, tm);
  std::vector<cv::Point3d> pts;  // x, y, weight
  const int reach = std::max(1, static_cast<int>(std::lround(kNearLineSigmas * sigma)));
  for (double t = t0; t <= t1; t += 1.0) {
    const cv::Point2d n = normal(l, t), p = at(l, t);
    for (int k = -reach; k <= reach; ++k) {
      const cv::Point2d q = p + k * n;
      const double w = sample(ridge.strength, q) - ridge.threshold;
      if (w > 0)
        pts.emplace_back(std::round(q.x), std::round(q.y), w);
    }
  }
  if (pts.size() < 3)
    return l;
  for (int iter = 0; iter < 5; ++iter) {
    double a11 = 0, a12 = 0, a22 = 0, b1 = 0, b2 = 0;
    for (const cv::Point3d& q : pts) {
      const cv::Point2d d(q.x - c.x, q.y - c.y);
      const double r = std::max(cv::norm(d), 1e-9);
      const cv::Point2d j = -d / r;  // d(r - R)/dc
      const double e = r - radius;
      a11 += q.z * j.x * j.x, a12 += q.z * j.x * j.y, a22 += q.z * j.y * j.y;
      b1 -= q.z * j.x * e, b2 -= q.z * j.y * e;
    }
    const double det = a11 * a22 - a12 * a12;
    if (std::abs(det) < 1e-12)
      break;
    c += cv::Point2d((a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det);
  }
  const cv::Point2d radial = (pm - c) / std::max(cv::norm(pm - c), 1e-9);
  Line out;
  out.point = c + radius * radial;
  out.dir = cv::Point2d(-radial.y, radial.x);
  if (out.dir.dot(tangent(l, tm)) < 0)
    out.dir = -out.dir;
  // The centre lies on the side of the normal when kappa > 0.
  const cv::Point2d n(-out.dir.y, out.dir.x);
  out.kappa = (c - out.point).dot(n) > 0 ? 1.0 / radius : -1.0 / radius;
  return out;
}

/// Step 2, in a fan: the frame less its depth profile, at the speckle's typical spread. A B-mode
/// frame is log compressed, so what varies with depth alone (the attenuation and the gain's
/// compensation of it) is an offset in grey levels per depth; and the probe face's ring-down,
/// added to the echoes before compression, lifts the band under the face and compresses every
/// echo contrast in it, the speckle's and a needle's alike. The band's gradient across a needle
/// just inserted reads as noise against its contrast, and its compressed ridge drowns among the
/// whole fan's strongest. At each depth (the distance from the face's centre, or the row under a
/// straight face) the median grey level over the fan is subtracted and the rest scaled by the
/// typical depth's interquartile spread over this depth's (kProfileMinGain to kProfileMaxGain):
/// tissue fills most of a depth's arc, a needle or a layer crosses a few of its pixels. A steep
/// needle crosses many depths, and its faint echo then stands out against the speckle of each.
/// The frame's median level is added back (the side symmetry is a ratio of grey levels).
void flattenDepthProfile(const cv::Mat& grey8, const ImagingRegion& region, cv::Mat* grey32) {
  if (region.shape != ImagingRegion::Shape::kSector || region.mask.empty())
    return;
  const bool curved = region.top_radius_px > 0.0;
  auto depthOf = [&](int x, int y) {
    return curved ? static_cast<int>(
                        std::lround(std::hypot(x - region.apex_px.x, y - region.apex_px.y)))
                  : y;
  };
  const double far = curved ? std::hypot(std::max(region.apex_px.x, grey8.cols - region.apex_px.x),
                                         std::max(region.apex_px.y, grey8.rows - region.apex_px.y))
                            : grey8.rows;
  const int depths = static_cast<int>(far) + 2;
  cv::Mat depth(grey8.size(), CV_32S, cv::Scalar(-1));
  std::vector<int> hist(static_cast<std::size_t>(depths) * 256, 0), all(256, 0);
  for (int y = 0; y < grey8.rows; ++y) {
    const std::uint8_t* g = grey8.ptr<std::uint8_t>(y);
    const std::uint8_t* m = region.mask.ptr<std::uint8_t>(y);
    int* d = depth.ptr<int>(y);
    for (int x = 0; x < grey8.cols; ++x) {
      if (m[x] == 0)
        continue;
      d[x] = std::clamp(depthOf(x, y), 0, depths - 1);
      ++hist[static_cast<std::size_t>(d[x]) * 256 + g[x]];
      ++all[g[x]];
    }
  }
  // The grey level below which a share q of a histogram's pixels lie; -1 for too few pixels.
  auto quantile = [](const int* h, double q) {
    int n = 0;
    for (int v = 0; v < 256; ++v)
      n += h[v];
    if (n < kProfileMinPixels)
      return -1.0;
    double seen = 0.0;
    for (int v = 0; v < 256; ++v) {
      seen += h[v];
      if (seen >= q * n)
        return double(v);
    }
    return 255.0;
  };
  const double level = quantile(all.data(), 0.5);
  if (level < 0.0)
    return;
  std::vector<float> offset(static_cast<std::size_t>(depths), static_cast<float>(level));
  std::vector<float> spread(static_cast<std::size_t>(depths), -1.0F), spreads;
  for (int k = 0; k < depths; ++k) {
    const int* h = &hist[static_cast<std::size_t>(k) * 256];
    const double m = quantile(h, 0.5);
    if (m < 0.0)
      continue;  // too few pixels at this depth: left as it is
    offset[static_cast<std::size_t>(k)] = static_cast<float>(m);
    spread[static_cast<std::size_t>(k)] = static_cast<float>(quantile(h, 0.75) - quantile(h, 0.25));
    spreads.push_back(spread[static_cast<std::size_t>(k)]);
  }
  if (spreads.empty())
    return;
  std::nth_element(spreads.begin(), spreads.begin() + spreads.size() / 2, spreads.end());
  const double typical = spreads[spreads.size() / 2];  // the typical depth's spread
  std::vector<float> gain(static_cast<std::size_t>(depths), 1.0F);
  for (std::size_t k = 0; k < gain.size(); ++k) {
    if (spread[k] == 0.0F)
      gain[k] = static_cast<float>(kProfileMaxGain);
    else if (spread[k] > 0.0F)
      gain[k] =
          static_cast<float>(std::clamp(typical / spread[k], kProfileMinGain, kProfileMaxGain));
  }
  // Smoothed over depth: a bin's quantiles are whole grey levels, and a step in gain from one
  // depth to the next would cut a bright layer crossing it into pieces.
  cv::Mat gain_row(1, depths, CV_32F, gain.data()), offset_row(1, depths, CV_32F, offset.data());
  cv::blur(gain_row, gain_row, cv::Size(2 * kGainSmooth_px + 1, 1), cv::Point(-1, -1),
           cv::BORDER_REPLICATE);
  cv::blur(offset_row, offset_row, cv::Size(2 * kLevelSmooth_px + 1, 1), cv::Point(-1, -1),
           cv::BORDER_REPLICATE);
  for (int y = 0; y < grey32->rows; ++y) {
    float* g = grey32->ptr<float>(y);
    const int* d = depth.ptr<int>(y);
    for (int x = 0; x < grey32->cols; ++x) {
      if (d[x] < 0)
        continue;
      const auto k = static_cast<std::size_t>(d[x]);
      g[x] = static_cast<float>(level) + gain[k] * (g[x] - offset[k]);
    }
  }
}

/// Step 5: contrast, side symmetry, coherence and evidence of a candidate segment. The side bands
/// leave out what lies outside a bounded imaging region: the black beyond a fan's face is no
/// tissue, and beside a shaft just inserted under the face it would read as an interface's dark
/// side.
void measureCues(const RidgeMap& ridge, const ImagingRegion& region, Candidate* c, double sigma) {
  double on = 0, a = 0, b = 0, a2 = 0, b2 = 0, aligned = 0, ridge_px = 0, a_depth = 0;
  int count = 0, band_a = 0, band_b = 0;
  auto inside = [&](cv::Point2d q) { return !region.bounded() || region.insetAt(q) >= 1.0F; };
  const double lo = kBandInnerSigmas * sigma, hi = kBandOuterSigmas * sigma;
  for (double t = c->t0; t <= c->t1; t += 1.0) {
    const cv::Point2d p = at(c->line, t), n = normal(c->line, t), d = tangent(c->line, t);
    const double line_angle = std::atan2(d.y, d.x);
    a_depth += n.y;  // > 0: side a (p + o n) lies deeper than side b
    on += sample(ridge.smooth, p);
    ++count;
    for (double o = lo; o <= hi; o += 1.0) {
      if (inside(p + o * n)) {
        const double va = sample(ridge.smooth, p + o * n);
        a += va, a2 += va * va, ++band_a;
      }
      if (inside(p - o * n)) {
        const double vb = sample(ridge.smooth, p - o * n);
        b += vb, b2 += vb * vb, ++band_b;
      }
    }
    if (sample(ridge.strength, p) > ridge.threshold) {
      double dt = std::abs(ridgeDirection(ridge, p) - line_angle);
      dt = std::fmod(dt, kPi);
      dt = std::min(dt, kPi - dt);
      aligned += dt < kAlignedTolerance_rad ? 1.0 : 0.0;
      ridge_px += 1.0;
    }
  }
  if (count == 0 || band_a + band_b == 0)
    return;
  on /= count;
  // A side wholly outside the region (a shaft along its boundary) takes the other's values.
  const double ma = band_a > 0 ? a / band_a : b / band_b, mb = band_b > 0 ? b / band_b : ma;
  const double va = band_a > 0 ? a2 / band_a - ma * ma : b2 / band_b - mb * mb;
  const double vb = band_b > 0 ? b2 / band_b - mb * mb : va;
  const double var = 0.5 * (va + vb);
  const double noise = std::sqrt(std::max(var, 1.0));
  NeedleSegment& s = c->cues;
  s.contrast = on - 0.5 * (ma + mb);
  s.symmetry = (std::min(ma, mb) + 1.0) / (std::max(ma, mb) + 1.0);
  s.coherence = ridge_px > 0 ? aligned / ridge_px : 0.0;
  const double length = c->t1 - c->t0;
  s.evidence = s.contrast / noise * std::sqrt(std::max(length, 0.0) / (4.0 * sigma));
  c->score = s.evidence * std::pow(s.symmetry, kSymmetryPower) * s.coherence;
  const bool shadow_below = (a_depth > 0.0) == (ma < mb);
  c->acceptance = shadow_below
                      ? s.evidence * std::pow(s.symmetry, kShadowSymmetryPower) * s.coherence
                      : c->score;
}

/// The margin of a bounded imaging region that counts as its border [px]: the ridge left out
/// near it (kRegionInsetSigmas) and kBorderMargin_px more.
double regionMargin(double sigma) {
  return kRegionInsetSigmas * sigma + kBorderMargin_px;
}

/// Whether p lies within kBorderMargin_px of the frame's border, or within regionMargin of a
/// bounded imaging region's boundary.
bool onBorder(cv::Point2d p, const ImagingRegion& region, double sigma) {
  const cv::Size size = region.inset.size();
  return p.x < kBorderMargin_px || p.y < kBorderMargin_px ||
         p.x > size.width - 1 - kBorderMargin_px || p.y > size.height - 1 - kBorderMargin_px ||
         (region.bounded() && region.insetAt(p) < regionMargin(sigma));
}

/// Distance from p along dir to the frame's border, or to a bounded region's (regionMargin).
double rayToBorder(cv::Point2d p, cv::Point2d dir, const ImagingRegion& region, double sigma) {
  const cv::Size size = region.inset.size();
  double t = 1e9;
  if (dir.x > 1e-9)
    t = std::min(t, (size.width - 1 - p.x) / dir.x);
  if (dir.x < -1e-9)
    t = std::min(t, -p.x / dir.x);
  if (dir.y > 1e-9)
    t = std::min(t, (size.height - 1 - p.y) / dir.y);
  if (dir.y < -1e-9)
    t = std::min(t, -p.y / dir.y);
  if (region.bounded()) {
    for (double u = 0.0; u < t; u += 2.0) {
      if (region.insetAt(p + u * dir) < regionMargin(sigma)) {
        t = u;
        break;
      }
    }
  }
  return std::max(t, 0.0);
}

/// Step 6: orient the segment tail -> tip from the entry side.
void orientByEntry(const Candidate& c, const AcquisitionOptions& o, const ImagingRegion& region,
                   NeedleSegment* s) {
  cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  bool a_is_tail = true;
  const double sigma = o.ridge_sigma_px;
  switch (o.entry) {
    case EntrySide::kLeft:
      a_is_tail = a.x < b.x;
      break;
    case EntrySide::kRight:
      a_is_tail = a.x > b.x;
      break;
    case EntrySide::kTop:
      a_is_tail = a.y < b.y;
      break;
    case EntrySide::kBottom:
      a_is_tail = a.y > b.y;
      break;
    case EntrySide::kAuto: {
      // The needle comes in from the border its shaft points to: the end with the shorter
      // way out along the shaft (its tangent there, for an arc) is the entry.
      if (c.line.kappa == 0.0) {
        const cv::Point2d d = (b - a) / std::max(cv::norm(b - a), 1e-9);
        a_is_tail = rayToBorder(a, -d, region, sigma) <= rayToBorder(b, d, region, sigma);
      } else {
        a_is_tail = rayToBorder(a, -tangent(c.line, c.t0), region, sigma) <=
                    rayToBorder(b, tangent(c.line, c.t1), region, sigma);
      }
      break;
    }
  }
  // The priors outrank the side: the end nearer the stated entry point is the tail, and the
  // shaft points the stated way.
  if (o.entry_point_px) {
    a_is_tail = cv::norm(a - *o.entry_point_px) <= cv::norm(b - *o.entry_point_px);
  } else if (o.entry_angle_rad) {
    a_is_tail =
        (b - a).dot(cv::Point2d(std::cos(*o.entry_angle_rad), std::sin(*o.entry_angle_rad))) >= 0.0;
  }
  {
    const cv::Point2d ta = a_is_tail ? a : b, tb = a_is_tail ? b : a;
    const cv::Point2d d = (ta - tb) / std::max(cv::norm(ta - tb), 1e-9);
    s->entry_gap_px = rayToBorder(ta, d, region, sigma);
  }
  s->tail_px = a_is_tail ? a : b;
  s->tip_px = a_is_tail ? b : a;
  s->angle_rad = std::atan2(s->tip_px.y - s->tail_px.y, s->tip_px.x - s->tail_px.x);
  s->curvature_per_px = 0.0;
  if (c.line.kappa != 0.0) {
    const cv::Point2d d = a_is_tail ? tangent(c.line, c.t1) : -tangent(c.line, c.t0);
    s->angle_rad = std::atan2(d.y, d.x);
    s->curvature_per_px = a_is_tail ? c.line.kappa : -c.line.kappa;
  }
}

/// Cross-line contrast at p: the smoothed frame on the line minus its mean in the side bands.
double crossContrast(const RidgeMap& ridge, cv::Point2d p, cv::Point2d n, double sigma) {
  double side = 0;
  int count = 0;
  for (double o = kBandInnerSigmas * sigma; o <= kBandOuterSigmas * sigma; o += 1.0) {
    side += sample(ridge.smooth, p + o * n) + sample(ridge.smooth, p - o * n);
    count += 2;
  }
  // The line's own value: the brightest within the ridge filter's reach across it (the fitted
  // line may sit a pixel or two off the shaft's centre towards the tip).
  const int reach = std::max(1, static_cast<int>(std::lround(kNearLineSigmas * sigma)));
  float on = 0.0F;
  for (int k = -reach; k <= reach; ++k)
    on = std::max(on, sample(ridge.smooth, p + k * n));
  return on - side / std::max(count, 1);
}

/// Step 6 (tip): walking from the tail, the needle ends where its cross-line contrast stays
/// below kTipLevel of the shaft's level for more than max_gap (a faint
/// streak beyond the tip passes the ridge threshold but not this).
void tipAtHalfLevel(const RidgeMap& ridge, double sigma, double max_gap, const Candidate& cand,
                    NeedleSegment* s) {
  // The shaft from the tail towards the tip: straight, or the candidate's arc walked from
  // whichever end is the tail.
  Line path;
  double length = cv::norm(s->tip_px - s->tail_px);
  if (cand.line.kappa == 0.0) {
    if (length < 1.0)
      return;
    path = {s->tail_px, (s->tip_px - s->tail_px) / length, 0.0};
  } else {
    const bool from_t0 = cv::norm(s->tail_px - at(cand.line, cand.t0)) < 0.5;
    length = cand.t1 - cand.t0 + kArcTipBeyondGaps * max_gap;
    path = {s->tail_px, from_t0 ? tangent(cand.line, cand.t0) : -tangent(cand.line, cand.t1),
            s->curvature_per_px};
  }
  std::vector<double> c;
  for (double u = 0; u <= length; u += 1.0)
    c.push_back(crossContrast(ridge, at(path, u), normal(path, u), sigma));
  std::vector<double> smooth(c.size());
  for (std::size_t i = 0; i < c.size(); ++i) {
    const std::size_t a = i < 2 ? 0 : i - 2, b = std::min(c.size() - 1, i + 2);
    double sum = 0;
    for (std::size_t k = a; k <= b; ++k)
      sum += c[k];
    smooth[i] = sum / static_cast<double>(b - a + 1);
  }
  const std::size_t traced = std::min(
      smooth.size(),
      static_cast<std::size_t>(cand.line.kappa == 0.0 ? smooth.size() : cand.t1 - cand.t0 + 1.0));
  std::vector<double> sorted(smooth.begin(), smooth.begin() + static_cast<long>(traced));
  const auto k = static_cast<long>(kShaftLevelQuantile * static_cast<double>(sorted.size() - 1));
  std::nth_element(sorted.begin(), sorted.begin() + k, sorted.end());
  const double half = kTipLevel * sorted[static_cast<std::size_t>(k)];
  if (half <= 0)
    return;
  double last = 0;
  if (path.kappa != 0.0) {
    // An arc traced on past the tail (across a reverberation copy or the shadow's edge): the
    // needle is the run above the level (gaps up to max_gap bridged) with the most contrast.
    double best = 0, sum = 0, start = 0, best_start = 0, on = -1e9;
    for (std::size_t i = 0; i < smooth.size(); ++i) {
      const double u = static_cast<double>(i);
      if (smooth[i] < half && i >= traced)
        break;  // past the traced end: only while the contrast holds, no gap bridged
      if (smooth[i] < half)
        continue;
      if (u - on > max_gap)
        sum = 0, start = u;
      sum += smooth[i];
      on = u;
      if (sum > best)
        best = sum, best_start = start, last = u;
    }
    s->tail_px = at(path, best_start);
    s->tip_px = at(path, last);
    const cv::Point2d d = tangent(path, last);
    s->angle_rad = std::atan2(d.y, d.x);
    return;
  }
  // The trace may start on a speckle ridge in line before the shaft: the walk starts
  // where the contrast first reaches the level, and the tail moves there.
  std::size_t first = 0;
  while (first < smooth.size() && smooth[first] < half)
    ++first;
  if (first == smooth.size())
    return;
  last = static_cast<double>(first);
  for (std::size_t i = first; i < smooth.size(); ++i) {
    const double u = static_cast<double>(i);
    if (u - last > max_gap)
      break;
    if (smooth[i] >= half)
      last = u;
  }
  s->tail_px = at(path, static_cast<double>(first));
  s->tip_px = at(path, last);
}

/// Step 4 for a needle of constant curvature (options.radius_px): from the straight fit (about
/// the chord of the visible part), an arc of that radius bending either way, each refit to the
/// ridge and traced again; the way that traces more ridge wins.
bool bendToArc(const RidgeMap& ridge, const AcquisitionOptions& o, Candidate* c) {
  double best_strength = 0.0;
  Candidate best = *c;
  for (const double sign : {1.0, -1.0}) {
    Candidate arc = *c;
    const double tm = 0.5 * (arc.t0 + arc.t1);
    arc.line = {at(c->line, tm), c->line.dir, sign / o.radius_px};
    arc.t0 -= tm;
    arc.t1 -= tm;
    double strength = 0.0;
    bool ok = true;
    for (int pass = 0; pass < 3 && ok; ++pass) {
      arc.line = refitArc(ridge, arc.line, arc.t0, arc.t1, o.ridge_sigma_px);
      ok = traceSegment(ridge, arc.line, o.ridge_sigma_px, o.max_gap_px, &arc.t0, &arc.t1,
                        &strength);
    }
    if (ok && strength > best_strength) {
      best_strength = strength;
      best = arc;
    }
  }
  *c = best;
  return best_strength > 0.0;
}

/// Whether the candidate never leaves the band of kEdgeBand_px along a bounded region's boundary.
bool hugsRegionEdge(const Candidate& c, const ImagingRegion& region) {
  if (!region.bounded())
    return false;
  for (double t = c.t0; t <= c.t1; t += 2.0) {
    if (region.insetAt(at(c.line, t)) > kEdgeBand_px)
      return false;
  }
  return true;
}

/// Whether, in a fan, both ends of the candidate come within kThroughReach of the fan's width
/// from its boundary along the shaft: a structure crossing the image (a tissue interface
/// spanning the fan), not a needle, whose tip lies well inside the image. (In a linear probe's
/// rectangle a shallow needle from the side can come that close at both ends: the recorded
/// in-vitro frames' tip error went from 6.5 to 11.8 px median with this rule there.)
bool runsThroughRegion(const Candidate& c, const ImagingRegion& region, double sigma) {
  if (region.shape != ImagingRegion::Shape::kSector)
    return false;
  const double reach = kThroughReach * region.box.width;
  const cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  return rayToBorder(a, -tangent(c.line, c.t0), region, sigma) < reach &&
         rayToBorder(b, tangent(c.line, c.t1), region, sigma) < reach;
}

/// Whether, in a fan with a curved probe face, the candidate reaches the fan from deeper than
/// kMaxEntryDepth of the fan's depth: its entry end's way out along the shaft meets the fan's
/// boundary there. A needle inserted through the skin beside the probe reaches the fan through
/// the face or the upper part of its straight edges; a deep interface meets the edge deep.
bool entersDeep(const Candidate& c, const ImagingRegion& region, const AcquisitionOptions& o) {
  if (region.shape != ImagingRegion::Shape::kSector || region.top_radius_px <= 0.0 ||
      o.entry != EntrySide::kAuto || o.entry_point_px)
    return false;
  const double sigma = o.ridge_sigma_px;
  const cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  const cv::Point2d da = -tangent(c.line, c.t0), db = tangent(c.line, c.t1);
  const double ra = rayToBorder(a, da, region, sigma), rb = rayToBorder(b, db, region, sigma);
  const cv::Point2d hit = ra <= rb ? a + ra * da : b + rb * db;
  const double depth = cv::norm(hit - region.apex_px) - region.top_radius_px;
  const double fan_depth =
      region.box.y + region.box.height - region.apex_px.y - region.top_radius_px;
  return depth > kMaxEntryDepth * fan_depth;
}

/// The two ends of the probe face of a fan: with a curved face, the outermost points of its arc
/// with the region just below them; with a face too small or too flat to fit an arc (a phased
/// array), the ends of the fan's top row. False outside a fan.
bool faceEnds(const ImagingRegion& region, double sigma, cv::Point2d* left, cv::Point2d* right) {
  if (region.shape != ImagingRegion::Shape::kSector)
    return false;
  const double margin = regionMargin(sigma) + 2.0;
  if (region.top_radius_px <= 0.0) {
    const int row = std::min(region.box.y + cvRound(margin), region.inset.rows - 1);
    int lo = region.inset.cols, hi = -1;
    for (int x = 0; x < region.inset.cols; ++x) {
      if (region.inset.at<float>(row, x) > 0.0F)
        lo = std::min(lo, x), hi = std::max(hi, x);
    }
    if (hi < lo)
      return false;
    *left = cv::Point2d(lo, region.box.y);
    *right = cv::Point2d(hi, region.box.y);
    return true;
  }
  const double r = region.top_radius_px, below = r + margin;
  double lo = 1e9, hi = -1e9;
  for (double phi = -0.5 * kPi; phi <= 0.5 * kPi; phi += 1.0 / below) {
    const cv::Point2d u(std::sin(phi), std::cos(phi));
    if (region.insetAt(region.apex_px + below * u) > 0.0F)
      lo = std::min(lo, phi), hi = std::max(hi, phi);
  }
  if (hi < lo)
    return false;
  *left = region.apex_px + r * cv::Point2d(std::sin(lo), std::cos(lo));
  *right = region.apex_px + r * cv::Point2d(std::sin(hi), std::cos(hi));
  return true;
}

/// Whether, in a fan, the candidate traced back from its entry end (the
/// end with the shorter way out, as orientByEntry takes it) rises to the skin, the row of the
/// face's ends, within kSkinReach of the fan's width beside the face. A needle inserted through
/// the skin goes deeper as it advances, and punctures the skin beside the probe or under its
/// face; a line that does not rise towards its entry end, or one so shallow that it meets the
/// skin far from the probe, is a tissue interface.
bool reachesSkin(const Candidate& c, const ImagingRegion& region, const AcquisitionOptions& o) {
  cv::Point2d left, right;
  if (o.entry != EntrySide::kAuto || o.entry_point_px ||
      !faceEnds(region, o.ridge_sigma_px, &left, &right))
    return true;
  const double sigma = o.ridge_sigma_px;
  const cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  const cv::Point2d da = -tangent(c.line, c.t0), db = tangent(c.line, c.t1);
  const bool a_is_tail = rayToBorder(a, da, region, sigma) <= rayToBorder(b, db, region, sigma);
  const cv::Point2d tail = a_is_tail ? a : b, back = a_is_tail ? da : db;
  const double skin_row = std::max(left.y, right.y);
  double x = tail.x;
  if (tail.y > skin_row) {
    if (back.y >= -1e-6)
      return false;  // the shaft does not rise towards its entry end
    x = tail.x + back.x * (skin_row - tail.y) / back.y;
  }
  const double reach = kSkinReach * region.box.width;
  return x >= std::min(left.x, right.x) - reach && x <= std::max(left.x, right.x) + reach;
}

/// Whether the candidate is strong enough to be the needle: its acceptance reaches
/// options.min_evidence; a shaft anchored at the fan's entry (oriented: its cues' entry_gap_px
/// set) needs kAnchoredEvidence of it, its side symmetry counted as the shadow's
/// (kShadowSymmetryPower: the face's band and the shaft's shadow both brighten one side).
bool strongEnough(const Candidate& c, const AcquisitionOptions& o, const ImagingRegion& region) {
  cv::Point2d left, right;
  const NeedleSegment& s = c.cues;
  const bool anchored = o.entry == EntrySide::kAuto && !o.entry_point_px &&
                        faceEnds(region, o.ridge_sigma_px, &left, &right) &&
                        s.entry_gap_px <= kAnchoredGap_px && s.coherence >= kAnchoredCoherence;
  if (anchored)
    return s.evidence * std::pow(s.symmetry, kShadowSymmetryPower) * s.coherence >=
           kAnchoredEvidence * o.min_evidence;
  return c.acceptance >= o.min_evidence;
}

/// In a fan (auto entry, no entry point), the way from the candidate's upper end out to the
/// fan's boundary along the shaft when it is at most kAnchoredGap_px: the part of a shaft just
/// inserted that the probe face's band hides, counted in its length; else 0.
double anchoredGap(const Candidate& c, const AcquisitionOptions& o, const ImagingRegion& region) {
  cv::Point2d left, right;
  if (o.entry != EntrySide::kAuto || o.entry_point_px ||
      !faceEnds(region, o.ridge_sigma_px, &left, &right))
    return 0.0;
  const cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  const bool a_up = a.y < b.y;
  const cv::Point2d up = a_up ? a : b, out = a_up ? -tangent(c.line, c.t0) : tangent(c.line, c.t1);
  const double gap = rayToBorder(up, out, region, o.ridge_sigma_px);
  return gap <= kAnchoredGap_px ? gap : 0.0;
}

/// In a fan (auto entry, no entry point), for a candidate that never leaves the edge band
/// (kEdgeBand_px): the length of its line from its shallower end back out of the fan, when it
/// enters the fan across the boundary; else 0. It enters when its shallower end lies in the strip
/// along the boundary (kEnterStrip_px beyond the ridge left out there), it goes deeper along its
/// length at kEnterMinAngle_rad or more (the region's own edge runs along the boundary: along a
/// straight side its depth does not change, along the face's arc its chords and tangents deepen
/// at both ends or only near one, never steadily), its midpoint halfway in depth
/// (kEnterMidShare either way), and kEnterMinTraced_px of it is traced. A needle inserted
/// beside the end of a convex probe meets the face at 5-15 degrees: for its first tens of
/// pixels it stays within the strip and the face's ring-down band, and only its deeper part is
/// traced; the hidden part, up to kEntryZone_px, counts in its length.
double entersAcrossEdge(const Candidate& c, const AcquisitionOptions& o,
                        const ImagingRegion& region) {
  cv::Point2d left, right;
  if (!o.entry_across_edge || o.entry != EntrySide::kAuto || o.entry_point_px ||
      !faceEnds(region, o.ridge_sigma_px, &left, &right) || c.t1 - c.t0 < kEnterMinTraced_px)
    return 0.0;
  const double i0 = region.insetAt(at(c.line, c.t0)), i1 = region.insetAt(at(c.line, c.t1));
  const double mid = region.insetAt(at(c.line, 0.5 * (c.t0 + c.t1)));
  const double lo = std::min(i0, i1), rise = std::abs(i1 - i0);
  const bool steady =
      mid >= lo + (0.5 - kEnterMidShare) * rise && mid <= lo + (0.5 + kEnterMidShare) * rise;
  if (lo > regionMargin(o.ridge_sigma_px) + kEnterStrip_px ||
      rise < std::sin(kEnterMinAngle_rad) * (c.t1 - c.t0) || !steady)
    return 0.0;
  const bool a_low = i0 <= i1;
  const cv::Point2d p = a_low ? at(c.line, c.t0) : at(c.line, c.t1);
  const cv::Point2d out = a_low ? -tangent(c.line, c.t0) : tangent(c.line, c.t1);
  double u = 0.0;
  while (u < kEntryZone_px && region.insetAt(p + u * out) >= 1.0F)
    u += 1.0;
  return std::max(u, 1.0);
}

/// Whether the candidate agrees with the priors (kPriorPoint_px, kPriorAngle_rad); true without.
bool meetsPriors(const Candidate& c, const AcquisitionOptions& o) {
  if (o.entry_angle_rad) {
    const cv::Point2d d = tangent(c.line, 0.5 * (c.t0 + c.t1));
    double da = std::abs(std::atan2(d.y, d.x) - *o.entry_angle_rad);
    da = std::fmod(da, kPi);
    if (std::min(da, kPi - da) > kPriorAngle_rad)
      return false;
  }
  if (o.entry_point_px) {
    const cv::Point2d e = *o.entry_point_px;
    const Line& l = c.line;
    const cv::Point2d n(-l.dir.y, l.dir.x);
    const double off =
        l.kappa == 0.0 ? std::abs((e - l.point).dot(n))
                       : std::abs(cv::norm(e - (l.point + n / l.kappa)) - 1.0 / std::abs(l.kappa));
    if (off > kPriorPoint_px)
      return false;
  }
  return true;
}

/// Marks the traced segment of c in `traced` (CV_8U), kNearLineSigmas filter scales either side.
void markTraced(const Candidate& c, double sigma, cv::Mat* traced) {
  const int thickness = 2 * static_cast<int>(std::ceil(kNearLineSigmas * sigma)) + 1;
  const double step = c.line.kappa == 0.0 ? c.t1 - c.t0 : 8.0;
  for (double t = c.t0; t < c.t1; t += step) {
    cv::line(*traced, at(c.line, t), at(c.line, std::min(t + step, c.t1)), cv::Scalar(255),
             thickness);
  }
}

/// Steps 4-5 for one Hough line: trace, refit, trace again, measure. The traced segment (also of
/// a line then ruled out) is marked in `traced`.
std::optional<Candidate> examine(const RidgeMap& ridge, const Line& line,
                                 const AcquisitionOptions& o, const ImagingRegion& region,
                                 cv::Mat* traced) {
  Candidate c;
  c.line = line;
  if (!traceSegment(ridge, c.line, o.ridge_sigma_px, o.max_gap_px, &c.t0, &c.t1))
    return {};
  for (int pass = 0; pass < 2; ++pass) {
    c.line = refitLine(ridge, c.line, c.t0, c.t1, o.ridge_sigma_px);
    if (!traceSegment(ridge, c.line, o.ridge_sigma_px, o.max_gap_px, &c.t0, &c.t1))
      return {};
  }
  if (o.radius_px > 0.0 && !bendToArc(ridge, o, &c))
    return {};
  markTraced(c, o.ridge_sigma_px, traced);
  const bool in_band = hugsRegionEdge(c, region);
  const double entering = in_band ? entersAcrossEdge(c, o, region) : 0.0;
  if (c.t1 - c.t0 + std::max(anchoredGap(c, o, region), entering) < o.min_length_px)
    return {};
  // A line running from border to border has no tip in view: an interface, not a needle; nor
  // is the imaging region's own edge, nor a line the priors rule out.
  const double sigma = o.ridge_sigma_px;
  if (onBorder(at(c.line, c.t0), region, sigma) && onBorder(at(c.line, c.t1), region, sigma))
    return {};
  if ((in_band && entering == 0.0) || runsThroughRegion(c, region, sigma) ||
      entersDeep(c, region, o) || !reachesSkin(c, region, o) || !meetsPriors(c, o))
    return {};
  measureCues(ridge, region, &c, o.ridge_sigma_px);
  return c;
}

/// Step 4: whether segment (a, b) lies within the band of kSameStructure_px around segment
/// (ka, kb) (both ends near its line and within its span), in nearly its direction.
bool within(cv::Point2d a, cv::Point2d b, cv::Point2d ka, cv::Point2d kb) {
  const double length = cv::norm(kb - ka);
  if (length < 1.0)
    return false;
  const cv::Point2d d = (kb - ka) / length, n(-d.y, d.x);
  const cv::Point2d e = b - a;
  if (std::abs(e.dot(n)) > std::sin(kSameStructure_rad) * cv::norm(e))
    return false;
  for (const cv::Point2d& p : {a, b}) {
    const double along = (p - ka).dot(d);
    if (std::abs((p - ka).dot(n)) > kSameStructure_px || along < -kSameStructure_px ||
        along > length + kSameStructure_px)
      return false;
  }
  return true;
}

/// Step 4: adds c to `all` unless it is the same segment as one there (kSameSegment_px at both
/// ends, or lying along it: within()); of two the same, the better score stays (with `replace`;
/// without, the one there stays).
void keepDistinct(const Candidate& c, std::vector<Candidate>* all, bool replace = true) {
  const cv::Point2d a = at(c.line, c.t0), b = at(c.line, c.t1);
  for (Candidate& k : *all) {
    const cv::Point2d ka = at(k.line, k.t0), kb = at(k.line, k.t1);
    const bool straight = c.line.kappa == 0.0 && k.line.kappa == 0.0;
    const bool same = (cv::norm(a - ka) < kSameSegment_px && cv::norm(b - kb) < kSameSegment_px) ||
                      (cv::norm(a - kb) < kSameSegment_px && cv::norm(b - ka) < kSameSegment_px) ||
                      (straight && (within(a, b, ka, kb) || within(ka, kb, a, b)));
    if (same) {
      if (replace && c.score > k.score)
        k = c;
      return;
    }
  }
  all->push_back(c);
}

std::string summary(const NeedleSegment& s) {
  std::ostringstream out;
  out.precision(3);
  out << "needle " << s.length_px() << " px, tip (" << s.tip_px.x << ", " << s.tip_px.y
      << "), evidence " << s.evidence << ", symmetry " << s.symmetry << ", coherence "
      << s.coherence << ", gap " << s.entry_gap_px
      << (s.extended_by_motion ? ", tip moved on to the motion's front" : "");
  return out.str();
}

}  // namespace

std::string toString(EntrySide side) {
  switch (side) {
    case EntrySide::kLeft:
      return "left";
    case EntrySide::kRight:
      return "right";
    case EntrySide::kTop:
      return "top";
    case EntrySide::kBottom:
      return "bottom";
    case EntrySide::kAuto:
      break;
  }
  return "auto";
}

std::optional<EntrySide> entrySideFromString(const std::string& name) {
  for (EntrySide s : {EntrySide::kAuto, EntrySide::kLeft, EntrySide::kRight, EntrySide::kTop,
                      EntrySide::kBottom}) {
    if (toString(s) == name)
      return s;
  }
  return std::nullopt;
}

void AcquisitionOptions::validate() const {
  auto check = [](bool ok, const char* field, double v) {
    if (!ok) {
      throw std::invalid_argument(std::string("AcquisitionOptions.") + field + " = " +
                                  std::to_string(v) + " is out of range");
    }
  };
  check(std::isfinite(ridge_sigma_px) && ridge_sigma_px >= 0.5 && ridge_sigma_px <= 20,
        "ridge_sigma_px", ridge_sigma_px);
  check(std::isfinite(min_length_px) && min_length_px >= 5, "min_length_px", min_length_px);
  check(std::isfinite(max_gap_px) && max_gap_px >= 0, "max_gap_px", max_gap_px);
  check(std::isfinite(min_evidence) && min_evidence >= 0, "min_evidence", min_evidence);
  check(std::isfinite(radius_px) && (radius_px == 0 || radius_px >= min_length_px / kPi),
        "radius_px", radius_px);
  if (entry_point_px) {
    check(std::isfinite(entry_point_px->x), "entry_point_px.x", entry_point_px->x);
    check(std::isfinite(entry_point_px->y), "entry_point_px.y", entry_point_px->y);
  }
  if (entry_angle_rad)
    check(std::isfinite(*entry_angle_rad), "entry_angle_rad", *entry_angle_rad);
}

double NeedleSegment::length_px() const {
  return cv::norm(tip_px - tail_px);
}

cv::Mat toGrey8(const cv::Mat& frame, std::string* problem) {
  std::ostringstream why;
  cv::Mat grey;
  if (frame.empty()) {
    why << "empty frame";
  } else if (frame.depth() != CV_8U && frame.depth() != CV_16U) {
    why << "unsupported pixel depth (type " << frame.type() << ", " << frame.cols << " x "
        << frame.rows << "): need 8- or 16-bit";
  } else if (frame.channels() != 1 && frame.channels() != 3 && frame.channels() != 4) {
    why << "unsupported channel count " << frame.channels() << ": need 1, 3 or 4";
  } else {
    cv::Mat mono = frame;
    if (frame.channels() == 3)
      cv::cvtColor(frame, mono, cv::COLOR_BGR2GRAY);
    if (frame.channels() == 4)
      cv::cvtColor(frame, mono, cv::COLOR_BGRA2GRAY);
    if (mono.depth() == CV_16U) {
      double mx = 0;
      cv::minMaxLoc(mono, nullptr, &mx);
      mono.convertTo(grey, CV_8U, mx > 0 ? 255.0 / mx : 1.0);
    } else {
      grey = mono;
    }
  }
  if (problem)
    *problem = why.str();
  return grey;
}

NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options) {
  return acquireNeedle(frame, options, cv::Mat());
}

void keepFreedMemory() {
#ifdef __GLIBC__
  constexpr int kMmapThreshold = 256 << 20;  // blocks up to 256 MB come from the heap
  constexpr int kTrimThreshold = 512 << 20;  // the heap is trimmed only past 512 MB free
  mallopt(M_MMAP_THRESHOLD, kMmapThreshold);
  mallopt(M_TRIM_THRESHOLD, kTrimThreshold);
#endif
}

namespace {

/// Sequence cue of one oriented candidate: the signed motion map's mean over the tip end, which
/// runs on past the traced end by `beyond` px (the part the needle has just advanced into is the
/// faint, blurred end that the trace stops short of), less the unsigned map's mean along the rest
/// of the shaft. A needle advancing along its own axis brightens the tissue ahead of its tip while
/// its shaft stays in place; a flickering band changes along its whole length, and a line whose
/// end is an edge of a moving shadow darkens there: neither moves like a needle.
double tipMotion(const cv::Mat& motion, const NeedleSegment& s, double beyond) {
  const double length = s.length_px();
  if (motion.empty() || length < 1.0)
    return 0.0;
  const cv::Point2d d = (s.tip_px - s.tail_px) / length;
  const double zone = std::min(length, std::max(kMotionMinZone_px, kMotionTipZone * length));
  double tip = 0, shaft = 0;
  int tip_count = 0, shaft_count = 0;
  for (double u = 0.0; u <= length + beyond; u += 1.0) {
    const float v = sample(motion, s.tail_px + u * d);
    if (u >= length - zone) {
      tip += v;
      ++tip_count;
    } else {
      shaft += std::abs(v);
      ++shaft_count;
    }
  }
  return (tip_count > 0 ? tip / tip_count : 0.0) - (shaft_count > 0 ? shaft / shaft_count : 0.0);
}

/// Sequence cue past the estimated tip: the largest mean of the signed motion map over a window
/// of kAheadTo_px - kAheadFrom_px along the tip's direction, starting kAheadFrom_px to
/// kAheadReach_px - (kAheadTo_px - kAheadFrom_px) beyond the tip; 0 without a motion map. With
/// `front`, the distance beyond the tip of that window's far end.
double motionAhead(const cv::Mat& motion, const NeedleSegment& s, double* front = nullptr) {
  if (motion.empty())
    return 0.0;
  const cv::Point2d d(std::cos(s.angle_rad), std::sin(s.angle_rad));
  std::vector<double> v;
  for (double u = kAheadFrom_px; u <= kAheadReach_px; u += 1.0)
    v.push_back(sample(motion, s.tip_px + u * d));
  const auto window = static_cast<std::size_t>(kAheadTo_px - kAheadFrom_px + 1.0);
  double sum = 0.0, best = -1e9;
  for (std::size_t i = 0; i < v.size(); ++i) {
    sum += v[i];
    if (i + 1 < window)
      continue;
    if (i >= window)
      sum -= v[i - window];
    if (sum > best) {
      best = sum;
      if (front)
        *front = kAheadFrom_px + static_cast<double>(i);
    }
  }
  return best / static_cast<double>(window);
}

/// A brightening blob of the motion map: where a needle advancing along its own axis has just
/// gone (its echo and reverberation tail appear there) while the tissue around stays still.
struct MotionBlob {
  cv::Point2d front;       ///< its pixel farthest along its axis (away from the entry) at half peak
  cv::Point2d back;        ///< its extent back along its principal axis
  double dominance = 0.0;  ///< its share of the frame's brightening above the level
  double elongation = 0.0;  ///< sqrt of the principal moments' ratio
  double peak = 0.0;        ///< its largest motion value
  int area = 0;
};

std::optional<MotionBlob> motionBlob(const cv::Mat& motion, EntrySide entry) {
  if (motion.empty())
    return std::nullopt;
  const cv::Mat mask = motion > kBlobLevel;
  // Fragments of one change (the needle's echo and its reverberation copies, a few pixels
  // apart) are one blob: components of the mask dilated by kBlobJoin_px, summed over the mask.
  cv::Mat joined, labels;
  cv::dilate(mask, joined,
             cv::getStructuringElement(cv::MORPH_ELLIPSE,
                                       cv::Size(2 * kBlobJoin_px + 1, 2 * kBlobJoin_px + 1)));
  const int n = cv::connectedComponents(joined, labels, 8, CV_32S);
  if (n < 2)
    return std::nullopt;
  std::vector<double> sum(static_cast<std::size_t>(n), 0.0);
  std::vector<int> count(static_cast<std::size_t>(n), 0);
  for (int r = 0; r < labels.rows; ++r) {
    const int* l = labels.ptr<int>(r);
    const float* m = motion.ptr<float>(r);
    const std::uint8_t* in = mask.ptr<std::uint8_t>(r);
    for (int c = 0; c < labels.cols; ++c) {
      if (l[c] > 0 && in[c]) {
        sum[static_cast<std::size_t>(l[c])] += m[c];
        ++count[static_cast<std::size_t>(l[c])];
      }
    }
  }
  // Specks of noise (smaller than kBlobSpeck_px) are no change that competes with the blob.
  double total = 0.0;
  for (int k = 1; k < n; ++k)
    total += count[static_cast<std::size_t>(k)] >= kBlobSpeck_px ? sum[static_cast<std::size_t>(k)]
                                                                 : 0.0;
  const int best = static_cast<int>(std::max_element(sum.begin() + 1, sum.end()) - sum.begin());
  double w = 0, mx = 0, my = 0, sxx = 0, syy = 0, sxy = 0, peak = 0;
  int area = 0;
  std::vector<cv::Point> pts;
  for (int r = 0; r < labels.rows; ++r) {
    const int* l = labels.ptr<int>(r);
    const float* m = motion.ptr<float>(r);
    const std::uint8_t* in = mask.ptr<std::uint8_t>(r);
    for (int c = 0; c < labels.cols; ++c) {
      if (l[c] != best || !in[c])
        continue;
      w += m[c], mx += m[c] * c, my += m[c] * r;
      sxx += m[c] * c * c, syy += m[c] * r * r, sxy += m[c] * c * r;
      peak = std::max(peak, double(m[c]));
      ++area;
      pts.emplace_back(c, r);
    }
  }
  mx /= w, my /= w;
  const double cxx = sxx / w - mx * mx, cyy = syy / w - my * my, cxy = sxy / w - mx * my;
  const double phi = 0.5 * std::atan2(2 * cxy, cxx - cyy);
  const double tr = cxx + cyy, det = cxx * cyy - cxy * cxy;
  const double l1 = 0.5 * tr + std::sqrt(std::max(0.25 * tr * tr - det, 0.0));
  const double l2 = std::max(0.5 * tr - std::sqrt(std::max(0.25 * tr * tr - det, 0.0)), 1e-6);
  cv::Point2d d(std::cos(phi), std::sin(phi));
  // kAuto: the newest change (the front) is the strongest, the trail behind it fades with the
  // background's memory: the front is the side the weighted centroid leans to.
  double bulk = 0.0;
  for (const cv::Point& p : pts)
    bulk += (p.x - mx) * d.x + (p.y - my) * d.y;
  const bool flip =
      (entry == EntrySide::kLeft && d.x < 0) || (entry == EntrySide::kRight && d.x > 0) ||
      (entry == EntrySide::kTop && d.y < 0) || (entry == EntrySide::kBottom && d.y > 0) ||
      (entry == EntrySide::kAuto && bulk > 0);
  if (flip)
    d = -d;
  MotionBlob b;
  double lo = 1e18, hi = -1e18;
  double half_hi = -1e18;
  for (const cv::Point& p : pts) {
    const double u = (p.x - mx) * d.x + (p.y - my) * d.y;
    hi = std::max(hi, u);
    lo = std::min(lo, u);
    // The front: the blob's pixel farthest along at half its peak or more (half the height of
    // a blurred edge is the edge).
    if (motion.at<float>(p) >= 0.5 * peak && u > half_hi) {
      half_hi = u;
      b.front = cv::Point2d(p.x, p.y);
    }
  }
  b.back = cv::Point2d(mx, my) + lo * d;
  b.dominance = total > 0 ? sum[static_cast<std::size_t>(best)] / total : 0.0;
  b.elongation = std::sqrt(l1 / l2);
  b.peak = peak;
  b.area = area;
  return b;
}

/// How far along from + u dir (u in [0, reach]) the brightening goes: the last u where the motion
/// map is at least half its largest value on the way (half the height of a blurred edge is the
/// edge); -1 if nothing brightens.
double motionFront(const cv::Mat& motion, cv::Point2d from, cv::Point2d dir, double reach) {
  std::vector<float> v;
  for (double u = 0.0; u <= reach; u += 1.0)
    v.push_back(sample(motion, from + u * dir));
  const float peak = v.empty() ? 0.0F : *std::max_element(v.begin(), v.end());
  if (peak <= 0.0F)
    return -1.0;
  for (std::size_t i = v.size(); i-- > 0;) {
    if (v[i] >= 0.5F * peak)
      return static_cast<double>(i);
  }
  return -1.0;
}

/// A line's tip traced short of where the needle is (the ridge fades, or the shaft runs into a
/// layer's glare) while the frame's one brightening blob lies ahead on the line: the tip moves on
/// along the line to the motion's front.
void extendToMotionFront(const cv::Mat& motion, const NeedleSegment& blob, NeedleSegment* s) {
  const cv::Point2d d(std::cos(s->angle_rad), std::sin(s->angle_rad)), n(-d.y, d.x);
  const double ahead = (blob.tip_px - s->tip_px).dot(d);
  if (ahead < kBlobAhead_px || std::abs((blob.tip_px - s->tip_px).dot(n)) > kBlobOnLine_px)
    return;
  const double u = motionFront(motion, s->tip_px, d, ahead + kBlobAhead_px);
  if (u < kBlobAhead_px)
    return;
  s->tip_px += u * d;
  s->extended_by_motion = true;
}

/// Step 6 without a moving line: a dominant, strong brightening blob (kBlobDominance of the
/// frame's brightening, peak kBlobPeak, at least kBlobMinArea_px pixels) is where a needle has
/// just advanced while nothing else changed: its tip is the blob's front along its principal axis.
/// A needle inside a saturated layer or a shadow shows no line, but its tip still brightens the
/// pixels it reaches (its echo, its reverberation tail). Tissue that moves (a hand-held probe,
/// a deforming phantom: the recorded frames' largest blob holds 0.2-0.7 of the brightening)
/// spreads the change over the frame and gives nothing here.
std::optional<NeedleSegment> tipFromMotion(const cv::Mat& motion, EntrySide entry,
                                           double min_dominance = kBlobDominance) {
  const std::optional<MotionBlob> b = motionBlob(motion, entry);
  if (!b || b->dominance < min_dominance || b->peak < kBlobPeak || b->area < kBlobMinArea_px)
    return std::nullopt;
  NeedleSegment s;
  s.found = true;
  s.from_motion = true;
  s.tail_px = b->back;
  s.tip_px = b->front;
  s.angle_rad = std::atan2(b->front.y - b->back.y, b->front.x - b->back.x);
  s.motion = b->peak;
  std::ostringstream out;
  out.precision(3);
  out << "tip from the motion alone (no moving line): tip (" << s.tip_px.x << ", " << s.tip_px.y
      << "), blob " << b->area << " px holding " << b->dominance << " of the change";
  s.message = out.str();
  return s;
}

/// Step 6 with the sequence cue: orient every candidate, measure its motion; when one that
/// passes the evidence threshold moves, the still ones drop out (never a still line over a
/// moving needle); the best score wins.
std::optional<Candidate> bestCandidate(std::vector<Candidate>& all, const AcquisitionOptions& o,
                                       const ImagingRegion& region, const cv::Mat& motion) {
  bool any_moving = false;
  // A tip on the frame's border is no tip in view: the line runs on out of the frame (a layer
  // seen from the stated entry side, or a needle past the field of view).
  all.erase(std::remove_if(all.begin(), all.end(),
                           [&](Candidate& c) {
                             orientByEntry(c, o, region, &c.cues);
                             if (onBorder(c.cues.tip_px, region, o.ridge_sigma_px))
                               return true;
                             c.cues.motion =
                                 tipMotion(motion, c.cues, kMotionBeyondGaps * o.max_gap_px);
                             return false;
                           }),
            all.end());
  for (const Candidate& c : all)
    any_moving = any_moving || (c.cues.motion >= kMinMotionRatio && c.acceptance >= o.min_evidence);
  std::optional<Candidate> best;
  for (const Candidate& c : all) {
    if (any_moving && c.cues.motion < kMinMotionRatio)
      continue;
    if (!best || c.score > best->score)
      best = c;
  }
  return best;
}

/// Steps 3-5 on one ridge map: its Hough lines examined until kMaxCandidates distinct ones.
void examineLines(const RidgeMap& votes, const RidgeMap& ridge, const AcquisitionOptions& o,
                  const ImagingRegion& region, std::vector<Candidate>* all, cv::Mat* traced,
                  bool replace = true) {
  const std::vector<Line> lines = candidateLines(votes, o.min_length_px);
  for (const Line& line : lines) {
    if (static_cast<int>(all->size()) >= kMaxCandidates)
      return;
    if (std::optional<Candidate> c = examine(ridge, line, o, region, traced))
      keepDistinct(*c, all, replace);
  }
}

/// Step 3, in a fan (auto entry, no entry point), when neither round found a candidate strong
/// enough: a round of its own over the entry zone, the part of the fan within kEntryZone_px of its
/// boundary and no deeper than kMaxEntryDepth of it. A needle inserted through the skin beside the
/// probe enters the fan there (through the face or the upper part of a straight edge); just
/// inserted, its shaft is short and lies in the face's ring-down band, and among the whole fan's
/// strongest ridge pixels (the long interfaces, the speckle) it casts no Hough line. Over the zone
/// alone, its thresholds taken from the zone's ridge, it does; each line is then traced along the
/// whole fan at the zone's thresholds and judged by the same rules. A structure the whole fan's
/// rounds found keeps their trace: at the zone's lower thresholds a shaft's trace runs on along
/// the speckle past its tip.
void examineEntryZone(const RidgeMap& ridge, const AcquisitionOptions& o,
                      const ImagingRegion& region, std::vector<Candidate>* all, cv::Mat* traced) {
  cv::Point2d left, right;
  if (o.entry != EntrySide::kAuto || o.entry_point_px ||
      !faceEnds(region, o.ridge_sigma_px, &left, &right))
    return;
  cv::Mat zone = region.mask & (region.inset <= kEntryZone_px);
  const int deep = region.box.y + static_cast<int>(kMaxEntryDepth * region.box.height);
  if (deep < zone.rows)
    zone.rowRange(std::max(deep, 0), zone.rows).setTo(0);
  if (cv::countNonZero(zone) == 0)
    return;
  RidgeMap votes = ridge, trace = ridge;
  votes.strength = cv::Mat(ridge.strength.size(), CV_32F, cv::Scalar(0));  // a buffer of its own
  ridge.strength.copyTo(votes.strength, zone);
  ridgeThresholds(&votes, zone);
  trace.threshold = votes.threshold;
  trace.hough_threshold = votes.hough_threshold;
  examineLines(votes, trace, o, region, all, traced, false);
}

/// Steps 3-5 in two rounds. A few long bright structures (tissue interfaces) hold most of the
/// strongest few percent of ridge pixels: the thresholds then lie above a fainter needle's ridge,
/// which casts no Hough line (convex frames with two bright layers: a shaft plain to see had no
/// line in any frame). When the first round leaves no candidate strong enough to be the needle,
/// the second leaves out what the first traced, takes the thresholds from the ridge that remains
/// and examines its Hough lines the same way. (Always run, its lower thresholds let a chance
/// line of speckle outrank a needle whose own shadow darkens one side.)
std::vector<Candidate> collectCandidates(const RidgeMap& ridge, const AcquisitionOptions& o,
                                         const ImagingRegion& region) {
  std::vector<Candidate> all;
  cv::Mat traced(ridge.strength.size(), CV_8U, cv::Scalar(0));
  examineLines(ridge, ridge, o, region, &all, &traced);
  auto acceptable = [&] {
    return std::any_of(all.begin(), all.end(),
                       [&](const Candidate& c) { return c.acceptance >= o.min_evidence; });
  };
  if (acceptable() || static_cast<int>(all.size()) >= kMaxCandidates)
    return all;
  if (cv::countNonZero(traced) > 0) {
    RidgeMap rest = ridge;
    rest.strength = ridge.strength.clone();
    rest.strength.setTo(0.0F, traced);
    ridgeThresholds(&rest, region);
    examineLines(rest, rest, o, region, &all, &traced);
  }
  if (!acceptable() && o.entry_zone)
    examineEntryZone(ridge, o, region, &all, &traced);
  return all;
}

}  // namespace

NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options,
                            const cv::Mat& motion) {
  std::string problem;
  const cv::Mat grey = toGrey8(frame, &problem);
  return acquireNeedle(frame, options, motion, findImagingRegion(grey));
}

NeedleSegment acquireNeedle(const cv::Mat& frame, const AcquisitionOptions& options,
                            const cv::Mat& motion, const ImagingRegion& region) {
  NeedleSegment none;
  try {
    options.validate();
  } catch (const std::invalid_argument& e) {
    none.message = e.what();
    return none;
  }
  std::string problem;
  const cv::Mat grey = toGrey8(frame, &problem);  // step 1
  if (grey.empty()) {
    none.message = problem;
    return none;
  }
  if (!motion.empty() && (motion.size() != grey.size() || motion.type() != CV_32FC1)) {
    none.message = "motion map is not CV_32FC1 of the frame's size";
    return none;
  }
  if (region.inset.size() != grey.size()) {
    none.message = "imaging region is not of the frame's size";
    return none;
  }
  cv::Mat grey32;
  grey.convertTo(grey32, CV_32F);
  if (options.flatten_depth)
    flattenDepthProfile(grey, region, &grey32);
  RidgeMap ridge = ridgeFilter(grey32, options.ridge_sigma_px);  // step 2
  if (region.bounded())  // the region's own edge and the black outside it are no ridge
    ridge.strength.setTo(0.0F, region.inset < kRegionInsetSigmas * options.ridge_sigma_px);
  ridgeThresholds(&ridge, region);

  std::vector<Candidate> all = collectCandidates(ridge, options, region);  // steps 3-5
  const std::optional<Candidate> best = bestCandidate(all, options, region, motion);
  // No line moves like a needle: the tip where the frame alone brightens, if it does and the
  // best line does not end there (a line traced to that tip is kept: it shows the shaft).
  const std::optional<NeedleSegment> hidden = tipFromMotion(motion, options.entry);
  if (!best) {
    if (hidden)
      return *hidden;
    none.message = "no line of at least " + std::to_string(options.min_length_px) + " px";
    return none;
  }
  NeedleSegment s = best->cues;  // step 6
  tipAtHalfLevel(ridge, options.ridge_sigma_px, options.max_gap_px, *best, &s);
  if (hidden && best->cues.motion < kMinMotionRatio &&
      cv::norm(hidden->tip_px - s.tip_px) > kBlobOnLine_px)
    return *hidden;
  if (hidden)
    extendToMotionFront(motion, *hidden, &s);
  double front = 0.0;
  s.motion_ahead = motionAhead(motion, s, &front);
  if (s.motion_ahead >= kMinMotionRatio && !s.extended_by_motion) {
    // Traced short: the tip moves on along its line to where the brightening ends.
    const cv::Point2d d(std::cos(s.angle_rad), std::sin(s.angle_rad));
    const double u = motionFront(motion, s.tip_px, d, front);
    if (u >= kBlobAhead_px) {
      s.tip_px += u * d;
      s.extended_by_motion = true;
      s.motion_ahead = motionAhead(motion, s);
    }
  }
  if (!strongEnough(*best, options, region)) {
    if (hidden)  // a line too weak on its own: the brightening shows the tip
      return *hidden;
    s.found = false;
    s.message = "best line too weak to be a needle: " + summary(s);
    return s;
  }
  s.found = true;
  s.message = summary(s);
  return s;
}

// ---- SequenceTracker --------------------------------------------------------------------------

SequenceTracker::SequenceTracker(const AcquisitionOptions& options) : options_(options) {
  options_.validate();
}

bool SequenceTracker::agrees(const NeedleSegment& a, const NeedleSegment& b, double tip_px,
                             double far_px) const {
  double da = std::abs(a.angle_rad - b.angle_rad);
  da = std::min(da, 2 * kPi - da);
  const cv::Point2d n(-std::sin(a.angle_rad), std::cos(a.angle_rad));
  const cv::Point2d nb(-std::sin(b.angle_rad), std::cos(b.angle_rad));
  // How far b's tip lies BEHIND a's along a's axis (cos, sin) = (n.y, -n.x): the wide gate
  // far_px applies behind (see kGateBehind_px).
  const double behind = (b.tip_px - a.tip_px).dot(cv::Point2d(-n.y, n.x));
  if (a.from_motion && b.from_motion) {
    // Two tips from the motion alone: no shaft, a rough axis; only the distance counts.
    return cv::norm(b.tip_px - a.tip_px) < std::max(tip_px, far_px);
  }
  if (a.from_motion || b.from_motion) {
    // A tip from the motion alone against a shaft: its front lies among the reverberation
    // copies beside the needle, on the shaft's line.
    const cv::Point2d n_line = a.from_motion ? nb : n, d_line(n_line.y, -n_line.x);
    const double along_line = (b.tip_px - a.tip_px).dot(d_line);
    return std::abs((b.tip_px - a.tip_px).dot(n_line)) < kGateMotionLine_px &&
           along_line > -tip_px && along_line < std::max(tip_px, far_px);
  }
  // Off the line both ways: a line that only meets the other's far extension (a layer in line
  // with the needle hundreds of pixels on) is not the same line.
  const double off_line =
      std::max(std::abs((b.tip_px - a.tip_px).dot(n)), std::abs((a.tip_px - b.tip_px).dot(nb)));
  return da < kGateAngle_rad && off_line < kGateLine_px && behind > -tip_px &&
         behind < std::max(tip_px, far_px);
}

/// Moving tissue (breathing, a hand-held probe, tissue pushed by the needle) moves the frame:
/// the background follows the tissue's local motion before the difference. The motion is dense
/// optical flow (DIS) at half resolution, averaged over cells of kFlowCell_px and median
/// filtered over kFlowMedian x kFlowMedian cells: the needle's advancing tip (a few cells) is an
/// outlier to the tissue around it and is left out, so the background does not follow the needle.
/// The background moves only when some cell's motion reaches kTissueShift_px: on still tissue
/// the flow's noise (and the needle's residue) stays below it, and the background is left as it
/// is (an interpolated warp blurs it).
constexpr double kTissueShift_px = 1.0;
constexpr int kFlowCell_px = 32;
constexpr int kFlowMedian = 5;

/// The tissue's motion from `current` to `background` (both CV_32F, full size) as remap maps of
/// the frame's size (current(p) ~ background(map(p))); empty when no cell moved kTissueShift_px.
bool tissueFlow(const cv::Mat& background, const cv::Mat& current, cv::Mat* map_x, cv::Mat* map_y) {
  cv::Mat bg_half, cur_half, bg8, cur8, flow;
  cv::pyrDown(background, bg_half);
  cv::pyrDown(current, cur_half);
  bg_half.convertTo(bg8, CV_8U);
  cur_half.convertTo(cur8, CV_8U);
  const cv::Ptr<cv::DISOpticalFlow> dis =
      cv::DISOpticalFlow::create(cv::DISOpticalFlow::PRESET_FAST);
  dis->calc(cur8, bg8, flow);
  const cv::Size cells(std::max(1, current.cols / kFlowCell_px),
                       std::max(1, current.rows / kFlowCell_px));
  cv::Mat coarse;
  cv::resize(flow, coarse, cells, 0, 0, cv::INTER_AREA);
  if (cells.width >= kFlowMedian && cells.height >= kFlowMedian)
    cv::medianBlur(coarse, coarse, kFlowMedian);
  coarse *= 2.0;  // half-resolution pixels to full
  double largest = 0.0;
  for (int r = 0; r < coarse.rows; ++r)
    for (int c = 0; c < coarse.cols; ++c)
      largest = std::max(largest, cv::norm(coarse.at<cv::Vec2f>(r, c)));
  if (!(largest >= kTissueShift_px))
    return false;
  cv::Mat dense;
  cv::resize(coarse, dense, current.size(), 0, 0, cv::INTER_LINEAR);
  std::vector<cv::Mat> parts;
  cv::split(dense, parts);
  *map_x = parts[0];
  *map_y = parts[1];
  for (int r = 0; r < dense.rows; ++r) {
    float* x = map_x->ptr<float>(r);
    float* y = map_y->ptr<float>(r);
    for (int c = 0; c < dense.cols; ++c) {
      x[c] += static_cast<float>(c);
      y[c] += static_cast<float>(r);
    }
  }
  return true;
}

cv::Mat SequenceTracker::motionMap(const cv::Mat& frame) {
  std::string problem;
  const cv::Mat grey = toGrey8(frame, &problem);
  if (grey.empty())
    return {};
  cv::Mat current;
  grey.convertTo(current, CV_32F);
  cv::Mat motion;
  if (!background_.empty() && background_.size() == current.size()) {
    cv::Mat map_x, map_y;
    if (tissueFlow(background_, current, &map_x, &map_y)) {
      cv::Mat moved;
      cv::remap(background_, moved, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
      background_ = moved;
    }
    // The signed difference smoothed at the needle's scale, over the mean of its magnitude: the
    // frame's own noise averages out, a change as wide as the needle does not.
    cv::subtract(current, background_, motion);
    cv::GaussianBlur(motion, motion, cv::Size(), options_.ridge_sigma_px);
    motion *= 1.0 / (cv::norm(motion, cv::NORM_L1) / static_cast<double>(motion.total()) +
                     1.0);  // +1 grey level: a noise-free still frame
    cv::accumulateWeighted(current, background_, kBackgroundRate);
  } else {
    background_ = current;
  }
  return motion;
}

SequenceTracker::Output SequenceTracker::onFrame(const cv::Mat& frame) {
  if (!frame.empty() && !last_frame_.empty() && frame.size() == last_frame_.size() &&
      frame.type() == last_frame_.type() && cv::norm(frame, last_frame_, cv::NORM_INF) == 0) {
    Output repeated = last_output_;
    repeated.confident = false;
    repeated.segment.message =
        "repeated frame (identical to the previous): " + repeated.segment.message;
    return repeated;
  }
  last_frame_ = frame.clone();
  size_ = frame.size();
  motion_ = motionMap(frame);
  updateRegion(frame);
  last_output_ = update(acquireNeedle(frame, options_, motion_, region_));
  return last_output_;
}

void SequenceTracker::updateRegion(const cv::Mat& frame) {
  std::string problem;
  const cv::Mat grey = toGrey8(frame, &problem);
  if (grey.empty())
    return;
  const bool resized = max_frame_.size() != grey.size();
  if (resized) {
    max_frame_ = grey.clone();
    region_frames_ = 0;
  } else {
    max_frame_ = cv::max(max_frame_, grey);
  }
  // The region settles within a few frames (speckle fills the image's dark spots); then it is
  // refreshed every kRegionRefresh frames.
  if (region_frames_ < kRegionSettle || region_frames_ % kRegionRefresh == 0)
    region_ = findImagingRegion(max_frame_);
  ++region_frames_;
}

void SequenceTracker::startTrack(const NeedleSegment& d) {
  track_ = d;
  velocity_px_ = 0;
  start_tip_px_ = d.tip_px;
  start_tail_px_ = d.tail_px;
  moved_ = d.motion >= kMinMotionRatio;
}

bool SequenceTracker::advancedLikeANeedle(const NeedleSegment& d, const cv::Point2d& axis) const {
  // The tip advanced along the axis while the shaft's far end stayed (a needle being inserted);
  // a line of moving tissue (a layer drifting with breathing or the probe) moves at both ends.
  const double advance = std::abs((d.tip_px - start_tip_px_).dot(axis));
  return advance >= kEarnAdvance_px &&
         (d.from_motion || cv::norm(d.tail_px - start_tail_px_) < 0.5 * advance);
}

double SequenceTracker::motionAxis(const NeedleSegment& d) const {
  // The tip's own path is the needle's axis once it is long enough; before that the shaft the
  // track saw, if it saw one.
  const cv::Point2d path = d.tip_px - start_tip_px_;
  if (cv::norm(path) >= kEarnAdvance_px)
    return std::atan2(path.y, path.x);
  return track_ && !track_->from_motion ? track_->angle_rad : d.angle_rad;
}

NeedleSegment SequenceTracker::predicted() const {
  NeedleSegment pred = *track_;
  const cv::Point2d axis(std::cos(pred.angle_rad), std::sin(pred.angle_rad));
  pred.tip_px += velocity_px_ * axis;
  pred.tail_px += velocity_px_ * axis;
  return pred;
}

std::optional<SequenceTracker::Output> SequenceTracker::coast(const NeedleSegment& d,
                                                              const std::string& why) {
  if (!moved_ || velocity_px_ <= 0.0 || coasted_ >= kMaxCoast)
    return std::nullopt;
  NeedleSegment pred = predicted();
  if (onBorder(pred.tip_px, region_, options_.ridge_sigma_px))
    return std::nullopt;  // the tip has left the field of view
  ++coasted_;
  pred.found = true;
  pred.motion = d.found ? d.motion : 0.0;
  pred.message = "tip hidden, coasting on the motion model (" + why + ")";
  track_ = pred;
  missed_ = 0;
  Output out;
  out.segment = pred;
  out.predicted = true;
  return out;
}

std::optional<SequenceTracker::Output> SequenceTracker::reacquire(const NeedleSegment& d) {
  if (moved_ && d.motion < kMinMotionRatio)
    return std::nullopt;  // a still line never replaces a moving needle
  if (candidate_ && agrees(*candidate_, d, kAgreeTip_px, kAgreeTip_px)) {
    ++candidate_count_;
  } else {
    candidate_count_ = 1;
  }
  candidate_ = d;
  if (candidate_count_ < kReacquireAfter)
    return std::nullopt;
  startTrack(d);
  agreeing_ = candidate_count_;
  missed_ = 0;
  Output out;
  out.segment = d;
  out.segment.message = "re-acquired: " + d.message;
  return out;
}

std::optional<NeedleSegment> SequenceTracker::blobOnTrack(const NeedleSegment& pred) const {
  // Only a track of tips from the motion (a shaft's track keeps its gates), and only a front that
  // advanced along the axis (the background's fading memory of an earlier change stays put).
  if (!track_ || !track_->from_motion)
    return std::nullopt;
  std::optional<NeedleSegment> b = tipFromMotion(motion_, options_.entry, kBlobDominanceOnTrack);
  const cv::Point2d axis(std::cos(pred.angle_rad), std::sin(pred.angle_rad));
  if (!b || (b->tip_px - track_->tip_px).dot(axis) < kChainStepMin_px ||
      !agrees(pred, *b, kGateTip_px, kGateBehind_px))
    return std::nullopt;
  b->message = "tip from the motion on the track: " + b->message;
  return b;
}

std::optional<NeedleSegment> SequenceTracker::advancingBlob() {
  const std::optional<NeedleSegment> b =
      tipFromMotion(motion_, options_.entry, kBlobDominanceChain);
  if (!b) {
    chain_.clear();
    return std::nullopt;
  }
  bool continues = false;
  if (!chain_.empty()) {
    const cv::Point2d step = b->tip_px - chain_.back();
    const double len = cv::norm(step);
    const cv::Point2d axis(std::cos(b->angle_rad), std::sin(b->angle_rad));
    continues = len >= kChainStepMin_px && len <= kGateTip_px &&
                std::abs(step.dot(axis)) >= kChainTurnCos * len;
    if (continues && chain_.size() >= 2) {
      const cv::Point2d before = chain_.back() - chain_[chain_.size() - 2];
      continues = step.dot(before) >= kChainTurnCos * len * cv::norm(before);
    }
  }
  if (!continues)
    chain_.clear();
  chain_.push_back(b->tip_px);
  if (static_cast<int>(chain_.size()) < kChainFrames)
    return std::nullopt;
  NeedleSegment s = *b;
  s.message = "tip from a brightening advancing in line over " + std::to_string(chain_.size()) +
              " frames: " + b->message;
  return s;
}

SequenceTracker::Output SequenceTracker::update(const NeedleSegment& detection) {
  Output out;
  NeedleSegment d = detection;
  if (!(track_ && moved_)) {
    // No moving track yet: a brightening whose front advances in line, frame after frame, is a
    // needle hidden in moving tissue, unless a line moves like a needle itself.
    const std::optional<NeedleSegment> b = advancingBlob();
    if (b && !(d.found && d.motion >= kMinMotionRatio))
      d = *b;
  } else {
    chain_.clear();  // a chain starts afresh once a moving track is lost
  }
  if (track_) {
    // Motion model: the tip moves along the needle's axis at the last speed.
    NeedleSegment pred = predicted();
    const cv::Point2d axis(std::cos(pred.angle_rad), std::sin(pred.angle_rad));
    if (moved_ && !(d.found && agrees(pred, d, kGateTip_px, kGateBehind_px))) {
      // The moving track's tip not seen as a line: the brightening where it went, if it is there.
      if (std::optional<NeedleSegment> b = blobOnTrack(pred))
        d = *b;
    }
    if (d.found && agrees(pred, d, kGateTip_px, moved_ ? kGateBehind_px : kGateTip_px)) {
      coasted_ = 0;
      velocity_px_ = 0.5 * velocity_px_ + 0.5 * (d.tip_px - track_->tip_px).dot(axis);
      const bool close = cv::norm(d.tip_px - pred.tip_px) < kAgreeTip_px;
      agreeing_ = close ? agreeing_ + 1 : 1;
      moved_ = moved_ || d.motion >= kMinMotionRatio || advancedLikeANeedle(d, axis);
      seen_moving_ = seen_moving_ || moved_;
      track_ = d;
      if (d.from_motion)
        track_->angle_rad = motionAxis(d);
      missed_ = 0;
      candidate_.reset();
      out.segment = *track_;
      // Never confident while the tissue ahead of the tip still brightens (the needle has
      // advanced past the traced tip), nor from the motion alone (no shaft seen).
      out.confident = agreeing_ >= kConfirmFrames && moved_ && d.motion_ahead < kMinMotionRatio &&
                      !d.from_motion;
      if (seen_moving_ && !moved_) {
        out.segment.found = false;  // the needle moved before: a still line is not it
        out.segment.message = "a still line, and the needle moved before: " + d.message;
      }
      return out;
    }
    if (d.found && d.motion >= kMinMotionRatio && track_->motion < kMinMotionRatio && !moved_) {
      // The sequence cue: the track was a still line, this detection moves at its tip (a
      // needle advancing): the still line gives way at once, without waiting for agreement.
      startTrack(d);
      agreeing_ = 1;
      missed_ = 0;
      candidate_.reset();
      out.segment = d;
      out.segment.message = "moving needle replaces a still line: " + d.message;
      return out;
    }
    if (d.found) {  // gated out: re-acquire only after agreeing frames
      if (std::optional<Output> again = reacquire(d))
        return *again;
    }
    if (std::optional<Output> coasting = coast(d, d.found ? "detection gated out" : d.message))
      return *coasting;
    if (moved_ || ++missed_ > kMaxPredicted) {
      track_.reset();
      agreeing_ = 0;
      coasted_ = 0;
      out.segment = d;
      out.segment.found = false;
      out.segment.message = "track lost: " + d.message;
      return out;
    }
    pred.found = !seen_moving_;  // after a needle has moved, a still line is not it
    pred.message =
        "predicted along the axis (" + (d.found ? "detection gated out" : d.message) + ")";
    out.segment = pred;
    out.predicted = true;
    return out;
  }
  out.segment = d;
  if (d.found) {
    startTrack(d);
    agreeing_ = 1;
    missed_ = 0;
    coasted_ = 0;
    if (seen_moving_ && !moved_) {
      out.segment.found = false;  // the needle moved before: a still line is not it
      out.segment.message = "a still line, and the needle moved before: " + d.message;
    }
  }
  return out;
}

}  // namespace needle_guidance::imaging
