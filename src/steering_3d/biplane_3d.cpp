// Information fusion of two orthogonal views with a chi-square gate (biplane_3d.h).
#include "needle_guidance/steering_3d/biplane_3d.h"

#include <Eigen/Cholesky>
#include <sstream>

namespace needle_guidance::steering_3d {
namespace {

/// Rows of frame scene axes a view measures: (x, y) along z, (x, z) along y.
Eigen::Matrix<double, 2, 3> observation(ViewAxis axis) {
  Eigen::Matrix<double, 2, 3> H = Eigen::Matrix<double, 2, 3>::Zero();
  H(0, 0) = 1.0;
  H(1, axis == ViewAxis::kAlongZ ? 1 : 2) = 1.0;
  return H;
}

bool valid(const ViewDetection& v) {
  if (!v.p_m.allFinite() || !v.covariance_m2.allFinite() ||
      (v.covariance_m2 - v.covariance_m2.transpose()).norm() > 1e-12 * v.covariance_m2.norm()) {
    return false;
  }
  const Eigen::LLT<Eigen::Matrix2d> llt(v.covariance_m2);
  return llt.info() == Eigen::Success;
}

}  // namespace

Result<TipEstimate3, BiplaneStatus> triangulateBiplane(const ViewDetection& a,
                                                       const ViewDetection& b, double gate) {
  if (!valid(a) || !valid(b)) {
    return BiplaneStatus(BiplaneCode::kBadInput,
                         "biplane: a detection is not finite or its covariance is not positive "
                         "definite");
  }
  if (a.axis == b.axis) {
    return BiplaneStatus(BiplaneCode::kBadInput, "biplane: both views look along the same axis");
  }
  Matrix3 information = Matrix3::Zero();
  Vector3 weighted = Vector3::Zero();
  for (const ViewDetection* v : {&a, &b}) {
    const Eigen::Matrix<double, 2, 3> H = observation(v->axis);
    const Eigen::Matrix2d R_inv = v->covariance_m2.inverse();
    information += H.transpose() * R_inv * H;
    weighted += H.transpose() * R_inv * v->p_m;
  }
  TipEstimate3 out;
  out.covariance_m2 = information.inverse();
  out.p_SceneTip = out.covariance_m2 * weighted;
  for (const ViewDetection* v : {&a, &b}) {
    const Eigen::Vector2d r = v->p_m - observation(v->axis) * out.p_SceneTip;
    out.chi_square += r.dot(v->covariance_m2.inverse() * r);
  }
  if (!(out.chi_square <= gate)) {
    std::ostringstream os;
    os << "biplane: views disagree (chi-square " << out.chi_square << " > gate " << gate << "; x "
       << a.p_m.x() * 1e3 << " vs " << b.p_m.x() * 1e3 << " mm): not fused";
    return BiplaneStatus(BiplaneCode::kDisagree, os.str());
  }
  return out;
}

}  // namespace needle_guidance::steering_3d
