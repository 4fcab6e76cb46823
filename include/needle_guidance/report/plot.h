// Small PNG plots drawn with OpenCV, so that a procedure's report (written by a node, a bench or
// a test) has its figures without Python: line plots with axes, ticks, labels and a legend, and
// a colour key for maps.
#pragma once

#include <opencv2/core.hpp>

#include <string>
#include <vector>

namespace needle_guidance {
namespace report {

/// A line / scatter plot. Series are drawn in the order added; the axes cover every finite
/// point (non-finite points are skipped, never drawn).
class LinePlot {
public:
  LinePlot(std::string title, std::string x_label, std::string y_label);

  /// A polyline through (x[k], y[k]); throws std::invalid_argument if the sizes differ.
  void addLine(const std::string& name, const std::vector<double>& x, const std::vector<double>& y,
               const cv::Scalar& bgr, int thickness = 2);
  /// Markers at (x[k], y[k]) (filled circles).
  void addPoints(const std::string& name, const std::vector<double>& x,
                 const std::vector<double>& y, const cv::Scalar& bgr, int radius = 4);
  /// A map: a filled cell of cell_w x cell_h centred on each (x[k], y[k]), coloured by value[k]
  /// on `colourmap` (cv::ColormapTypes) from lo to hi; pair the figure with withColourKey.
  /// Throws std::invalid_argument if the sizes differ or lo >= hi.
  void addCells(const std::vector<double>& x, const std::vector<double>& y,
                const std::vector<double>& value, double cell_w, double cell_h, int colourmap,
                double lo, double hi);
  /// A horizontal reference line (e.g. a tolerance) with its name in the legend.
  void addHorizontal(const std::string& name, double y, const cv::Scalar& bgr);
  /// Fixes an axis range instead of fitting the data.
  void setXRange(double lo, double hi);
  void setYRange(double lo, double hi);

  /// The figure (BGR, 8-bit).
  cv::Mat render(int width_px = 800, int height_px = 500) const;
  /// Renders and writes a PNG; throws std::runtime_error naming the path if it cannot.
  void save(const std::string& path, int width_px = 800, int height_px = 500) const;

private:
  struct Series {
    std::string name;
    std::vector<double> x, y;
    cv::Scalar bgr;
    int size = 2;
    bool line = true;
    std::vector<cv::Scalar> cell_bgr;  ///< non-empty: a map of cells
    double cell_w = 0.0, cell_h = 0.0;
  };
  std::string title_, x_label_, y_label_;
  std::vector<Series> series_;
  bool fixed_x_ = false, fixed_y_ = false;
  double x_lo_ = 0.0, x_hi_ = 1.0, y_lo_ = 0.0, y_hi_ = 1.0;
};

/// A distinct colour for series k (a fixed, colour-blind-friendly cycle).
cv::Scalar seriesColour(std::size_t k);

/// Draws a vertical colour key for a map coloured by `colourmap` (cv::ColormapTypes) from `lo`
/// to `hi` at the right edge of `image` (widening it), with tick labels and a title.
cv::Mat withColourKey(const cv::Mat& image, int colourmap, double lo, double hi,
                      const std::string& title);

}  // namespace report
}  // namespace needle_guidance
