"""Garment edges kept off the skin as drawn: hems, cuffs and collars never dip under the body they hang over.

The engine's penetration handling (Eq. 10) binds each garment vertex to the body once and keeps it outside its bound
point; near an open edge the cloth moves off the skin it was bound to (a sleeve's cuff swings, a hem rides up), and
the body faces there are drawn (they are uncovered in some poses), so the skin shows through the cloth in a
saw-tooth along the edge. Each frame, every garment vertex within a band of the open edges (at rest) is pushed out
of the tangent planes of the few body vertices closest to it at rest, skinned for this frame: a fixed binding of a
few hundred body vertices, no per-frame search, no full-body skinning.

Pure array functions; shapes: V garment vertices, M band vertices, K neighbours each, U bound body vertices,
B bones, I bone influences per body vertex.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..body.kinematics import skin_point, skin_vertex

__all__ = ["EDGE_BAND", "EDGE_CLEARANCE", "EDGE_NEIGHBORS", "MAX_PUSH", "SkinBinding", "bind_edges_to_skin",
           "push_off_skin"]

#: Garment vertices this close to an open edge (geodesically, at rest) are kept off the skin.
EDGE_BAND = 0.03
#: Distance kept between a band vertex and the tangent plane of each of its bound skin vertices, metres: the
#: display offset of the rest of the garment. 4 mm left 6 % fewer faces through the edges but lifted the edges
#: enough to show 9 % more of the hidden body under them (docs/notes/2026-12-07-edge-pokes.md).
EDGE_CLEARANCE = 0.002
#: Skin vertices each band vertex is bound to (their tangent planes together approximate the skin under it).
EDGE_NEIGHBORS = 4
#: The deepest a vertex may lie under a plane and still be pushed out of it, metres: a vertex farther under lies
#: across a fold of the body (an arm against the torso) or beyond the skin (a loose hem around the ankle, under
#: the plane of the foot's far side), not under that skin. Pushing those by a capped amount made a loose hem jagged.
MAX_PUSH = 0.02


@dataclass(frozen=True)
class SkinBinding:
    """M garment band vertices, each bound to K of U body vertices, and what skins those U for a frame."""

    band: np.ndarray  # (M,) int64 garment vertex ids
    neighbors: np.ndarray  # (M, K) int64 rows of the arrays below
    rest: np.ndarray  # (U, 3) float64 body vertices at rest (the shape's, as drawn)
    normals: np.ndarray  # (U, 3) float64 their unit normals at rest
    bones: np.ndarray  # (U, I) int64 bone ids
    weights: np.ndarray  # (U, I) float64 skinning weights

    def __len__(self) -> int:
        return len(self.band)


def bind_edges_to_skin(garment, edge_distance, skin, skin_normals, bones, weights,
                       band: float = EDGE_BAND, neighbors: int = EDGE_NEIGHBORS) -> SkinBinding:
    """Bind each garment vertex (V, 3) at rest whose edge_distance (V,) is under `band` to its `neighbors` closest
    skin vertices (N, 3) at rest (the drawn body: vertices of no drawn face left out by the caller), with their unit
    normals (N, 3) and skinning (bones, weights) (N, I)."""
    ids = np.flatnonzero(np.asarray(edge_distance) < band)
    k = min(int(neighbors), len(skin))
    if len(ids) == 0 or k == 0:
        empty = np.zeros((0, 3))
        return SkinBinding(ids.astype(np.int64), np.zeros((len(ids), 0), dtype=np.int64), empty, empty,
                           np.zeros((0, np.shape(bones)[1]), dtype=np.int64), np.zeros((0, np.shape(weights)[1])))
    _, closest = cKDTree(skin).query(np.asarray(garment, dtype=np.float64)[ids], k=k)
    closest = closest.reshape(len(ids), k)
    used, rows = np.unique(closest, return_inverse=True)  # skin only the body vertices that are bound
    return SkinBinding(ids.astype(np.int64), rows.reshape(closest.shape).astype(np.int64),
                       np.ascontiguousarray(skin[used], dtype=np.float64),
                       np.ascontiguousarray(skin_normals[used], dtype=np.float64),
                       np.ascontiguousarray(bones[used], dtype=np.int64),
                       np.ascontiguousarray(weights[used], dtype=np.float64))


@numba.njit(cache=True, nogil=True)
def _push(points, band, neighbors, rest, normals, bones, weights, transforms, clearance, max_push):
    n_skin = rest.shape[0]
    posed = np.empty((n_skin, 3))
    posed_normals = np.empty((n_skin, 3))
    for u in range(n_skin):  # the bound body vertices skinned as the body is, and their normals by the same blend
        posed[u, 0], posed[u, 1], posed[u, 2] = skin_vertex(rest, bones, weights, transforms, u)
        tip = skin_point(rest[u, 0] + normals[u, 0], rest[u, 1] + normals[u, 1], rest[u, 2] + normals[u, 2], bones,
                         weights, u, transforms)
        length = 0.0
        for a in range(3):
            posed_normals[u, a] = tip[a] - posed[u, a]
            length += posed_normals[u, a] ** 2
        length = np.sqrt(length)
        if length > 0.0:
            for a in range(3):
                posed_normals[u, a] /= length
    pushed = 0
    for m in range(band.shape[0]):
        v = band[m]
        best, chosen = 0.0, -1
        for j in range(neighbors.shape[1]):  # the plane that lifts it most, among those it lies just under
            u = neighbors[m, j]
            height = 0.0
            for a in range(3):
                height += (points[v, a] - posed[u, a]) * posed_normals[u, a]
            push = clearance - height
            if best < push <= max_push:
                best, chosen = push, u
        if chosen >= 0:
            for a in range(3):
                points[v, a] += best * posed_normals[chosen, a]
            pushed += 1
    return pushed


def push_off_skin(points, binding: SkinBinding, transforms, clearance: float = EDGE_CLEARANCE,
                  max_push: float = MAX_PUSH) -> int:
    """Push the band vertices of points (V, 3) (changed in place) to at least `clearance` outside the tangent plane of
    each bound skin vertex posed by transforms (B, 3, 4), where they lie at most `max_push` under it; returns how
    many moved."""
    if len(binding) == 0:
        return 0
    return int(_push(points, binding.band, binding.neighbors, binding.rest, binding.normals, binding.bones,
                     binding.weights, np.ascontiguousarray(transforms, dtype=np.float64), float(clearance),
                     float(max_push)))
