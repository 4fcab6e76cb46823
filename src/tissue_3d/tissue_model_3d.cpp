// TissueModel3: the tetrahedral mesh and its embedding tissue (stiffness assembly, the factored
// compliance and the element locator of fem::EmbeddingTissue) (needle_insertion_3d.h).
#include "needle_guidance/tissue_3d/needle_insertion_3d.h"

namespace needle_guidance::tissue_3d {

TissueModel3::TissueModel3(TetMesh3 mesh, const std::vector<fem::Material>& materials,
                           bool corotational)
    : mesh_(std::move(mesh)) {
  embedding_ = std::make_unique<fem::EmbeddingTissue<3>>(mesh_, mesh_.node_fixed, materials, 1.0,
                                                         corotational);
}

TissueModel3::~TissueModel3() = default;

}  // namespace needle_guidance::tissue_3d
