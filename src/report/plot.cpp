#include "needle_guidance/report/plot.h"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace needle_guidance {
namespace report {
namespace {

constexpr int kFont = cv::FONT_HERSHEY_SIMPLEX;
constexpr double kTextScale = 0.45;
const cv::Scalar kInk(30, 30, 30);
const cv::Scalar kGrid(225, 225, 225);

/// 1, 2 or 5 times a power of ten, about span / 6.
double tickStep(double span) {
  const double raw = span / 6.0;
  const double power = std::pow(10.0, std::floor(std::log10(raw)));
  for (double m : {1.0, 2.0, 5.0, 10.0}) {
    if (m * power >= raw)
      return m * power;
  }
  return 10.0 * power;
}

std::string tickLabel(double v) {
  std::ostringstream s;
  s.precision(4);
  s << (std::abs(v) < 1e-12 ? 0.0 : v);
  return s.str();
}

/// Range of the finite values, widened when empty or flat.
void fitRange(const std::vector<double>& values, double& lo, double& hi) {
  lo = std::numeric_limits<double>::infinity();
  hi = -lo;
  for (double v : values) {
    if (std::isfinite(v)) {
      lo = std::min(lo, v);
      hi = std::max(hi, v);
    }
  }
  if (!(lo <= hi)) {
    lo = 0.0;
    hi = 1.0;
  } else if (hi - lo < 1e-12 * std::max(1.0, std::abs(hi))) {
    lo -= 0.5;
    hi += 0.5;
  } else {
    const double pad = 0.04 * (hi - lo);
    lo -= pad;
    hi += pad;
  }
}

void text(cv::Mat& image, const std::string& s, cv::Point at, double scale = kTextScale,
          const cv::Scalar& colour = kInk) {
  cv::putText(image, s, at, kFont, scale, colour, 1, cv::LINE_AA);
}

}  // namespace

LinePlot::LinePlot(std::string title, std::string x_label, std::string y_label)
    : title_(std::move(title)), x_label_(std::move(x_label)), y_label_(std::move(y_label)) {}

void LinePlot::addLine(const std::string& name, const std::vector<double>& x,
                       const std::vector<double>& y, const cv::Scalar& bgr, int thickness) {
  if (x.size() != y.size()) {
    throw std::invalid_argument("LinePlot::addLine: series '" + name + "' has " +
                                std::to_string(x.size()) + " x and " + std::to_string(y.size()) +
                                " y values");
  }
  series_.push_back({name, x, y, bgr, thickness, true, {}, 0.0, 0.0});
}

void LinePlot::addPoints(const std::string& name, const std::vector<double>& x,
                         const std::vector<double>& y, const cv::Scalar& bgr, int radius) {
  addLine(name, x, y, bgr, radius);
  series_.back().line = false;
}

void LinePlot::addCells(const std::vector<double>& x, const std::vector<double>& y,
                        const std::vector<double>& value, double cell_w, double cell_h,
                        int colourmap, double lo, double hi) {
  if (x.size() != y.size() || x.size() != value.size() || !(lo < hi)) {
    throw std::invalid_argument("LinePlot::addCells: " + std::to_string(x.size()) + " x, " +
                                std::to_string(y.size()) + " y, " + std::to_string(value.size()) +
                                " values and range [" + std::to_string(lo) + ", " +
                                std::to_string(hi) + "]");
  }
  Series s{"", x, y, kInk, 0, false, {}, cell_w, cell_h};
  cv::Mat levels(1, static_cast<int>(value.size()), CV_8UC1), bgr;
  for (std::size_t k = 0; k < value.size(); ++k) {
    const double t =
        std::isfinite(value[k]) ? std::clamp((value[k] - lo) / (hi - lo), 0.0, 1.0) : 0.0;
    levels.at<unsigned char>(static_cast<int>(k)) =
        static_cast<unsigned char>(std::lround(255 * t));
  }
  if (!value.empty()) {
    cv::applyColorMap(levels, bgr, colourmap);
  }
  for (std::size_t k = 0; k < value.size(); ++k) {
    const cv::Vec3b c = bgr.at<cv::Vec3b>(static_cast<int>(k));
    s.cell_bgr.emplace_back(c[0], c[1], c[2]);
  }
  series_.push_back(std::move(s));
}

void LinePlot::addHorizontal(const std::string& name, double y, const cv::Scalar& bgr) {
  series_.push_back({name, {}, {y}, bgr, 1, true, {}, 0.0, 0.0});
}

void LinePlot::setXRange(double lo, double hi) {
  fixed_x_ = true;
  x_lo_ = lo;
  x_hi_ = hi;
}

void LinePlot::setYRange(double lo, double hi) {
  fixed_y_ = true;
  y_lo_ = lo;
  y_hi_ = hi;
}

cv::Mat LinePlot::render(int width_px, int height_px) const {
  std::vector<double> xs, ys;
  for (const auto& s : series_) {
    xs.insert(xs.end(), s.x.begin(), s.x.end());
    ys.insert(ys.end(), s.y.begin(), s.y.end());
  }
  double x_lo = x_lo_, x_hi = x_hi_, y_lo = y_lo_, y_hi = y_hi_;
  if (!fixed_x_)
    fitRange(xs, x_lo, x_hi);
  if (!fixed_y_)
    fitRange(ys, y_lo, y_hi);

  cv::Mat image(height_px, width_px, CV_8UC3, cv::Scalar(255, 255, 255));
  const cv::Rect area(70, 50, width_px - 90, height_px - 105);
  auto px = [&](double x, double y) {
    return cv::Point(
        area.x + static_cast<int>(std::lround((x - x_lo) / (x_hi - x_lo) * area.width)),
        area.y + area.height -
            static_cast<int>(std::lround((y - y_lo) / (y_hi - y_lo) * area.height)));
  };
  // Grid and ticks.
  const double xs_step = tickStep(x_hi - x_lo), ys_step = tickStep(y_hi - y_lo);
  for (double x = std::ceil(x_lo / xs_step) * xs_step; x <= x_hi; x += xs_step) {
    const cv::Point a = px(x, y_lo);
    cv::line(image, a, {a.x, area.y}, kGrid, 1);
    text(image, tickLabel(x), {a.x - 12, area.y + area.height + 18});
  }
  for (double y = std::ceil(y_lo / ys_step) * ys_step; y <= y_hi; y += ys_step) {
    const cv::Point a = px(x_lo, y);
    cv::line(image, a, {area.x + area.width, a.y}, kGrid, 1);
    text(image, tickLabel(y), {4, a.y + 5});
  }
  cv::rectangle(image, area, kInk, 1);
  text(image, title_, {area.x, 20}, 0.6);  // title on its own line, the y label below it
  text(image, x_label_, {area.x + area.width / 2 - 60, height_px - 15});
  text(image, y_label_, {4, area.y - 6});

  // Data, clipped to the axes.
  cv::Mat plot_area = image(area);
  const cv::Point offset(area.x, area.y);
  for (const auto& s : series_) {
    if (s.x.empty() && s.y.size() == 1) {  // horizontal reference
      cv::line(plot_area, px(x_lo, s.y[0]) - offset, px(x_hi, s.y[0]) - offset, s.bgr, 1,
               cv::LINE_AA);
      continue;
    }
    if (!s.cell_bgr.empty()) {  // a map of cells
      for (std::size_t k = 0; k < s.x.size(); ++k) {
        cv::rectangle(plot_area, px(s.x[k] - 0.5 * s.cell_w, s.y[k] - 0.5 * s.cell_h) - offset,
                      px(s.x[k] + 0.5 * s.cell_w, s.y[k] + 0.5 * s.cell_h) - offset, s.cell_bgr[k],
                      cv::FILLED);
      }
      continue;
    }
    bool have_previous = false;
    cv::Point previous;
    for (std::size_t k = 0; k < s.x.size(); ++k) {
      if (!std::isfinite(s.x[k]) || !std::isfinite(s.y[k])) {
        have_previous = false;
        continue;
      }
      const cv::Point p = px(s.x[k], s.y[k]) - offset;
      if (s.line && have_previous)
        cv::line(plot_area, previous, p, s.bgr, s.size, cv::LINE_AA);
      if (!s.line)
        cv::circle(plot_area, p, s.size, s.bgr, cv::FILLED, cv::LINE_AA);
      previous = p;
      have_previous = true;
    }
  }
  // Legend, top right inside the axes.
  int row = 0;
  for (const auto& s : series_) {
    if (s.name.empty())
      continue;
    const cv::Point at(area.x + area.width - 210, area.y + 18 + 18 * row++);
    cv::rectangle(image, {at.x - 6, at.y - 13}, {at.x + 205, at.y + 5}, cv::Scalar(255, 255, 255),
                  cv::FILLED);
    cv::line(image, {at.x, at.y - 4}, {at.x + 24, at.y - 4}, s.bgr, 3, cv::LINE_AA);
    text(image, s.name, {at.x + 30, at.y});
  }
  return image;
}

void LinePlot::save(const std::string& path, int width_px, int height_px) const {
  if (!cv::imwrite(path, render(width_px, height_px)))
    throw std::runtime_error("LinePlot: cannot write '" + path + "'");
}

cv::Scalar seriesColour(std::size_t k) {
  // Okabe-Ito (BGR): blue, orange, green, vermillion, purple, sky blue, yellow, black.
  static const cv::Scalar kCycle[] = {{178, 114, 0},   {0, 159, 230},  {115, 158, 0},  {0, 94, 213},
                                      {167, 121, 204}, {233, 180, 86}, {66, 228, 240}, {0, 0, 0}};
  return kCycle[k % (sizeof kCycle / sizeof kCycle[0])];
}

cv::Mat withColourKey(const cv::Mat& image, int colourmap, double lo, double hi,
                      const std::string& title) {
  constexpr int kKeyWidth = 110, kBarWidth = 22;
  cv::Mat bgr;
  if (image.channels() == 1)
    cv::cvtColor(image, bgr, cv::COLOR_GRAY2BGR);
  else
    bgr = image;
  cv::Mat out(bgr.rows, bgr.cols + kKeyWidth, CV_8UC3, cv::Scalar(255, 255, 255));
  bgr.copyTo(out(cv::Rect(0, 0, bgr.cols, bgr.rows)));
  const int top = 30, bottom = bgr.rows - 20, x0 = bgr.cols + 12;
  cv::Mat ramp(bottom - top, 1, CV_8UC1);
  for (int r = 0; r < ramp.rows; ++r)
    ramp.at<unsigned char>(r) =
        static_cast<unsigned char>(255 - (255 * r) / std::max(1, ramp.rows - 1));
  cv::Mat coloured;
  cv::applyColorMap(ramp, coloured, colourmap);
  cv::resize(coloured, coloured, {kBarWidth, ramp.rows}, 0, 0, cv::INTER_NEAREST);
  coloured.copyTo(out(cv::Rect(x0, top, kBarWidth, ramp.rows)));
  cv::rectangle(out, cv::Rect(x0, top, kBarWidth, ramp.rows), kInk, 1);
  for (int k = 0; k <= 4; ++k) {
    const double v = hi - (hi - lo) * k / 4.0;
    const int y = top + (ramp.rows - 1) * k / 4;
    cv::line(out, {x0 + kBarWidth, y}, {x0 + kBarWidth + 4, y}, kInk, 1);
    text(out, tickLabel(v), {x0 + kBarWidth + 7, y + 5}, 0.4);
  }
  text(out, title, {bgr.cols + 4, 18}, 0.45);
  return out;
}

}  // namespace report
}  // namespace needle_guidance
