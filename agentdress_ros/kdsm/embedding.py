"""Embedding points in the KDSM (paper Sec. 4) and the per-frame kernel that poses them.

A material-space point u^m lies in one rest tet (found in O(1) on the BCC lattice, `lattice.locate_lattice_tet`)
with barycentric weights lambda (4,); a pose theta moves it to sum_k lambda_k v_k(theta), the tet's four vertices
skinned with their own weights. With u^m the rest garment this is the fixed embedding (Fig. 3); with
u^m = u^{m_o} + d(theta) the plastic displacements d of Sec. 4 re-embed the garment every frame.

Points outside the meshed shell fall back to linear blend skinning with the point's own skin weights (the
garment's), and are counted. The per-frame kernel builds no search structure: the lattice is the grid.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..body.kinematics import skin_point
from .lattice import locate_lattice_tet
from .mesh import KDSM


@dataclass(frozen=True)
class Embedding:
    """Parent tets and barycentric weights of P points; tet -1 (weights 0) for points outside the shell."""

    tets: np.ndarray  # (P,) int32
    weights: np.ndarray  # (P, 4) float64, rows sum to 1 for embedded points

    @property
    def outside(self) -> np.ndarray:
        return self.tets < 0


@numba.njit(cache=True, nogil=True, inline="always")
def _rest_barycentric(t, lattice, x, y, z, vertices, tets, class_inverse):
    """Barycentric weights (4 scalars) of (x, y, z) in rest tet t of lattice tet id `lattice`."""
    v0 = tets[t, 0]
    dx = x - vertices[v0, 0]
    dy = y - vertices[v0, 1]
    dz = z - vertices[v0, 2]
    m = class_inverse[lattice % 12]
    l1 = m[0, 0] * dx + m[0, 1] * dy + m[0, 2] * dz
    l2 = m[1, 0] * dx + m[1, 1] * dy + m[1, 2] * dz
    l3 = m[2, 0] * dx + m[2, 1] * dy + m[2, 2] * dz
    return 1.0 - l1 - l2 - l3, l1, l2, l3


@numba.njit(cache=True, nogil=True, inline="always")
def _mesh_tet(x, y, z, origin, spacing, dims, lattice_tets):
    """(mesh tet, lattice tet id) of a point; mesh tet -1 outside the shell."""
    lattice = locate_lattice_tet(x, y, z, origin, spacing, dims)
    return (-1 if lattice < 0 else lattice_tets[lattice]), lattice


@numba.njit(cache=True, nogil=True)
def embed_points(points, origin, spacing, dims, lattice_tets, vertices, tets, class_inverse, out_tets, out_weights):
    """Parent rest tet out_tets (P,) and barycentric weights out_weights (P, 4) of points (P, 3); returns the count
    of points outside the shell (tet -1, weights 0)."""
    outside = 0
    for p in range(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        t, lattice = _mesh_tet(x, y, z, origin, spacing, dims, lattice_tets)
        out_tets[p] = t
        if t < 0:
            outside += 1
            out_weights[p, :] = 0.0
            continue
        out_weights[p, 0], out_weights[p, 1], out_weights[p, 2], out_weights[p, 3] = _rest_barycentric(
            t, lattice, x, y, z, vertices, tets, class_inverse)
    return outside


@numba.njit(cache=True, nogil=True, fastmath=True, inline="always")
def _skin_tet(t, l0, l1, l2, l3, vertices, tets, skin_indices, skin_weights, transforms, mark, skinned):
    """sum_c lambda_c v_c(theta) over the four skinned vertices of tet t, as three scalars.

    Neighbouring garment vertices share tet vertices (1,200 T-shirt vertices touch about 2,700 distinct ones, not
    4,800), so each tet vertex is skinned once per frame: row v of skinned (N, 4) holds it where its last entry, the
    frame's stamp, equals `mark` (one cache line for both).
    """
    ox = 0.0
    oy = 0.0
    oz = 0.0
    for c in range(4):
        v = tets[t, c]
        if skinned[v, 3] != mark:
            skinned[v, 0], skinned[v, 1], skinned[v, 2] = skin_point(vertices[v, 0], vertices[v, 1], vertices[v, 2],
                                                                     skin_indices, skin_weights, v, transforms)
            skinned[v, 3] = mark
        lam = l0 if c == 0 else (l1 if c == 1 else (l2 if c == 2 else l3))
        ox += lam * skinned[v, 0]
        oy += lam * skinned[v, 1]
        oz += lam * skinned[v, 2]
    return ox, oy, oz


@numba.njit(cache=True, nogil=True, fastmath=True)
def pose_embedded(points, embed_tets, embed_weights, vertices, tets, skin_indices, skin_weights, transforms,
                  fallback_indices, fallback_weights, mark, skinned, out):
    """out (P, 3): every point sum_k lambda_k v_k(theta), skinning only its parent tet's four vertices; points with
    tet -1 are skinned themselves (points (P, 3) with fallback_indices/fallback_weights (P, K)).

    embed_tets (P,), embed_weights (P, 4) (an Embedding), vertices (N, 3) rest tet vertices, tets (T, 4),
    skin_indices/skin_weights (N, 4) of the tet vertices, transforms (B, 3, 4); mark (float) and skinned (N, 4):
    the frame's cache of skinned tet vertices and their stamps (a mark not yet stamped starts a new frame).
    """
    for p in range(points.shape[0]):
        t = embed_tets[p]
        if t < 0:
            out[p, 0], out[p, 1], out[p, 2] = skin_point(points[p, 0], points[p, 1], points[p, 2],
                                                         fallback_indices, fallback_weights, p, transforms)
            continue
        out[p, 0], out[p, 1], out[p, 2] = _skin_tet(t, embed_weights[p, 0], embed_weights[p, 1],
                                                    embed_weights[p, 2], embed_weights[p, 3], vertices, tets,
                                                    skin_indices, skin_weights, transforms, mark, skinned)
    return out


@numba.njit(cache=True, nogil=True)  # no fastmath: a NaN displacement must reach the lattice test as NaN
def pose_displaced(rest_points, displacements, origin, spacing, dims, lattice_tets, vertices, tets, class_inverse,
                   skin_indices, skin_weights, transforms, fallback_indices, fallback_weights, mark, skinned,
                   parent_tets, out):
    """The run-time step of Sec. 4: re-embed u^m = rest_points + displacements (P, 3) in the rest lattice (O(1) per
    point) and skin the parent tet's four vertices. Writes out (P, 3) world positions and parent_tets (P,) (-1: the
    point left the shell and was skinned with its own weights fallback_indices/fallback_weights (P, K)); returns
    the number of such points. displacements and out may be strided views (a (3, V) buffer transposed). Other
    arguments as in KDSM and pose_embedded."""
    outside = 0
    for p in range(rest_points.shape[0]):
        x = rest_points[p, 0] + displacements[p, 0]
        y = rest_points[p, 1] + displacements[p, 1]
        z = rest_points[p, 2] + displacements[p, 2]
        t, lattice = _mesh_tet(x, y, z, origin, spacing, dims, lattice_tets)
        parent_tets[p] = t
        if t < 0:
            outside += 1
            out[p, 0], out[p, 1], out[p, 2] = skin_point(x, y, z, fallback_indices, fallback_weights, p, transforms)
            continue
        l0, l1, l2, l3 = _rest_barycentric(t, lattice, x, y, z, vertices, tets, class_inverse)
        out[p, 0], out[p, 1], out[p, 2] = _skin_tet(t, l0, l1, l2, l3, vertices, tets, skin_indices, skin_weights,
                                                    transforms, mark, skinned)
    return outside


def embed(kdsm: KDSM, points: np.ndarray) -> Embedding:
    """Embedding of points (P, 3) in the rest KDSM."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    tets = np.empty(len(points), dtype=np.int32)
    weights = np.empty((len(points), 4))
    embed_points(points, kdsm.origin, kdsm.spacing, kdsm.dims, kdsm.lattice_tets, kdsm.vertices, kdsm.tets,
                 kdsm.class_inverse, tets, weights)
    return Embedding(tets, weights)


