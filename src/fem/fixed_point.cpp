// Anderson acceleration (fixed_point.h).
#include "needle_guidance/fem/fixed_point.h"

#include <Eigen/QR>

namespace needle_guidance::fem {

Eigen::VectorXd AndersonAcceleration::next(const Eigen::VectorXd& x, const Eigen::VectorXd& t) {
  const Eigen::VectorXd r = t - x;
  if (last_residual_.size() == r.size()) {
    d_residual_.push_back(r - last_residual_);
    d_image_.push_back(t - last_image_);
    if (static_cast<int>(d_residual_.size()) > memory_) {
      d_residual_.pop_front();
      d_image_.pop_front();
    }
  } else {
    reset();
  }
  last_residual_ = r;
  last_image_ = t;
  const int m = static_cast<int>(d_residual_.size());
  if (m == 0) {
    return t;
  }
  Eigen::MatrixXd dr(r.size(), m), dt(r.size(), m);
  for (int j = 0; j < m; ++j) {
    dr.col(j) = d_residual_[static_cast<std::size_t>(j)];
    dt.col(j) = d_image_[static_cast<std::size_t>(j)];
  }
  const Eigen::VectorXd gamma = dr.colPivHouseholderQr().solve(r);
  if (!gamma.allFinite()) {
    reset();
    return t;
  }
  return t - dt * gamma;
}

void AndersonAcceleration::reset() {
  d_residual_.clear();
  d_image_.clear();
  last_residual_.resize(0);
  last_image_.resize(0);
}

}  // namespace needle_guidance::fem
