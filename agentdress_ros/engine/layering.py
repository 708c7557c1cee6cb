"""Layered garments: an outer garment never passes inside an inner one (a T-shirt worn over trousers).

Like the paper's penetration handling against the body (Eq. 10), the outer garment is bound once - when the shape
changes - to the inner garment's surface: each outer vertex that lies over the inner garment gets the triangle of
the inner garment closest to it at rest (three vertex ids and barycentric weights). Every frame, the outer vertex
is pushed out along the inner surface's interpolated normal until it is at least `clearance` outside the bound
point: a fixed binding, no per-frame search. Outer vertices further than 10 cm from the inner garment at rest
(a T-shirt's chest above the trousers' waist) are not bound.

That keeps the outer garment's vertices outside, but an inner vertex can still pass between them, through an outer
triangle (the trousers' hips through a T-shirt's 3 cm triangles as the hips swing). The reverse binding catches it:
each inner vertex under the outer garment at rest gets the outer triangles within UNDER_RINGS rings of its closest
one; every frame the one it lies under is found among them (the garments slide 6-10 cm over each other in a walk),
and if the inner vertex comes closer to it than `clearance`, that triangle is lifted along its vertex normals, each
corner by its share of the lift (`lift_over_inner`).

Pure array functions; shapes: V outer vertices, W inner vertices, G inner triangles, M bound outer vertices.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import trimesh
from scipy.spatial import cKDTree

__all__ = ["CLEARANCE", "LayerBinding", "UnderBinding", "bind_layers", "bind_to_vertices", "bind_under",
           "face_vertex_normals", "lift_over_inner", "push_out_of_inner", "track_nearest", "vertex_neighbours"]

#: Default gap kept between an outer garment and the inner one, metres.
CLEARANCE = 0.004
#: The reverse binding: inner vertices within this distance of the outer garment at rest, and at least
#: UNDER_EDGE_MARGIN inside its open edges (below a hem the inner garment shows by design), lift the outer one.
UNDER_DISTANCE = 0.05
UNDER_EDGE_MARGIN = 0.01
#: Rings of triangles (sharing a corner) around its closest one at rest that an inner vertex searches each frame:
#: three rings of a 1,200-vertex garment (3 cm edges) reach about 9 cm.
UNDER_RINGS = 3
#: The refined layers' vertex binding follows the inner garment by at most this many edges a frame.
TRACK_STEPS = 4


@dataclass(frozen=True)
class LayerBinding:
    """M outer vertices bound to a point of the inner garment's surface."""

    outer: np.ndarray  # (M,) int64 outer vertex ids
    triangles: np.ndarray  # (M, 3) int64 inner vertex ids of the carrying triangle
    barycentric: np.ndarray  # (M, 3) float32 weights, rows sum to 1
    faces: np.ndarray  # (M,) int64 inner face id of the carrying triangle

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
    empty = LayerBinding(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32),
                         np.zeros(0, np.int64))
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
                        barycentric[keep].astype(np.float32), face_ids[keep].astype(np.int64))


def bind_to_vertices(outer, inner, max_distance: float = 0.1) -> LayerBinding:
    """Bind outer vertices (V, 3) to their closest inner vertex (W, 3) at rest, within max_distance: a binding for a
    fine mesh over a fine mesh (refined garments, ~1.5 cm edges), made in milliseconds by a k-d tree where
    bind_layers' closest points on triangles take a second (a body-shape change rebinds)."""
    distance, nearest = cKDTree(np.asarray(inner, dtype=np.float64)).query(
        np.asarray(outer, dtype=np.float64), distance_upper_bound=max_distance)
    ids = np.flatnonzero(np.isfinite(distance))
    nearest = nearest[ids].astype(np.int64)
    barycentric = np.zeros((len(ids), 3), dtype=np.float32)
    barycentric[:, 0] = 1.0
    return LayerBinding(ids.astype(np.int64), np.repeat(nearest[:, None], 3, axis=1), barycentric,
                        np.full(len(ids), -1, dtype=np.int64))


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
def _point_and_normal(points, normals, corners, weights):
    """The point sum_c weights[c] points[corners[c]] and the unit normal interpolated likewise (zero if they
    cancel) of one triangle."""
    px = py = pz = nx = ny = nz = 0.0
    for c in range(3):
        j = corners[c]
        w = weights[c]
        px += w * points[j, 0]
        py += w * points[j, 1]
        pz += w * points[j, 2]
        nx += w * normals[j, 0]
        ny += w * normals[j, 1]
        nz += w * normals[j, 2]
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    if length > 0.0:
        nx /= length
        ny /= length
        nz /= length
    return px, py, pz, nx, ny, nz