def unembed(kdsm: KDSM, embedding: Embedding, tet_vertices: np.ndarray | None = None) -> np.ndarray:
    """(P, 3) sum_k lambda_k v_k for tet vertex positions tet_vertices (N, 3) (default: the rest ones); NaN rows
    for points outside the shell."""
    tet_vertices = kdsm.vertices if tet_vertices is None else tet_vertices
    inside = ~embedding.outside
    out = np.full((len(embedding.tets), 3), np.nan)
    corners = tet_vertices[kdsm.tets[embedding.tets[inside]]]
    out[inside] = np.einsum("pk,pkd->pd", embedding.weights[inside], corners)
    return out


class KdsmPoser:
    """Poses one garment through a KDSM, per frame: `pose(transforms, displacements=None) -> (V, 3)`.

    rest (V, 3) is u^{m_o} (the rest garment); skin_indices/skin_weights (V, K) its own LBS weights, used by
    vertices that leave the shell. Without displacements it is the fixed embedding of Fig. 3 (embedded once).
    Each poser keeps a per-frame cache of skinned tet vertices (32 bytes per KDSM vertex: 3 MB at 2.5 cm).
    """

    def __init__(self, kdsm: KDSM, rest, skin_indices, skin_weights):
        self.kdsm = kdsm
        self.rest = np.ascontiguousarray(rest, dtype=np.float64)
        self.skin_indices = np.ascontiguousarray(skin_indices, dtype=np.int32)
        self.skin_weights = np.ascontiguousarray(skin_weights, dtype=np.float64)
        self.rest_embedding = embed(kdsm, self.rest)
        self.parent_tets = self.rest_embedding.tets.copy()
        self.fallback_count = int(self.rest_embedding.outside.sum())
        self._out = np.empty_like(self.rest)
        self._skinned = np.zeros((len(kdsm.vertices), 4))  # skinned tet vertices of this frame, and their stamps
        self._mark = 0.0

    def pose(self, transforms: np.ndarray, displacements: np.ndarray | None = None, out=None) -> np.ndarray:
        """World positions (V, 3) for bone transforms (B, 3, 4) and plastic displacements d (V, 3) (None: d = 0
        with the embedding fixed at rest), written into `out` (V, 3), which may be a strided view, or else into
        an array the next call reuses."""
        k = self.kdsm
        out = self._out if out is None else out
        transforms = np.ascontiguousarray(transforms, dtype=np.float64)
        self._mark += 1.0  # a new frame: every cached tet vertex is stale
        if displacements is None:
            pose_embedded(self.rest, self.rest_embedding.tets, self.rest_embedding.weights, k.vertices, k.tets,
                          k.skin_indices, k.skin_weights, transforms, self.skin_indices, self.skin_weights,
                          self._mark, self._skinned, out)
            self.fallback_count = int(self.rest_embedding.outside.sum())
            return out
        displacements = np.asarray(displacements)  # float32 or float64: pose_displaced is compiled for either
        self.fallback_count = pose_displaced(self.rest, displacements, k.origin, k.spacing, k.dims, k.lattice_tets,
                                             k.vertices, k.tets, k.class_inverse, k.skin_indices, k.skin_weights,
                                             transforms, self.skin_indices, self.skin_weights, self._mark,
                                             self._skinned, self.parent_tets, out)
        return out
