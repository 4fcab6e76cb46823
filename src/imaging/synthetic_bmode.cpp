// Synthetic B-mode frames; see synthetic_bmode.h.
#include "needle_guidance/imaging/synthetic_bmode.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>

namespace needle_guidance::imaging {

namespace {

/// Mean speckle level [grey levels]; lateral and axial PSF widths [px].
constexpr double kSpeckleMean = 60.0, kPsfLateral_px = 3.0, kPsfAxial_px = 1.0;
/// Reverberation copies: spacing [px] and first copy's relative brightness.
constexpr double kReverbSpacing_px = 10.0, kReverbGain = 0.25;
/// Shadow: attenuation per half-pixel sample of shaft above a pixel.
constexpr float kShadowPerSample = 0.995F;

/// The envelope of two Gaussian scatterer fields convolved with the PSF.
cv::Mat speckle(cv::Size size, std::uint64_t seed) {
  cv::RNG rng(seed);
  cv::Mat a(size, CV_32F), b(size, CV_32F);
  rng.fill(a, cv::RNG::NORMAL, 0, 1);
  rng.fill(b, cv::RNG::NORMAL, 0, 1);
  cv::GaussianBlur(a, a, cv::Size(), kPsfLateral_px, kPsfAxial_px);
  cv::GaussianBlur(b, b, cv::Size(), kPsfLateral_px, kPsfAxial_px);
  cv::Mat env;
  cv::magnitude(a, b, env);
  return env * (kSpeckleMean / cv::mean(env)[0]);
}

void addInterface(const BModeInterface& f, cv::Mat* img, cv::Mat* add) {
  for (int y = 0; y < img->rows; ++y) {
    for (int x = 0; x < img->cols; ++x) {
      const double row = f.y0 + (f.y1 - f.y0) * x / std::max(img->cols - 1, 1);
      if (y > row)
        img->at<float>(y, x) *= static_cast<float>(f.below_gain);
    }
  }
  cv::line(*add, cv::Point2d(0, f.y0), cv::Point2d(img->cols - 1, f.y1), f.brightness, 3,
           cv::LINE_AA);
}

/// Heading at the tail: the chord's, turned back by half the arc's total turn.
double tailHeading(const BModeNeedle& n) {
  const cv::Point2d chord = n.tip - n.tail;
  const double k = n.curvature_per_px;
  return std::atan2(chord.y, chord.x) - std::asin(std::clamp(0.5 * cv::norm(chord) * k, -1.0, 1.0));
}

void addNeedle(const BModeNeedle& n, cv::Mat* img, cv::Mat* add) {
  const double len = n.length();
  if (len < 1.0)
    return;
  const double fade_start = (1.0 - n.fade_fraction) * len;
  for (double s = 0; s <= len; s += 0.5) {
    const cv::Point2d p = n.at(s);
    const double w = s < fade_start ? 1.0 : 1.0 - (s - fade_start) / (len - fade_start + 1e-9);
    cv::circle(*add, p, 1, n.brightness * w, cv::FILLED, cv::LINE_AA);
    for (int k = 1; k <= 2; ++k) {
      cv::circle(*add, p + cv::Point2d(0, kReverbSpacing_px * k), 1,
                 kReverbGain * n.brightness * w / k, cv::FILLED);
    }
    const int x = static_cast<int>(p.x);
    if (x < 0 || x >= img->cols)
      continue;
    for (int y = std::max(static_cast<int>(p.y) + 3, 0); y < img->rows; ++y) {
      img->at<float>(y, x) *= kShadowPerSample;
    }
  }
}

}  // namespace

double BModeNeedle::length() const {
  const double chord = cv::norm(tip - tail), k = std::abs(curvature_per_px);
  return k == 0.0 ? chord : 2.0 * std::asin(std::min(1.0, 0.5 * chord * k)) / k;
}

cv::Point2d BModeNeedle::at(double s) const {
  const double k = curvature_per_px;
  if (k == 0.0) {
    const double chord = cv::norm(tip - tail);
    return chord > 0.0 ? tail + s * ((tip - tail) / chord) : tail;
  }
  const double h0 = tailHeading(*this), h = h0 + k * s;
  return tail + cv::Point2d(std::sin(h) - std::sin(h0), std::cos(h0) - std::cos(h)) * (1.0 / k);
}

double BModeNeedle::tipAngle() const {
  if (curvature_per_px == 0.0)
    return std::atan2(tip.y - tail.y, tip.x - tail.x);
  return tailHeading(*this) + curvature_per_px * length();
}

cv::Mat syntheticBMode(cv::Size size, std::uint64_t seed,
                       const std::optional<BModeInterface>& interface_line,
                       const std::optional<BModeNeedle>& needle) {
  cv::Mat img = speckle(size, seed);
  cv::Mat add = cv::Mat::zeros(size, CV_32F);
  if (interface_line)
    addInterface(*interface_line, &img, &add);
  if (needle)
    addNeedle(*needle, &img, &add);
  cv::GaussianBlur(add, add, cv::Size(), 1.0);
  img += add;
  cv::Mat out;
  img.convertTo(out, CV_8U);
  return out;
}

}  // namespace needle_guidance::imaging
