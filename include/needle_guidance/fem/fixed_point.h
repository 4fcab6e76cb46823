// Anderson acceleration of a fixed-point iteration x = T(x) (Walker and Ni 2011, "type II"):
// the next iterate mixes the last m images T(x_k) with the weights that minimise the linear
// combination of the last residuals T(x_k) - x_k. A plain iteration converges only while T
// contracts; the corotational equilibrium u = K^-1 f + v(u) of a slender, bending body has
// near-unit oscillating modes that the plain iteration does not damp and this one removes.
#pragma once

#include <Eigen/Core>
#include <deque>

namespace needle_guidance::fem {

class AndersonAcceleration {
public:
  /// memory: how many past residual differences are mixed (>= 1).
  explicit AndersonAcceleration(int memory = 5) : memory_(memory < 1 ? 1 : memory) {}
  /// Given the current iterate x and its image t = T(x), returns the next iterate.
  Eigen::VectorXd next(const Eigen::VectorXd& x, const Eigen::VectorXd& t);
  /// Forgets the history (the map T changed).
  void reset();

private:
  int memory_;
  Eigen::VectorXd last_residual_, last_image_;
  std::deque<Eigen::VectorXd> d_residual_, d_image_;
};

}  // namespace needle_guidance::fem
