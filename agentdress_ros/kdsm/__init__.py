"""KDSM: cloth embedded in a skinned tetrahedral mesh of the air around the body (papers/kdsm_skinning_3d_
parameterization.txt), ROS-free.

- `mesh`: the KDSM, a body-centred-cubic tet mesh of the body's thickened level set at beta0's rest pose, skinned
  with the closest body point's weights (Sec. 3); `lattice`, `levelset` are its parts.
- `embedding`: barycentric embedding, the fixed embedding of Fig. 3 and the per-frame kernel that re-embeds
  u^{m_o} + d(theta) and skins the four parent tet vertices (Sec. 4).
- `inverse`: inverse embedding of ground-truth drapes, Methods 1, 2 and the hybrid (Sec. 5).
- `surface`: the paper's baseline, offsets from the skinned body surface.

The training of the `kdsm` pose model (targets d(theta) from a sequence pack, the Table 1 analysis, the learned
d(theta) stored as the database group pose_model/kdsm) is offline code: offline.kdsm_training, offline.kdsm_model.
"""
from .embedding import Embedding, KdsmPoser, embed, unembed
from .mesh import KDSM, KDSMSettings, build_kdsm, load_kdsm, save_kdsm

__all__ = ["KDSM", "KDSMSettings", "Embedding", "KdsmPoser", "build_kdsm", "embed", "unembed", "load_kdsm",
           "save_kdsm"]
