"""Forward kinematics and linear blend skinning as numba kernels (pure array functions).

Pose convention (see DESIGN.md): per bone the rotation vector `rotvecs[j]` (axis * angle) of its local rotation
R_j relative to its rest orientation, with every rest frame aligned with the world axes (as in SMPL), so the global
rotation is G_j = G_parent @ R_j; `root_translation` moves the root joint from its rest position. An all-zero pose
gives identity skinning transforms: the rest mesh.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, fastmath=False)
def rotvec_to_matrix(rotvec, out):
    """Rodrigues' formula for a (3,) rotation vector into out (3, 3); exact series near zero."""
    x, y, z = rotvec[0], rotvec[1], rotvec[2]
    angle2 = x * x + y * y + z * z
    if angle2 < 1e-12:
        # sin(a)/a ~ 1 - a^2/6, (1-cos a)/a^2 ~ 1/2 - a^2/24: no division by a tiny angle
        s = 1.0 - angle2 / 6.0
        c = 0.5 - angle2 / 24.0
    else:
        angle = np.sqrt(angle2)
        s = np.sin(angle) / angle
        c = (1.0 - np.cos(angle)) / angle2
    out[0, 0] = 1.0 - c * (y * y + z * z)
    out[0, 1] = c * x * y - s * z
    out[0, 2] = c * x * z + s * y
    out[1, 0] = c * x * y + s * z
    out[1, 1] = 1.0 - c * (x * x + z * z)
    out[1, 2] = c * y * z - s * x
    out[2, 0] = c * x * z - s * y
    out[2, 1] = c * y * z + s * x
    out[2, 2] = 1.0 - c * (x * x + y * y)


@numba.njit(cache=True)
def forward_kinematics(rotvecs, root_translation, rest_heads, parents, transforms):
    """Skinning transforms of a posed skeleton.

    rotvecs (B, 3), root_translation (3,), rest_heads (B, 3) joint positions at rest, parents (B,) with
    parents[j] < j and -1 for the root. Writes transforms (B, 3, 4): [G_j | p_j - G_j h_j], which maps a rest
    point rigidly attached to bone j to its posed position. Returns posed joint positions (B, 3).
    """
    n_bones = rotvecs.shape[0]
    local = np.empty((3, 3))
    globals_ = np.empty((n_bones, 3, 3))
    positions = np.empty((n_bones, 3))
    for j in range(n_bones):
        rotvec_to_matrix(rotvecs[j], local)
        p = parents[j]
        if p < 0:
            globals_[j] = local
            for a in range(3):
                positions[j, a] = rest_heads[j, a] + root_translation[a]
        else:
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += globals_[p, a, k] * local[k, b]
                    globals_[j, a, b] = acc
            for a in range(3):
                acc = positions[p, a]
                for k in range(3):
                    acc += globals_[p, a, k] * (rest_heads[j, k] - rest_heads[p, k])
                positions[j, a] = acc
        for a in range(3):
            offset = positions[j, a]
            for k in range(3):
                transforms[j, a, k] = globals_[j, a, k]
                offset -= globals_[j, a, k] * rest_heads[j, k]
            transforms[j, a, 3] = offset
    return positions


@numba.njit(cache=True, fastmath=True, inline="always")
def skin_point(x, y, z, skin_indices, skin_weights, row, transforms):
    """sum_k w_k T_{i_k} [x; y; z; 1] for the influences of `row` of skin_indices/skin_weights (zero weights
    skipped), as three scalars: the one skinning step of every kernel here and of the KDSM's."""
    ox = 0.0
    oy = 0.0
    oz = 0.0
    for k in range(skin_indices.shape[1]):
        w = skin_weights[row, k]
        if w == 0.0:
            continue
        b = skin_indices[row, k]
        ox += w * (transforms[b, 0, 0] * x + transforms[b, 0, 1] * y + transforms[b, 0, 2] * z + transforms[b, 0, 3])
        oy += w * (transforms[b, 1, 0] * x + transforms[b, 1, 1] * y + transforms[b, 1, 2] * z + transforms[b, 1, 3])
        oz += w * (transforms[b, 2, 0] * x + transforms[b, 2, 1] * y + transforms[b, 2, 2] * z + transforms[b, 2, 3])
    return ox, oy, oz


@numba.njit(cache=True, fastmath=True, inline="always")
def skin_vertex(rest, skin_indices, skin_weights, transforms, v):
    """sum_k w_vk T_{i_vk} [rest_v; 1] as three scalars (zero-weight slots skipped)."""
    return skin_point(rest[v, 0], rest[v, 1], rest[v, 2], skin_indices, skin_weights, v, transforms)


@numba.njit(cache=True, fastmath=True)
def linear_blend_skinning(rest, skin_indices, skin_weights, transforms, out):
    """out (V, 3) = sum_k w_vk T_{i_vk} [rest_v; 1] for rest (V, 3), skin_indices/weights (V, K), transforms (B, 3, 4).

    Zero-weight slots are skipped; dtype follows `out` (float32 or float64).
    """
    for v in range(skin_indices.shape[0]):
        out[v, 0], out[v, 1], out[v, 2] = skin_vertex(rest, skin_indices, skin_weights, transforms, v)
    return out


@numba.njit(cache=True, fastmath=True)
def linear_blend_skinning_into(rest, skin_indices, skin_weights, transforms, order, out):
    """`linear_blend_skinning` scattered: out[order[v]] = skinned vertex v (the engine's internal vertex order to
    the output order in the same pass; order (V,) int)."""
    for v in range(skin_indices.shape[0]):
        o = order[v]
        out[o, 0], out[o, 1], out[o, 2] = skin_vertex(rest, skin_indices, skin_weights, transforms, v)
    return out


def compact_skin_weights(indices: np.ndarray, weights: np.ndarray, max_influences: int = 4):
    """Keep the `max_influences` largest weights per vertex, renormalised: (V, K) -> (V, max_influences)."""
    order = np.argsort(-weights, axis=1)[:, :max_influences]
    top_w = np.take_along_axis(weights, order, axis=1).astype(np.float64)
    top_i = np.take_along_axis(indices, order, axis=1)
    total = top_w.sum(axis=1, keepdims=True)
    top_w = np.where(total > 0, top_w / np.where(total > 0, total, 1.0), 0.0)
    return np.ascontiguousarray(top_i, dtype=np.int32), np.ascontiguousarray(top_w)
