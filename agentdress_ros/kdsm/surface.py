"""Offsets from the skinned body surface (Jin et al. 2020): the baseline of the KDSM paper's Table 2.

Each garment vertex is bound once, at the rest pose, to its closest body point within its own body regions (a
triangle and barycentric weights). In any pose its position is stored as an offset in that point's surface frame:
two tangents and the interpolated normal (the paper's UVN coordinates). The tangents are UV-like: a smooth rest
tangent field, carried into the pose by each triangle's own deformation (its edges), so neighbouring garment vertices
share nearly the same frame, as texture-space directions would. A regressor learns the offsets as a function of the
pose exactly as it learns the KDSM's plastic displacements (offline.kdsm_model.compare).

Shapes: V garment vertices, N body vertices, F body faces.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..garment.binding import SurfaceBinding, bind_with_clearance, vertex_normals


@dataclass(frozen=True)
class SurfaceAnchors:
    """Where each garment vertex sits on the body, and its rest tangent in the edge basis of its triangle."""

    triangles: np.ndarray  # (V, 3) body vertex ids
    barycentric: np.ndarray  # (V, 3)
    tangent_edges: np.ndarray  # (V, 2): rest tangent = a (p1 - p0) + b (p2 - p0)


def closest_in_groups(points, vertices, faces, face_groups=None, point_groups=None) -> SurfaceBinding:
    """Each point's (P, 3) closest point on the surface (vertices (N, 3), faces (F, 3)); with face_groups (F,) and
    point_groups (P, G) bool, only among the faces of the point's own groups (a torso vertex never binds to a hand
    resting on the torso)."""
    points = np.asarray(points, dtype=np.float64)
    if face_groups is None:
        return bind_with_clearance(points, vertices, faces)
    best = np.full(len(points), np.inf)
    triangles = np.zeros((len(points), 3), dtype=np.int32)
    barycentric = np.full((len(points), 3), np.nan)  # a point of no group: NaN
    offset = np.zeros(len(points))
    for g in range(point_groups.shape[1]):
        rows = np.flatnonzero(point_groups[:, g])
        group_faces = faces[face_groups == g]
        if len(rows) == 0 or len(group_faces) == 0:
            continue
        binding = bind_with_clearance(points[rows], vertices, group_faces)
        base = np.einsum("pk,pkd->pd", binding.barycentric, vertices[binding.triangles])
        distance = np.linalg.norm(points[rows] - base, axis=1)
        closer = distance < best[rows]
        rows = rows[closer]
        best[rows] = distance[closer]
        triangles[rows] = binding.triangles[closer]
        barycentric[rows] = binding.barycentric[closer]
        offset[rows] = binding.offset[closer]
    return SurfaceBinding(triangles, barycentric, offset)


def _edges(vertices, triangles):
    corners = vertices[triangles]
    return corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]


def anchor_garment(rest_garment, rest_body, faces, face_groups=None, point_groups=None,
                   up=(0.0, 1.0, 0.0)) -> SurfaceAnchors:
    """Bind the rest garment (V, 3) to the rest body (N, 3) and fix each vertex's rest tangent: the body's `up`
    direction projected on the tangent plane (the side direction where up is along the normal), written in its
    triangle's edge basis so that it deforms with the triangle."""
    binding = closest_in_groups(rest_garment, rest_body, faces, face_groups, point_groups)
    e1, e2 = _edges(rest_body, binding.triangles)
    normal = np.cross(e1, e2)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-15)
    tangent = np.asarray(up, dtype=np.float64) - normal * (normal @ np.asarray(up, dtype=np.float64))[:, None]
    side = np.cross(normal, np.array([1.0, 0.0, 0.0]))
    weak = np.linalg.norm(tangent, axis=1) < 0.3
    tangent[weak] = side[weak]
    # least squares in the triangle's plane: tangent = a e1 + b e2
    gram = np.stack([np.stack([(e1 * e1).sum(1), (e1 * e2).sum(1)], 1),
                     np.stack([(e2 * e1).sum(1), (e2 * e2).sum(1)], 1)], 1)
    rhs = np.stack([(tangent * e1).sum(1), (tangent * e2).sum(1)], 1)
    coefficients = np.linalg.solve(gram, rhs[:, :, None])[:, :, 0]
    return SurfaceAnchors(binding.triangles, binding.barycentric, coefficients)


def surface_frames(anchors: SurfaceAnchors, body_vertices, faces):
    """Surface points (V, 3) and orthonormal frames (V, 3, 3) (rows: tangent, bitangent, normal) of the anchors on a
    body posed as body_vertices (N, 3)."""
    weights = anchors.barycentric[:, :, None]
    origin = (body_vertices[anchors.triangles] * weights).sum(axis=1)
    normal = (vertex_normals(body_vertices, faces)[anchors.triangles] * weights).sum(axis=1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-15)
    e1, e2 = _edges(body_vertices, anchors.triangles)
    tangent = anchors.tangent_edges[:, :1] * e1 + anchors.tangent_edges[:, 1:] * e2
    tangent -= normal * (tangent * normal).sum(axis=1, keepdims=True)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-15)
    return origin, np.stack([tangent, np.cross(normal, tangent), normal], axis=1)


def to_surface(points, origin, frames) -> np.ndarray:
    """World points (..., V, 3) as offsets (..., V, 3) in their surface frames (origin (..., V, 3), frames
    (..., V, 3, 3))."""
    return np.einsum("...ij,...j->...i", frames, points - origin)


def from_surface(offsets, origin, frames) -> np.ndarray:
    """The inverse of to_surface: offsets (..., V, 3) back to world points (..., V, 3)."""
    return origin + np.einsum("...ij,...i->...j", frames, offsets)
