"""Body surfaces and garment positions along a motion, for the animated collider.

Pure functions over the body model and a garment; no newton import.
"""
from __future__ import annotations

import numpy as np

from ..body.model import visible_body


def posed_surfaces(body, garment, shape, rotvecs, root_translation=None):
    """Body surfaces (K, N, 3) and skinned garments (K, V, 3) of K poses rotvecs (K, B, 3), root (K, 3) or None.

    shape: one body shape for every pose, or a list of K shapes (a body that changes shape as it moves)."""
    from ..body.kinematics import linear_blend_skinning

    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    roots = np.zeros((len(rotvecs), 3)) if root_translation is None else np.asarray(root_translation, np.float64)
    shapes = list(shape) if isinstance(shape, (list, tuple)) else [shape] * len(rotvecs)
    if len(shapes) != len(rotvecs):
        raise ValueError(f"{len(shapes)} shapes for {len(rotvecs)} poses")
    ids, _ = visible_body(body)
    bodies = np.empty((len(rotvecs), len(ids), 3))
    garments = np.empty((len(rotvecs), garment.n_vertices, 3))
    rests: dict = {}  # the garment's rest shape, once per distinct body shape
    for k, (pose, root, current) in enumerate(zip(rotvecs, roots, shapes)):
        if id(current) not in rests:
            rests[id(current)] = garment.rest_vertices(body, current)
        transforms, _ = body.pose(current, pose, root)
        bodies[k] = body.posed_vertices(current, transforms)[ids]
        linear_blend_skinning(rests[id(current)], garment.skin_indices, garment.skin_weights, transforms, garments[k])
    return bodies, garments


def _ramp(start, end, frames: int) -> np.ndarray:
    """(frames, ...) values from `start` towards `end` at t = 0, 1/frames, ..., excluding `end` itself."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    t = (np.arange(frames, dtype=np.float64) / max(frames, 1)).reshape((-1,) + (1,) * end.ndim)
    return start[None] + t * (end - start)[None]


def ramp_poses(pose, frames: int) -> np.ndarray:
    """Poses (frames, B, 3) from the rest pose towards `pose` (B, 3), excluding `pose` itself.

    Each bone's rotation vector is scaled by t in [0, 1): the slerp from the identity, so limbs swing along arcs
    and keep their length (a linear blend of vertex positions would shrink them).
    """
    return _ramp(np.zeros_like(np.asarray(pose, dtype=np.float64)), pose, frames)


def ramp_between(beta_from, pose_from, beta_to, pose_to, frames: int) -> tuple:
    """(betas (frames, S), poses (frames, B, 3)) from one body shape and pose towards another, excluding the
    target: the keyframes that carry a finished drape onto another shape or a nearby pose.

    Shape parameters and rotation vectors are blended linearly; for a pose from a nearby frame (or the same pose on
    another shape) the rotation vectors differ little, where this is close to a slerp per bone.
    """
    return _ramp(beta_from, beta_to, frames), _ramp(pose_from, pose_to, frames)
