"""Joint sensitivities of the garment (AgentDress Eq. 7 and 11), measured by skinning at the rest pose.

delta_{y,m}^k: displacement of garment vertex y per radian of pose degree of freedom m (bone b = m // 3, axis
m % 3), at the rest pose of training shape k, by central finite differences of the garment's linear blend
skinning. Skinning, not simulation: it is what moves the garment first-order, it is exact and costs milliseconds.
"""
from __future__ import annotations

import numpy as np

from ..body import AnnyBody
from ..body.kinematics import linear_blend_skinning
from ..garment import Garment


def vertex_sensitivity(body: AnnyBody, garment: Garment, shapes: np.ndarray, step: float = 1e-4) -> np.ndarray:
    """delta-bar_{y,m} (V, D): per garment vertex and pose dof, the mean over shapes (K, 6) of |d y / d theta_m|."""
    n_dof = 3 * body.n_bones
    total = np.zeros((garment.n_vertices, n_dof))
    out_plus = np.empty((garment.n_vertices, 3))
    out_minus = np.empty((garment.n_vertices, 3))
    for beta in shapes:
        shape = body.shape(beta)
        rest = garment.rest_vertices(body, shape)
        for m in range(n_dof):
            rotvecs = np.zeros((body.n_bones, 3))
            rotvecs[m // 3, m % 3] = step
            plus, _ = body.pose(shape, rotvecs)
            rotvecs[m // 3, m % 3] = -step
            minus, _ = body.pose(shape, rotvecs)
            linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, plus, out_plus)
            linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, minus, out_minus)
            total[:, m] += np.linalg.norm(out_plus - out_minus, axis=1) / (2.0 * step)
    return total / len(shapes)


def joint_weights(sensitivity: np.ndarray) -> np.ndarray:
    """s^L of Eq. 11 spread over its three dofs: (D,) where entry m holds s^{L(m)} = sum_y sum_{m' in L} delta."""
    per_joint = sensitivity.sum(axis=0).reshape(-1, 3).sum(axis=1)
    return np.repeat(per_joint, 3)


def region_dof_influence(sensitivity: np.ndarray, regions: np.ndarray) -> np.ndarray:
    """Q_{g,m} of Eq. 7: (R, D) = sum_y w_{g,y} delta-bar_{y,m}^2, with regions (V, R)."""
    return regions.T @ (sensitivity**2)
