"""A dressed body: one shape, several garments, posed together by linear blend skinning into reused buffers."""
from __future__ import annotations

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody, BodyShape
from ..body.kinematics import linear_blend_skinning
from .garment import Garment


class Dressing:
    """Body and garments at one shape. `set_shape` refits everything (rare); `pose` is the per-frame path.

    After `pose`, `body_vertices` (N, 3) and `garment_vertices[i]` (V_i, 3) hold the posed meshes; the arrays are
    allocated once per shape and overwritten in place every frame.
    """

    def __init__(self, body: AnnyBody, garments: list[Garment], beta=REFERENCE_SHAPE, dtype=np.float32):
        self.body = body
        self.garments = list(garments)
        self.dtype = dtype
        # Only the visible body surface is posed (helper meshes are for fitting garments, not for display).
        self.body_ids = body.body_vertex_ids
        remap = np.full(len(body.assets.template), -1, dtype=np.int64)
        remap[self.body_ids] = np.arange(len(self.body_ids))
        self.body_faces = remap[body.body_faces].astype(np.int32)
        self._body_skin = (body.skin_indices[self.body_ids], body.skin_weights[self.body_ids].astype(dtype))
        self._garment_skin = [(g.skin_indices, g.skin_weights.astype(dtype)) for g in self.garments]
        self.set_shape(beta)

    def set_shape(self, beta) -> BodyShape:
        """Refit body and garments to `beta` (6,) at rest; returns the checked shape (see `BodyShape.clamped`)."""
        shape = self.body.shape(beta)
        self.shape = shape
        self.body_rest = np.ascontiguousarray(shape.vertices[self.body_ids], dtype=self.dtype)
        self.garment_rest = [np.ascontiguousarray(g.rest_vertices(self.body, shape), dtype=self.dtype)
                             for g in self.garments]
        self.body_vertices = np.empty_like(self.body_rest)
        self.garment_vertices = [np.empty_like(rest) for rest in self.garment_rest]
        return shape

    def pose(self, rotvecs, root_translation=None):
        """Pose body and garments: rotvecs (B, 3), root_translation (3,). Returns the skinning transforms (B, 3, 4)."""
        transforms, _ = self.body.pose(self.shape, rotvecs, root_translation)
        transforms = transforms.astype(self.dtype)
        linear_blend_skinning(self.body_rest, *self._body_skin, transforms, self.body_vertices)
        for rest, skin, out in zip(self.garment_rest, self._garment_skin, self.garment_vertices):
            linear_blend_skinning(rest, *skin, transforms, out)
        return transforms
