// Information fusion of two orthogonal views with a chi-square gate (biplane_3d.h).
#include "needle_guidance/needle_model/biplane_3d.h"

#include <Eigen/Cholesky>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace needle_guidance::needle_model {
namespace {

bool valid(const ViewDetection& v) {
  if (!v.p_m.allFinite() || !v.covariance_m2.allFinite() ||
      (v.covariance_m2 - v.covariance_m2.transpose()).norm() > 1e-12 * v.covariance_m2.norm()) {
    return false;
  }
  const Eigen::LLT<Eigen::Matrix2d> llt(v.covariance_m2);
  return llt.info() == Eigen::Success;
}

}  // namespace

Eigen::Matrix<double, 2, 3> viewRows(ViewAxis axis) {
  Eigen::Matrix<double, 2, 3> H = Eigen::Matrix<double, 2, 3>::Zero();
  H(0, 0) = 1.0;
  H(1, axis == ViewAxis::kAlongZ ? 1 : 2) = 1.0;
  return H;
}

TipPose3 tipFromViews(const Vector3& p_SceneTip, double heading_z_rad, double heading_y_rad,
                      const Vector3& bevel_hint) {
  // Each view sees the shaft's direction projected on its plane: (t_x, t_y) and (t_x, t_z).
  const Vector3 tangent =
      Vector3(1.0, std::tan(heading_z_rad), std::tan(heading_y_rad)).normalized();
  const Vector3 bevel =
      std::abs(bevel_hint.normalized().dot(tangent)) < 0.99 ? bevel_hint : tangent.unitOrthogonal();
  return makeTipPose(p_SceneTip, tangent, bevel);
}

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
    const Eigen::Matrix<double, 2, 3> H = viewRows(v->axis);
    const Eigen::Matrix2d R_inv = v->covariance_m2.inverse();
    information += H.transpose() * R_inv * H;
    weighted += H.transpose() * R_inv * v->p_m;
  }
  TipEstimate3 out;
  out.covariance_m2 = information.inverse();
  out.p_SceneTip = out.covariance_m2 * weighted;
  for (const ViewDetection* v : {&a, &b}) {
    const Eigen::Vector2d r = v->p_m - viewRows(v->axis) * out.p_SceneTip;
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

void BiplaneImaging3::validate() const {
  const auto require = [](bool ok, const char* what) {
    if (!ok) {
      throw std::invalid_argument(std::string("BiplaneImaging3: ") + what);
    }
  };
  require(sigma_position_m > 0.0 && std::isfinite(sigma_position_m),
          "sigma_position_m must be finite and > 0");
  require(sigma_heading_rad >= 0.0 && std::isfinite(sigma_heading_rad),
          "sigma_heading_rad must be finite and >= 0");
  require(dropout >= 0.0 && dropout <= 1.0, "dropout must be in [0, 1]");
  require(outlier >= 0.0 && outlier <= 1.0, "outlier must be in [0, 1]");
  require(outlier_offset_m >= 0.0 && std::isfinite(outlier_offset_m),
          "outlier_offset_m must be finite and >= 0");
  require(gate > 0.0, "gate must be > 0");
}

BiplaneObserver3::BiplaneObserver3(BiplaneImaging3 imaging, std::uint64_t seed)
    : imaging_(imaging), rng_(seed) {
  imaging_.validate();
}

ViewDetection BiplaneObserver3::detect(const TipPose3& truth, ViewAxis axis, double& heading_rad,
                                       bool& found) {
  // Always six draws per view (the same stream whatever happens).
  const double z0 = normal_(rng_), z1 = normal_(rng_), zh = normal_(rng_);
  const double u_drop = unit_(rng_), u_out = unit_(rng_), u_dir = unit_(rng_);
  ViewDetection v;
  v.axis = axis;
  const Eigen::Vector2d p = viewRows(axis) * truth.p_SceneTip;
  const Eigen::Vector2d t = viewRows(axis) * truth.tangent();
  const double sigma = imaging_.sigma_position_m;
  v.p_m = p + sigma * Eigen::Vector2d(z0, z1);
  if (u_out < imaging_.outlier) {
    constexpr double kTwoPi = 6.283185307179586;
    v.p_m += imaging_.outlier_offset_m *
             Eigen::Vector2d(std::cos(kTwoPi * u_dir), std::sin(kTwoPi * u_dir));
  }
  v.covariance_m2 = sigma * sigma * Eigen::Matrix2d::Identity();
  heading_rad = std::atan2(t.y(), t.x()) + imaging_.sigma_heading_rad * zh;
  found = u_drop >= imaging_.dropout;
  return v;
}

Result<TipPose3, BiplaneStatus> BiplaneObserver3::observe(const TipPose3& truth,
                                                          const TipPose3& predicted) {
  double heading_z = 0.0, heading_y = 0.0;
  bool found_z = false, found_y = false;
  const ViewDetection along_z = detect(truth, ViewAxis::kAlongZ, heading_z, found_z);
  const ViewDetection along_y = detect(truth, ViewAxis::kAlongY, heading_y, found_y);
  if (!found_z || !found_y) {
    return BiplaneStatus(
        BiplaneCode::kNoDetection,
        std::string("biplane: no tip in the view along ") + (!found_z ? "z" : "y"));
  }
  const auto fused = triangulateBiplane(along_z, along_y, imaging_.gate);
  if (!fused) {
    return fused.status();
  }
  return tipFromViews(fused.value().p_SceneTip, heading_z, heading_y, predicted.bevel());
}

}  // namespace needle_guidance::needle_model