@numba.njit(cache=True, nogil=True, fastmath=True)
def _push(outer, inner, normals, ids, triangles, barycentric, clearance):
    pushed = 0
    for m in range(ids.shape[0]):
        px, py, pz, nx, ny, nz = _point_and_normal(inner, normals, triangles[m], barycentric[m])
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue
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


def vertex_neighbours(faces, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """(offsets (W + 1,), neighbours (E,)) int64 CSR of the vertices sharing an edge with each vertex of faces
    (G, 3)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(np.concatenate([edges, edges[:, ::-1]]), axis=1), axis=0)
    pairs = np.concatenate([edges, edges[:, ::-1]])
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    offsets = np.zeros(n_vertices + 1, dtype=np.int64)
    np.add.at(offsets, pairs[:, 0] + 1, 1)
    return np.cumsum(offsets), np.ascontiguousarray(pairs[:, 1])


@numba.njit(cache=True, nogil=True, fastmath=True)
def _track(outer, inner, ids, triangles, offsets, neighbours, steps):
    """For each bound outer vertex, walk from its inner vertex of the last frame (triangles[m, 0]) to the adjacent
    inner vertex closest to it, while one is closer (at most `steps` moves); written to all three columns."""
    for m in range(ids.shape[0]):
        i = ids[m]
        j = triangles[m, 0]
        best = (outer[i, 0] - inner[j, 0]) ** 2 + (outer[i, 1] - inner[j, 1]) ** 2 + (outer[i, 2] - inner[j, 2]) ** 2
        for _ in range(steps):
            moved = False
            for k in range(offsets[j], offsets[j + 1]):
                n = neighbours[k]
                d = (outer[i, 0] - inner[n, 0]) ** 2 + (outer[i, 1] - inner[n, 1]) ** 2 + (outer[i, 2] - inner[n, 2]) ** 2
                if d < best:
                    best, j, moved = d, n, True
            if not moved:
                break
        triangles[m, 0] = triangles[m, 1] = triangles[m, 2] = j


def track_nearest(outer, inner, binding: LayerBinding, adjacency, steps: int = TRACK_STEPS) -> None:
    """Follow a vertex binding (bind_to_vertices, its triangles owned by the caller) as the layers slide over each
    other: the inner vertex each bound outer vertex (V, 3) is pushed out of moves, in place, to a closer adjacent
    vertex of the posed inner garment (W, 3) while there is one (adjacency: vertex_neighbours of the inner faces).
    A walk, not a search: a binding fixed at rest pushed the shirt out of the trousers where they hung at rest,
    and the trousers' front seam came through the shirt where the hips had carried it."""
    if len(binding):
        _track(outer, inner, binding.outer, binding.triangles, adjacency[0], adjacency[1], steps)


@dataclass(frozen=True)
class UnderBinding:
    """M inner vertices under the outer garment, each with the outer triangles it may lie under (CSR)."""

    inner: np.ndarray  # (M,) int64 inner vertex ids
    offsets: np.ndarray  # (M + 1,) int64: the candidates of vertex m are faces[offsets[m]:offsets[m + 1]]
    faces: np.ndarray  # (K,) int64 outer face ids, the closest at rest first

    def __len__(self) -> int:
        return len(self.inner)


def bind_under(inner, outer, outer_faces, max_distance: float = UNDER_DISTANCE,
               edge_margin: float = UNDER_EDGE_MARGIN, rings: int = UNDER_RINGS) -> UnderBinding:
    """The reverse binding at rest: inner vertices (W, 3) within max_distance of the outer garment (V, 3), (F, 3) and
    at least edge_margin inside its open edges, each with its closest outer triangle and those within `rings` rings
    of it (triangles sharing a corner)."""
    outer_faces = np.asarray(outer_faces, dtype=np.int64)
    closest = bind_layers(inner, outer, outer_faces, max_distance, edge_margin)
    if len(closest) == 0:
        return UnderBinding(np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0, np.int64))
    # (V, max degree) faces incident to each outer vertex, -1 padded
    incident = trimesh.Trimesh(np.asarray(outer, dtype=np.float64), outer_faces, process=False).vertex_faces
    offsets, faces = [0], []
    for first in closest.faces.tolist():
        found, seen, frontier = [first], {first, -1}, [first]
        for _ in range(rings):
            near = sorted(set(incident[np.unique(outer_faces[frontier])].ravel().tolist()) - seen)
            found += near
            seen.update(near)
            frontier = near
        faces += found
        offsets.append(len(faces))
    return UnderBinding(closest.outer, np.asarray(offsets, dtype=np.int64), np.asarray(faces, dtype=np.int64))


