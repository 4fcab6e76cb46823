// TG-43 dose calculation for HDR brachytherapy sources (dissertation 6.2; AAPM TG-43 update,
// Rivard et al. 2004, and the AAPM/ESTRO high-energy consensus, Perez-Calatayud et al. 2012):
//   Ddot(r, theta) = S_K * Lambda * G_L(r, theta) / G_L(r0, theta0) * g_L(r) * F(r, theta)
// with the 2-D line-source formalism, or the 1-D point-source approximation
//   Ddot(r) = S_K * Lambda * (r0 / r)^2 * g_P(r) * phi_an(r).
// Units: SI inside (m, rad, s, Gy); S_K in U (1 U = 1 uGy m^2 h^-1 = 1 cGy cm^2 h^-1).
#pragma once

#include <Eigen/Core>
#include <string>
#include <vector>

namespace needle_guidance::dose {

using Point3 = Eigen::Vector3d;

enum class SourceModel { kLine, kPoint };

/// One source's consensus data, as read from config/sources/NAME/.
struct Tg43Data {
  std::string name;
  double dose_rate_constant_cGy_per_h_per_U = 0.0;  ///< Lambda [cGy h^-1 U^-1]
  double active_length_m = 0.0;                     ///< L [m]
  std::vector<double> gL_r_m;       ///< radial dose function abscissae [m], increasing
  std::vector<double> gL;           ///< g_L(r)
  std::vector<double> F_theta_rad;  ///< anisotropy rows [rad], increasing, 0..pi
  std::vector<double> F_r_m;        ///< anisotropy columns [m], increasing
  Eigen::MatrixXd F;                ///< F(theta_i, r_j)
};

class Tg43Source {
public:
  /// Validates the data (sizes, monotone abscissae, finite, positive Lambda and L).
  /// Throws std::invalid_argument naming the source and what is wrong.
  explicit Tg43Source(Tg43Data data);

  const Tg43Data& data() const { return data_; }
  const std::string& name() const { return data_.name; }

  /// Dose rate [Gy s^-1] per unit air-kerma strength [U] at distance r_m from the source centre
  /// and polar angle theta_rad from the source axis (0 = towards the distal tip). Finite for
  /// every r >= 0 and theta in [0, pi] (r -> 0 and on-axis points are handled, never NaN/inf).
  double doseRatePerU(double r_m, double theta_rad, SourceModel model = SourceModel::kLine) const;

  /// Same at point p for a source centred at `centre` whose unit axis `axis` points towards the
  /// distal tip (theta = 0).
  double doseRatePerU(const Point3& p, const Point3& centre, const Point3& axis,
                      SourceModel model = SourceModel::kLine) const;

private:
  Tg43Data data_;
  // precomputed values (geometry factor at the reference point, 1-D anisotropy function, ...)
  double g_ref_ = 0.0;
  std::vector<double> phi_an_;  ///< 1-D anisotropy function at F_r_m
};

/// Loads config/sources/NAME/ (source.yaml, radial_dose_gL.csv, anisotropy_F.csv) from the
/// package's config directory, or from `name_or_dir` if it is a directory. Throws
/// std::invalid_argument naming the file, line and reason for malformed data.
Tg43Source loadSource(const std::string& name_or_dir);

/// Names of the sources shipped in config/sources/.
std::vector<std::string> availableSources();

}  // namespace needle_guidance::dose
