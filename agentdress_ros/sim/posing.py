"""Body surfaces and garment positions along a motion, for the animated collider.

Pure functions over the body model and a garment; no newton import.
"""
from __future__ import annotations

import numpy as np


def visible_body(body):
    """(vertex ids (N,), faces (G, 3) re-indexed onto them): the closed body surface a collider uses."""
    ids = body.body_vertex_ids
    remap = np.full(len(body.assets.template), -1)
    remap[ids] = np.arange(len(ids))
    return ids, remap[body.body_faces]


def posed_surfaces(body, garment, shape, rotvecs, root_translation=None):
    """Body surfaces (K, N, 3) and skinned garments (K, V, 3) of K poses rotvecs (K, B, 3), root (K, 3) or None."""
    from ..body.kinematics import linear_blend_skinning

    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    roots = np.zeros((len(rotvecs), 3)) if root_translation is None else np.asarray(root_translation, np.float64)
    ids, _ = visible_body(body)
    rest = garment.rest_vertices(body, shape)
    bodies = np.empty((len(rotvecs), len(ids), 3))
    garments = np.empty((len(rotvecs),) + rest.shape)
    for k, (pose, root) in enumerate(zip(rotvecs, roots)):
        transforms, _ = body.pose(shape, pose, root)
        bodies[k] = body.posed_vertices(shape, transforms)[ids]
        linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, transforms, garments[k])
    return bodies, garments


def ramp_poses(pose, frames: int) -> np.ndarray:
    """Poses (frames, B, 3) from the rest pose towards `pose` (B, 3), excluding `pose` itself.

    Each bone's rotation vector is scaled by t in [0, 1): the slerp from the identity, so limbs swing along arcs
    and keep their length (a linear blend of vertex positions would shrink them).
    """
    t = np.arange(frames, dtype=np.float64) / max(frames, 1)
    return t[:, None, None] * np.asarray(pose, dtype=np.float64)[None]