@numba.njit(cache=True, nogil=True, fastmath=True)
def _lift(outer, normals, outer_faces, inner, ids, offsets, candidates, clearance, max_distance, lift):
    """lift (V,) = per outer vertex, the largest share it takes of lifting the triangle over each bound inner vertex
    (the first candidate, rings outwards, that its projection falls in within UNDER_DISTANCE of its plane; else the
    closest at rest, its projection clamped into it); then outer += lift x its normal. Returns how many inner
    vertices needed it."""
    lift[:] = 0.0
    count = 0
    for m in range(ids.shape[0]):
        i = ids[m]
        x0, x1, x2 = inner[i, 0], inner[i, 1], inner[i, 2]
        best = -1
        b0 = b1 = b2 = 0.0  # the chosen triangle's barycentric weights
        for k in range(offsets[m], offsets[m + 1]):
            f = candidates[k]
            a, b, c = outer_faces[f, 0], outer_faces[f, 1], outer_faces[f, 2]
            e0 = (outer[b, 0] - outer[a, 0], outer[b, 1] - outer[a, 1], outer[b, 2] - outer[a, 2])
            e1 = (outer[c, 0] - outer[a, 0], outer[c, 1] - outer[a, 1], outer[c, 2] - outer[a, 2])
            d = (x0 - outer[a, 0], x1 - outer[a, 1], x2 - outer[a, 2])
            d00 = e0[0] * e0[0] + e0[1] * e0[1] + e0[2] * e0[2]
            d01 = e0[0] * e1[0] + e0[1] * e1[1] + e0[2] * e1[2]
            d11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2]
            d20 = d[0] * e0[0] + d[1] * e0[1] + d[2] * e0[2]
            d21 = d[0] * e1[0] + d[1] * e1[1] + d[2] * e1[2]
            det = d00 * d11 - d01 * d01
            if det <= 0.0:
                continue
            v = (d11 * d20 - d01 * d21) / det
            u = (d00 * d21 - d01 * d20) / det
            w0 = 1.0 - v - u
            over = w0 >= 0.0 and v >= 0.0 and u >= 0.0
            if over:
                nx = e0[1] * e1[2] - e0[2] * e1[1]
                ny = e0[2] * e1[0] - e0[0] * e1[2]
                nz = e0[0] * e1[1] - e0[1] * e1[0]
                over = abs(d[0] * nx + d[1] * ny + d[2] * nz) < max_distance * np.sqrt(nx * nx + ny * ny + nz * nz)
            if over or k == offsets[m]:  # found; or the fallback, its projection clamped into it
                best = f
                b0, b1, b2 = max(w0, 0.0), max(v, 0.0), max(u, 0.0)
                total = b0 + b1 + b2
                b0, b1, b2 = b0 / total, b1 / total, b2 / total
            if over:
                break
        if best < 0:
            continue
        best_w = (b0, b1, b2)
        px, py, pz, nx, ny, nz = _point_and_normal(outer, normals, outer_faces[best], best_w)
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue
        squares = b0 * b0 + b1 * b1 + b2 * b2
        need = (x0 - px) * nx + (x1 - py) * ny + (x2 - pz) * nz + clearance
        if need > 0.0:
            count += 1
            for c in range(3):  # the least-norm corner moves that lift the point over the vertex by `need`
                j = outer_faces[best, c]
                share = best_w[c] * need / squares
                if share > lift[j]:
                    lift[j] = share
    for j in range(outer.shape[0]):
        if lift[j] > 0.0:
            outer[j, 0] += lift[j] * normals[j, 0]
            outer[j, 1] += lift[j] * normals[j, 1]
            outer[j, 2] += lift[j] * normals[j, 2]
    return count


def lift_over_inner(outer, outer_faces, inner, under: UnderBinding, clearance: float = CLEARANCE, normals=None,
                    lift=None) -> int:
    """Lift the outer garment (V, 3), (F, 3), in place, where an inner vertex (W, 3) bound under it (bind_under at
    rest) comes closer than `clearance` to the outer triangle it lies under, or passes through it: that triangle's
    corners move along their vertex normals by their barycentric share, so the point over the inner vertex ends at
    least `clearance` outside it (for a flat patch exactly; several inner vertices under one corner take the
    largest lift). normals (V, 3), lift (V,): buffers to reuse. Returns how many inner vertices lifted it."""
    if len(under) == 0:
        return 0
    normals = np.empty_like(outer) if normals is None else normals
    lift = np.empty(len(outer), dtype=outer.dtype) if lift is None else lift
    face_vertex_normals(outer, outer_faces, normals)
    return int(_lift(outer, normals, outer_faces, inner, under.inner, under.offsets, under.faces,
                     outer.dtype.type(clearance), UNDER_DISTANCE, lift))

