"""Rotation helpers in pure numpy, vectorised over leading axes.

Conventions: radians; a rotation vector is axis * angle (right-handed); matrices act on column vectors
(``v_world = R @ v_local``). Euler angles are *intrinsic* rotations applied in the order the axes are named,
as BVH files use them: ``euler_to_matrix((a, b, c), "ZYX") == Rz(a) @ Ry(b) @ Rx(c)``
(scipy's ``Rotation.from_euler("ZYX", ...)``, upper case = intrinsic).
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "axis_angle_matrix",
    "euler_to_matrix",
    "matrix_to_quaternion",
    "matrix_to_rotvec",
    "quaternion_to_matrix",
    "quaternion_to_rotvec",
    "rotation_between",
    "rotvec_to_matrix",
    "wrap_rotvec",
]

# Below this angle the Taylor series of sin(x)/x and (1-cos x)/x^2 are exact to float64 precision.
_SMALL_ANGLE = 1e-4


def rotvec_to_matrix(rotvecs) -> np.ndarray:
    """Rodrigues' formula. rotvecs (..., 3) -> matrices (..., 3, 3).

    Uses Taylor series for small angles so the result stays accurate (and differentiable) near zero.
    """
    v = np.asarray(rotvecs, dtype=np.float64)
    theta2 = np.einsum("...i,...i->...", v, v)
    theta = np.sqrt(theta2)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    # a = sin(t)/t, b = (1 - cos t)/t^2
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - np.cos(safe)) / (safe * safe))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(v.shape[:-1] + (3, 3))
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def matrix_to_quaternion(matrices) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) as (x, y, z, w) with w >= 0.

    Shepperd's method: pick the largest of the four squared components as the pivot, which keeps the
    division well conditioned for every rotation (including angles near pi, where w -> 0).
    """
    m = np.asarray(matrices, dtype=np.float64)
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = np.stack([m00, m11, m22, trace], axis=-1)
    pivot = np.argmax(candidates, axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    # Pivot on x, y or z.
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        sel = pivot == i
        if np.any(sel):
            mi = m[sel]
            qi = np.sqrt(np.maximum(1.0 + 2.0 * mi[:, i, i] - (mi[:, 0, 0] + mi[:, 1, 1] + mi[:, 2, 2]), 0.0)) * 0.5
            qs = np.empty((mi.shape[0], 4))
            qs[:, i] = qi
            qs[:, j] = (mi[:, j, i] + mi[:, i, j]) / (4.0 * qi)
            qs[:, k] = (mi[:, k, i] + mi[:, i, k]) / (4.0 * qi)
            qs[:, 3] = (mi[:, k, j] - mi[:, j, k]) / (4.0 * qi)
            q[sel] = qs
    sel = pivot == 3
    if np.any(sel):
        mi = m[sel]
        w = np.sqrt(np.maximum(1.0 + mi[:, 0, 0] + mi[:, 1, 1] + mi[:, 2, 2], 0.0)) * 0.5
        q[sel] = np.stack(
            [
                (mi[:, 2, 1] - mi[:, 1, 2]) / (4.0 * w),
                (mi[:, 0, 2] - mi[:, 2, 0]) / (4.0 * w),
                (mi[:, 1, 0] - mi[:, 0, 1]) / (4.0 * w),
                w,
            ],
            axis=-1,
        )
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def quaternion_to_matrix(quaternions) -> np.ndarray:
    """Unit quaternions (..., 4) as (x, y, z, w) -> rotation matrices (..., 3, 3)."""
    x, y, z, w = np.moveaxis(np.asarray(quaternions, dtype=np.float64), -1, 0)
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                     2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                     2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1).reshape(
        np.shape(quaternions)[:-1] + (3, 3))


