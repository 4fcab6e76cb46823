// Needle insertion into 3-D tissue (dissertation 2.3.3-2.3.6 and 2.4, in 3-D): the embedded-track
// insertion of fem::EmbeddedNeedle (embedded_needle.h, the same algorithm the 2-D tissue uses) on
// a tetrahedral mesh. The mesh never changes: the needle acts through constraints on tissue points
// embedded in tetrahedra, solved on the condensed compliance of those points, so a step's cost
// grows with the number of needle points, not with the mesh. Events (puncture, a new track
// point, stick to slip) are located where they happen within a step, so the result does not
// depend on the step length.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "needle_guidance/fem/condensed_compliance.h"
#include "needle_guidance/fem/embedded_needle.h"
#include "needle_guidance/tissue_3d/scene_tissue_3d.h"
#include "needle_guidance/tissue_3d/tet_mesh_3d.h"

namespace needle_guidance::tissue_3d {

/// A tissue point embedded in a tetrahedron.
using EmbeddedPoint = fem::EmbeddedPoint<3>;

/// The FEM tissue: mesh, stiffness factored once, and a locator for embedded points.
class TissueModel3 {
public:
  /// Throws std::invalid_argument if the mesh is invalid or not held by fixed nodes.
  /// corotational: the elements follow their rotation (scene key `tissue.model`).
  TissueModel3(TetMesh3 mesh, const std::vector<fem::Material>& materials,
               bool corotational = false);
  ~TissueModel3();
  const TetMesh3& mesh() const { return mesh_; }
  fem::CondensedCompliance& compliance() { return embedding_->compliance(); }
  const fem::CondensedCompliance& compliance() const { return embedding_->compliance(); }
  /// The element containing p (reference), or nullopt outside the mesh.
  std::optional<EmbeddedPoint> locate(const Vector3& p) const { return embedding_->locate(p); }
  const fem::EmbeddingTissue<3>& embedding() const { return *embedding_; }
  double assemblyCpuSeconds() const { return embedding_->assemblyCpuSeconds(); }
  bool corotational() const { return embedding_->corotational(); }
  /// fem::EmbeddingTissue::corotationDisplacement: the corotational part of the displacement
  /// at u [m] (empty for a linear model).
  Eigen::VectorXd corotationDisplacement(const Eigen::VectorXd& u) const {
    return embedding_->corotationDisplacement(u);
  }
  int invertedElements() const { return embedding_->invertedElements(); }
  double corotationCpuSeconds() const { return embedding_->corotationCpuSeconds(); }

private:
  TetMesh3 mesh_;
  std::unique_ptr<fem::EmbeddingTissue<3>> embedding_;
};

/// Figures of the last move, for reports.
using InsertionInfo3 = fem::EmbeddedNeedleInfo;

/// The embedded-track needle on a tetrahedral tissue; lateral position (y, z).
class NeedleInsertion3 : public fem::EmbeddedNeedle<3> {
public:
  /// The needle moves along +x at lateral position (y, z); the tissue's entry face is x =
  /// entry_x_m; the tip goes no deeper than max_tip_x_m (the compliance columns along the
  /// needle line are solved up to there in one batch when the needle enters).
  /// event_warp_tolerance_m: fem::EmbeddedNeedleParams::event_warp_tolerance_m (corotational
  /// tissue; the default is the simulation's). Throws std::invalid_argument for invalid
  /// parameters.
  NeedleInsertion3(
      TissueModel3& model, const Needle3& needle, double entry_x_m, double max_tip_x_m,
      double event_warp_tolerance_m = fem::EmbeddedNeedleParams{}.event_warp_tolerance_m);
};

}  // namespace needle_guidance::tissue_3d
