"""Layered garments: an outer garment never passes inside an inner one (a T-shirt worn over trousers).

Like the paper's penetration handling against the body (Eq. 10), the outer garment is bound once - when the shape
changes - to the inner garment's surface: each outer vertex that lies over the inner garment gets the triangle of
the inner garment closest to it at rest (three vertex ids and barycentric weights). Every frame, the outer vertex
is pushed out along the inner surface's interpolated normal until it is at least `clearance` outside the bound
point: a fixed binding, no per-frame search. Outer vertices further than 10 cm from the inner garment at rest
(a T-shirt's chest above the trousers' waist) are not bound.

Pure array functions; shapes: V outer vertices, W inner vertices, G inner triangles, M bound outer vertices.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import trimesh
from scipy.spatial import cKDTree

__all__ = ["CLEARANCE", "LayerBinding", "bind_layers", "face_vertex_normals", "push_out_of_inner"]

#: Default gap kept between an outer garment and the inner one, metres.
CLEARANCE = 0.004


@dataclass(frozen=True)
class LayerBinding:
    """M outer vertices bound to a point of the inner garment's surface."""

    outer: np.ndarray  # (M,) int64 outer vertex ids
    triangles: np.ndarray  # (M, 3) int64 inner vertex ids of the carrying triangle
    barycentric: np.ndarray  # (M, 3) float32 weights, rows sum to 1

    def __len__(self) -> int:
        return len(self.outer)


def bind_layers(outer, inner, inner_faces, max_distance: float = 0.1, edge_margin: float = 0.0) -> LayerBinding:
    """Bind outer vertices (V, 3) to the inner garment (W, 3), (G, 3) at rest: every outer vertex whose closest
    inner point is within max_distance and at least edge_margin from the inner garment's open edges. The default
    binds at the edges too: a shirt's hem over the trousers' waist, which slides under it as the hips swing."""
    from ..garment.coverage import boundary_distance

    outer = np.asarray(outer, dtype=np.float64)
    inner = np.asarray(inner, dtype=np.float64)
    inner_faces = np.asarray(inner_faces, dtype=np.int64)
    near = cKDTree(inner).query(outer, distance_upper_bound=max_distance + 0.05)[0]
    ids = np.flatnonzero(np.isfinite(near))
    empty = LayerBinding(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
    if len(ids) == 0:
        return empty
    mesh = trimesh.Trimesh(inner, inner_faces, process=False)
    closest, distance, face_ids = trimesh.proximity.closest_point(mesh, outer[ids])
    triangles = inner_faces[face_ids]
    barycentric = np.clip(trimesh.triangles.points_to_barycentric(inner[triangles], closest), 0.0, 1.0)
    barycentric /= barycentric.sum(axis=1, keepdims=True)
    edge = (boundary_distance(inner, inner_faces)[triangles] * barycentric).sum(axis=1)
    keep = (distance <= max_distance) & (edge >= edge_margin)
    if not keep.any():
        return empty
    return LayerBinding(ids[keep].astype(np.int64), triangles[keep].astype(np.int64),
                        barycentric[keep].astype(np.float32))


@numba.njit(cache=True, nogil=True, fastmath=True)
def face_vertex_normals(vertices, faces, out):
    """Area-weighted unit vertex normals out (W, 3) of a triangle mesh vertices (W, 3), faces (G, 3)."""
    out[:] = 0.0
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        e1x = vertices[b, 0] - vertices[a, 0]
        e1y = vertices[b, 1] - vertices[a, 1]
        e1z = vertices[b, 2] - vertices[a, 2]
        e2x = vertices[c, 0] - vertices[a, 0]
        e2y = vertices[c, 1] - vertices[a, 1]
        e2z = vertices[c, 2] - vertices[a, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        for v in (a, b, c):
            out[v, 0] += nx
            out[v, 1] += ny
            out[v, 2] += nz
    for v in range(out.shape[0]):
        length = np.sqrt(out[v, 0] ** 2 + out[v, 1] ** 2 + out[v, 2] ** 2)
        if length > 0.0:
            out[v, 0] /= length
            out[v, 1] /= length
            out[v, 2] /= length
    return out


@numba.njit(cache=True, nogil=True, fastmath=True)
def _push(outer, inner, normals, ids, triangles, barycentric, clearance):
    pushed = 0
    for m in range(ids.shape[0]):
        px = py = pz = nx = ny = nz = 0.0
        for c in range(3):
            j = triangles[m, c]
            w = barycentric[m, c]
            px += w * inner[j, 0]
            py += w * inner[j, 1]
            pz += w * inner[j, 2]
            nx += w * normals[j, 0]
            ny += w * normals[j, 1]
            nz += w * normals[j, 2]
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length == 0.0:
            continue
        nx /= length
        ny /= length
        nz /= length
        i = ids[m]
        h = (outer[i, 0] - px) * nx + (outer[i, 1] - py) * ny + (outer[i, 2] - pz) * nz
        if h < clearance:
            d = clearance - h
            outer[i, 0] += d * nx
            outer[i, 1] += d * ny
            outer[i, 2] += d * nz
            pushed += 1
    return pushed


def push_out_of_inner(outer, inner, inner_faces, binding: LayerBinding, clearance: float = CLEARANCE,
                      normals=None) -> int:
    """Push the bound outer vertices (V, 3), in place, to at least `clearance` outside the posed inner garment
    (W, 3), (G, 3) along its interpolated vertex normal. normals: a (W, 3) buffer to reuse. Returns how many
    vertices moved."""
    if len(binding) == 0:
        return 0
    normals = np.empty_like(inner) if normals is None else normals
    face_vertex_normals(inner, inner_faces, normals)
    return int(_push(outer, inner, normals, binding.outer, binding.triangles, binding.barycentric,
                     outer.dtype.type(clearance)))