def quaternion_to_rotvec(quaternions) -> np.ndarray:
    """Unit quaternions (..., 4) as (x, y, z, w) -> rotation vectors (..., 3) with angle in [0, pi]."""
    q = np.asarray(quaternions, dtype=np.float64)
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    xyz = q[..., :3]
    s = np.linalg.norm(xyz, axis=-1)
    # atan2 is accurate at both ends (s -> 0 and w -> 0), unlike acos(w) or asin(s).
    angle = 2.0 * np.arctan2(s, q[..., 3])
    small = s < 1e-12
    scale = np.where(small, 2.0 / np.where(small, q[..., 3], 1.0), angle / np.where(small, 1.0, s))
    return xyz * scale[..., None]


def matrix_to_rotvec(matrices) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3), angle in [0, pi]."""
    return quaternion_to_rotvec(matrix_to_quaternion(matrices))


def axis_angle_matrix(axis, angle) -> np.ndarray:
    """Rotation about a (not necessarily unit) axis (..., 3) by angle (...) radians -> (..., 3, 3)."""
    axis = np.asarray(axis, dtype=np.float64)
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return rotvec_to_matrix(unit * np.asarray(angle, dtype=np.float64)[..., None])


_AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2}


def euler_to_matrix(angles, order: str = "ZYX") -> np.ndarray:
    """Intrinsic Euler angles (..., 3) in radians, applied in ``order`` -> matrices (..., 3, 3).

    ``angles[..., i]`` is the rotation about axis ``order[i]``; the result is R_order[0] @ R_order[1] @ R_order[2].
    """
    order = order.upper()
    if len(order) != 3 or any(c not in _AXIS_INDEX for c in order):
        raise ValueError(f"Euler order must be three of X, Y, Z (e.g. 'ZYX'), got {order!r}")
    angles = np.asarray(angles, dtype=np.float64)
    result = None
    for i, name in enumerate(order):
        axis = np.zeros(3)
        axis[_AXIS_INDEX[name]] = 1.0
        r = rotvec_to_matrix(angles[..., i : i + 1] * axis)
        result = r if result is None else result @ r
    return result


def wrap_rotvec(rotvecs) -> np.ndarray:
    """Same rotations with the angle wrapped into [0, pi]. rotvecs (..., 3) -> (..., 3).

    An angle theta in (pi, 2 pi) about axis n equals 2 pi - theta about -n.
    """
    v = np.asarray(rotvecs, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1, keepdims=True)
    wrapped = np.mod(theta, 2.0 * np.pi)
    # Signed angle in (-pi, pi]: a negative value flips the axis, so the angle |wrapped| lies in [0, pi].
    wrapped = np.where(wrapped > np.pi, wrapped - 2.0 * np.pi, wrapped)
    safe = np.where(theta > 0.0, theta, 1.0)
    return v / safe * wrapped


def rotation_between(source, target) -> np.ndarray:
    """Minimal rotation taking direction ``source`` to direction ``target``. (..., 3), (..., 3) -> (..., 3, 3).

    Inputs need not be unit length (zero vectors give the identity). Antiparallel inputs rotate by pi about
    an axis perpendicular to ``source``.
    """
    a = np.asarray(source, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    na = np.linalg.norm(a, axis=-1, keepdims=True)
    nb = np.linalg.norm(b, axis=-1, keepdims=True)
    degenerate = (na[..., 0] < 1e-12) | (nb[..., 0] < 1e-12)
    a = a / np.where(na < 1e-12, 1.0, na)
    b = b / np.where(nb < 1e-12, 1.0, nb)
    cross = np.cross(a, b)
    sin = np.linalg.norm(cross, axis=-1)
    cos = np.einsum("...i,...i->...", a, b)
    angle = np.arctan2(sin, cos)
    # A perpendicular axis for the (anti)parallel case: cross with the basis vector least aligned with a.
    basis = np.eye(3)[np.argmin(np.abs(a), axis=-1)]
    perpendicular = np.cross(a, basis)
    perpendicular /= np.maximum(np.linalg.norm(perpendicular, axis=-1, keepdims=True), 1e-300)
    axis = np.where((sin < 1e-12)[..., None], perpendicular, cross / np.maximum(sin, 1e-300)[..., None])
    angle = np.where(degenerate, 0.0, angle)
    return rotvec_to_matrix(axis * angle[..., None])
