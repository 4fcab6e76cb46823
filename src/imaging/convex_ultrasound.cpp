// The realistic ultrasound model on a convex probe; see convex_ultrasound.h. The physical
// constants shared with the linear-probe model (display range, tissue and needle echoes, shadow,
// reverberation, attenuation) are realistic_ultrasound.h's; the ones here are the convex probe's
// own (a 3-5 MHz abdominal probe: coarser grain than the linear 7 MHz one).
#include "needle_guidance/imaging/convex_ultrasound.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>

#include "needle_guidance/tissue/image_warp.h"
#include "realistic_ultrasound.h"
#include "render_util.h"

namespace needle_guidance::imaging {
namespace {

namespace rs = realistic;
using render::streamSeed;

/// Point-spread function in the beam grid: lateral sigma in beams (a fixed angular width: the
/// lateral resolution in millimetres grows with depth) and axial sigma [m] (about 0.6 mm full
/// width at 3.5 MHz).
constexpr double kPsfLateral_beams = 0.8;
constexpr double kPsfAxial_m = 0.25e-3;
/// Probe face ring-down: a bright band under the face, kRingDown at the face decaying over
/// kRingDownDepth_m.
constexpr double kRingDown = 0.5;
constexpr double kRingDownDepth_m = 0.6e-3;
/// The needle's elevation beam profile: echo x exp(-(e / w)^2), e = slope x arc length.
constexpr double kElevationHalfWidth_m = 1.0e-3;  // a convex probe's thicker slice
/// The needle canvas (8-bit) spans amplitudes 0..kCanvasFullScale.
constexpr double kCanvasFullScale = 2.5;
/// A needle or layer pixel on the canvas above this (of full scale) casts a shadow down its beam.
constexpr double kShadowCaster = 0.3;

/// (beam, sample) -> frame pixel maps of the beam grid, and frame pixel -> (beam, sample).
struct BeamGrid {
  cv::Size size;                   ///< beams x samples (cols x rows)
  cv::Mat to_frame_x, to_frame_y;  ///< CV_32F of size: the frame pixel of each sample
  cv::Mat to_beam_x, to_beam_y;    ///< CV_32F of the frame's size: its (beam, sample), -1 outside
};

BeamGrid beamGrid(const ConvexProbe& p, cv::Size frame) {
  BeamGrid g;
  const int samples = std::max(2, static_cast<int>(std::lround(p.depth_px)));
  g.size = cv::Size(p.beams, samples);
  g.to_frame_x.create(g.size, CV_32F);
  g.to_frame_y.create(g.size, CV_32F);
  const double step = 2.0 * p.half_angle_rad / p.beams;
  for (int s = 0; s < samples; ++s) {
    const double r = p.face_radius_px + s;
    for (int b = 0; b < p.beams; ++b) {
      const double th = -p.half_angle_rad + (b + 0.5) * step;
      g.to_frame_x.at<float>(s, b) = static_cast<float>(p.apex_px.x + r * std::sin(th));
      g.to_frame_y.at<float>(s, b) = static_cast<float>(p.apex_px.y + r * std::cos(th));
    }
  }
  g.to_beam_x.create(frame, CV_32F);
  g.to_beam_y.create(frame, CV_32F);
  for (int y = 0; y < frame.height; ++y) {
    for (int x = 0; x < frame.width; ++x) {
      const double dx = x - p.apex_px.x, dy = y - p.apex_px.y;
      const double b = (std::atan2(dx, dy) + p.half_angle_rad) / step - 0.5;
      const double s = std::hypot(dx, dy) - p.face_radius_px;
      const bool in = b >= -0.5 && b <= p.beams - 0.5 && s >= 0.0 && s <= samples - 1.0;
      g.to_beam_x.at<float>(y, x) = in ? static_cast<float>(std::clamp(b, 0.0, p.beams - 1.0)) : -1;
      g.to_beam_y.at<float>(y, x) = in ? static_cast<float>(s) : -1;
    }
  }
  return g;
}

/// Specular amplitude of a structure at angle `dir` to the beam `beam`: facing it fully,
/// `parallel` along it, |sin|^2 between.
double specular(cv::Point2d dir, cv::Point2d beam, double facing, double parallel) {
  const double n = cv::norm(dir);
  const double c = n > 0.0 ? std::abs(dir.dot(beam)) / n : 0.0;  // |cos| to the beam
  return parallel + (facing - parallel) * (1.0 - c * c);
}

/// The frame's echogenicity (the tissue beyond each layer scaled by its gain) and the layers'
/// specular echo, in frame pixels.
void sceneMaps(const ConvexScene& sc, cv::Size size, cv::Mat* echo, cv::Mat* layers) {
  *echo = cv::Mat(size, CV_32F, cv::Scalar(rs::kTissueEcho));
  *layers = cv::Mat(size, CV_32F, cv::Scalar(0.0));
  for (const ConvexLayer& l : sc.layers) {
    const cv::Point2d d = l.b - l.a;
    const cv::Point2d n = d.x >= 0 ? cv::Point2d(-d.y, d.x) : cv::Point2d(d.y, -d.x);  // deeper
    for (int y = 0; y < size.height; ++y) {
      float* e = echo->ptr<float>(y);
      for (int x = 0; x < size.width; ++x) {
        // Beyond the layer (deeper than its line, within its extent across the beam).
        const cv::Point2d p(x, y);
        const double u = (p - l.a).dot(d) / std::max(d.dot(d), 1e-9);
        if (u >= 0.0 && u <= 1.0 && (p - l.a).dot(n) > 0.0)
          e[x] *= static_cast<float>(l.gain_below);
      }
    }
    const int pieces = std::max(1, static_cast<int>(cv::norm(d) / 4.0));
    for (int i = 0; i < pieces; ++i) {
      const cv::Point2d a = l.a + d * (double(i) / pieces), b = l.a + d * (double(i + 1) / pieces);
      const double amp =
          specular(d, sc.probe.beamAt(0.5 * (a + b)), l.amplitude, 0.1 * l.amplitude);
      cv::line(*layers, a, b, cv::Scalar(amp), std::max(1, static_cast<int>(l.width_px)),
               cv::LINE_AA);
    }
  }
}

/// The needle's specular echo in frame pixels (canvas of kCanvasFullScale).
cv::Mat needleMap(const ConvexScene& sc, cv::Size size, const std::vector<cv::Point2d>& pts) {
  cv::Mat canvas(size, CV_8U, cv::Scalar(0));
  double length = 0.0;
  const int width = std::max(1, static_cast<int>(std::lround(sc.needle_width_px)));
  for (std::size_t i = 1; i < pts.size(); ++i) {
    const cv::Point2d d = pts[i] - pts[i - 1];
    length += cv::norm(d);
    const double elevation_m = sc.elevation_slope * length * sc.probe.pixel_size_m;
    const double in_plane = std::exp(-std::pow(elevation_m / kElevationHalfWidth_m, 2.0));
    const double e =
        specular(d, sc.probe.beamAt(pts[i]), rs::kNeedleFacing, rs::kNeedleParallel) * in_plane;
    const cv::Point a(cvRound(pts[i - 1].x * 256), cvRound(pts[i - 1].y * 256));
    const cv::Point b(cvRound(pts[i].x * 256), cvRound(pts[i].y * 256));
    cv::line(canvas, a, b, cv::Scalar(255.0 * e / kCanvasFullScale), width, cv::LINE_AA, 8);
  }
  cv::Mat needle;
  canvas.convertTo(needle, CV_32F, kCanvasFullScale / 255.0);
  return needle;
}

/// Along each beam (a column of the beam grid): beyond the first strong specular echo, the
/// tissue in its shadow; the needle's reverberation copies deeper along the beam.
void alongBeams(const cv::Mat& needle, const cv::Mat& layers, double spacing_samples,
                cv::Mat* tissue_gain, cv::Mat* reverb) {
  *tissue_gain = cv::Mat(needle.size(), CV_32F, cv::Scalar(1.0));
  *reverb = cv::Mat(needle.size(), CV_32F, cv::Scalar(0.0));
  for (int b = 0; b < needle.cols; ++b) {
    float gain = 1.0F;
    for (int s = 0; s < needle.rows; ++s) {
      const float n = needle.at<float>(s, b);
      tissue_gain->at<float>(s, b) = gain;
      if (n > kShadowCaster)
        gain = std::min(
            gain, static_cast<float>(1.0 - (1.0 - rs::kNeedleShadowGain) * std::min(1.0F, n)));
      if (layers.at<float>(s, b) > kShadowCaster)
        gain = std::min(gain, 0.8F);  // a strong interface passes less on
      if (n <= 0.0F)
        continue;
      double copy = n * rs::kReverbFirst;
      for (int k = 1; k <= rs::kReverbCopies; ++k, copy *= rs::kReverbDecay) {
        const int t = s + static_cast<int>(std::lround(k * spacing_samples));
        if (t < needle.rows)
          reverb->at<float>(t, b) = std::max(reverb->at<float>(t, b), static_cast<float>(copy));
      }
    }
  }
}

}  // namespace

void ConvexProbe::validate() const {
  auto check = [](bool ok, const char* field, double v) {
    if (!ok) {
      throw std::invalid_argument(std::string("ConvexProbe.") + field + " = " + std::to_string(v) +
                                  " is out of range");
    }
  };
  check(std::isfinite(apex_px.x) && std::isfinite(apex_px.y), "apex_px", apex_px.x);
  check(std::isfinite(face_radius_px) && face_radius_px > 0, "face_radius_px", face_radius_px);
  check(std::isfinite(half_angle_rad) && half_angle_rad > 0 && half_angle_rad <= 1.4,
        "half_angle_rad", half_angle_rad);
  check(std::isfinite(depth_px) && depth_px > 1 && depth_px < 1e4, "depth_px", depth_px);
  check(beams >= 16 && beams <= 4096, "beams", beams);
  check(std::isfinite(pixel_size_m) && pixel_size_m > 0, "pixel_size_m", pixel_size_m);
}

cv::Point2d ConvexProbe::beamAt(cv::Point2d p) const {
  const cv::Point2d d = p - apex_px;
  const double n = cv::norm(d);
  return n > 0.0 ? d / n : cv::Point2d(0.0, 1.0);
}

bool ConvexProbe::inside(cv::Point2d p) const {
  const cv::Point2d d = p - apex_px;
  const double r = cv::norm(d);
  return r >= face_radius_px && r <= face_radius_px + depth_px &&
         std::abs(std::atan2(d.x, d.y)) <= half_angle_rad;
}

cv::Mat renderConvexFrame(const ConvexScene& sc, cv::Size size,
                          const std::vector<cv::Point2d>& needle_px, std::uint64_t index) {
  sc.probe.validate();
  for (const cv::Point2d& p : needle_px) {
    if (!std::isfinite(p.x) || !std::isfinite(p.y))
      throw std::invalid_argument("renderConvexFrame: needle point is not finite");
  }
  const BeamGrid g = beamGrid(sc.probe, size);
  cv::Mat echo, layers;
  sceneMaps(sc, size, &echo, &layers);
  const cv::Mat needle = needleMap(sc, size, needle_px);
  // Into the beam grid (what each beam's samples see).
  auto sample = [&g](const cv::Mat& m) {
    cv::Mat out;
    cv::remap(m, out, g.to_frame_x, g.to_frame_y, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    return out;
  };
  const cv::Mat echo_b = sample(echo), layers_b = sample(layers), needle_b = sample(needle);
  const double pixel = sc.probe.pixel_size_m, axial = kPsfAxial_m / pixel;
  cv::Mat speckle = tissue::rayleighSpeckle(g.size, kPsfLateral_beams, axial,
                                            std::uint32_t(streamSeed(sc.seed, 0, 0xC0E1)));
  if (sc.decorrelation > 0.0) {
    const cv::Mat fresh = tissue::rayleighSpeckle(
        g.size, kPsfLateral_beams, axial, std::uint32_t(streamSeed(sc.seed, index, 0xC0E2)));
    speckle = (1.0 - sc.decorrelation) * speckle + sc.decorrelation * fresh;
  }
  cv::Mat gain, reverb;
  alongBeams(needle_b, layers_b, rs::kReverbSpacing_m / pixel, &gain, &reverb);
  cv::Mat specular_b = cv::max(layers_b, cv::max(needle_b, reverb));
  cv::GaussianBlur(specular_b, specular_b, cv::Size(0, 0), kPsfLateral_beams, axial);
  cv::Mat a = speckle.mul(echo_b).mul(gain) * (rs::kTissueAmplitude / rs::kTissueEcho) + specular_b;
  cv::RNG rng(streamSeed(sc.seed, index, 0xC0E3));
  cv::Mat re(a.size(), CV_32F), im(a.size(), CV_32F);
  const double sigma = sc.noise_std * rs::kTissueAmplitude;
  rng.fill(re, cv::RNG::NORMAL, 0.0, sigma);
  rng.fill(im, cv::RNG::NORMAL, 0.0, sigma);
  const double display_gain = std::pow(10.0, sc.gain_db / 20.0);
  cv::Mat shown(a.size(), CV_32F);
  for (int s = 0; s < a.rows; ++s) {
    const double depth_m = s * pixel;
    const double att = std::exp(-rs::kAttenuation_per_m * depth_m) * display_gain;
    const double ring = kRingDown * std::exp(-depth_m / kRingDownDepth_m);
    for (int b = 0; b < a.cols; ++b) {
      const double v = (a.at<float>(s, b) + ring) * att;
      shown.at<float>(s, b) = static_cast<float>(
          rs::logCompress(std::hypot(v + re.at<float>(s, b), im.at<float>(s, b))));
    }
  }
  // Scan conversion: black outside the sector.
  cv::Mat frame;
  cv::remap(shown, frame, g.to_beam_x, g.to_beam_y, cv::INTER_LINEAR, cv::BORDER_CONSTANT,
            cv::Scalar(0.0));
  frame.setTo(0.0F, g.to_beam_y < 0.0F);
  cv::Mat out;
  frame.convertTo(out, CV_8U, 255.0);
  return out;
}

}  // namespace needle_guidance::imaging

namespace needle_guidance::imaging {
namespace {

/// The insertion's probe: the ends of its face on row face_top_px, the apex over the frame's
/// centre (apex_dx_px off it).
ConvexProbe probeOf(const ConvexInsertion& c) {
  ConvexProbe p;
  p.face_radius_px = c.face_radius_px;
  p.half_angle_rad = c.half_angle_rad;
  p.depth_px = c.depth_px;
  p.pixel_size_m = c.pixel_size_m;
  p.apex_px = cv::Point2d(0.5 * (c.size.width - 1) + c.apex_dx_px,
                          c.face_top_px - c.face_radius_px * std::cos(c.half_angle_rad));
  return p;
}

/// The needle's entry point on the face and its unit direction.
void entryOf(const ConvexInsertion& c, const ConvexProbe& p, cv::Point2d* entry, cv::Point2d* u) {
  const double th = c.entry * p.half_angle_rad;
  *entry = p.apex_px + p.face_radius_px * cv::Point2d(std::sin(th), std::cos(th));
  const double a = c.angle_deg * CV_PI / 180.0;
  *u = cv::Point2d(c.entry <= 0.0 ? std::cos(a) : -std::cos(a), std::sin(a));
}

}  // namespace

ConvexScene ConvexInsertion::scene() const {
  ConvexScene sc;
  sc.probe = probeOf(*this);
  sc.gain_db = gain_db;
  sc.noise_std = noise_std;
  sc.decorrelation = decorrelation;
  sc.elevation_slope = elevation_slope;
  sc.needle_width_px = needle_width_px;
  sc.seed = seed;
  // Layers: below the needle's deepest tip, long (most of the sector's width at their depth),
  // tilted a little, seeded.
  cv::Point2d tip;
  double angle = 0.0;
  needleAt(std::max(appear_at, 0) + frames, &tip, &angle);
  const ConvexProbe& p = sc.probe;
  const double face_depth = cv::norm(tip - p.apex_px) - p.face_radius_px;
  for (int k = 0; k < layers; ++k) {
    const double u = render::uniform01(render::streamSeed(seed, 0, 0x1A0 + std::uint64_t(k)));
    const double v = render::uniform01(render::streamSeed(seed, 0, 0x1B0 + std::uint64_t(k)));
    const double w = render::uniform01(render::streamSeed(seed, 0, 0x1C0 + std::uint64_t(k)));
    const double lo = std::min(face_depth + 25.0, p.depth_px - 40.0);
    const double depth = lo + (p.depth_px - 20.0 - lo) * (k + 0.3 + 0.5 * u) / std::max(layers, 1);
    const double r = p.face_radius_px + depth;
    const double span = (0.7 + 0.3 * v) * p.half_angle_rad, tilt = (w - 0.5) * 0.25;
    ConvexLayer l;
    l.a = p.apex_px + r * cv::Point2d(std::sin(-span + tilt), std::cos(-span + tilt));
    l.b = p.apex_px + r * cv::Point2d(std::sin(span + tilt), std::cos(span + tilt));
    l.amplitude = layer_amplitude;
    l.width_px = 4.0 + 3.0 * u;
    l.gain_below = k % 2 == 0 ? 0.6 : 1.4;
    sc.layers.push_back(l);
  }
  return sc;
}

double ConvexInsertion::visibleLength(int k) const {
  cv::Point2d tip;
  double angle = 0.0;
  const std::vector<cv::Point2d> pts = needleAt(k, &tip, &angle);
  const ConvexProbe p = probeOf(*this);
  double inside = 0.0;
  for (std::size_t i = 1; i < pts.size(); ++i)
    inside += p.inside(pts[i]) ? cv::norm(pts[i] - pts[i - 1]) : 0.0;
  return inside;
}

std::vector<cv::Point2d> ConvexInsertion::needleAt(int k, cv::Point2d* tip,
                                                   double* angle_rad) const {
  const ConvexProbe p = probeOf(*this);
  cv::Point2d entry, u;
  entryOf(*this, p, &entry, &u);
  *angle_rad = std::atan2(u.y, u.x);
  const double length = start_px + step_px * (k - std::max(appear_at, 0));
  *tip = entry + length * u;
  std::vector<cv::Point2d> pts;
  if (appear_at < 0 || k < appear_at)
    return pts;
  // From outside the sector (the skin beside the probe) to the tip, 1 px apart.
  for (double t = -60.0; t <= length; t += 1.0)
    pts.push_back(entry + t * u);
  return pts;
}

}  // namespace needle_guidance::imaging
