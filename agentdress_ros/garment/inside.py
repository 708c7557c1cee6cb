"""Which points lie inside the posed body, robust to the body passing into itself.

Anny's linear blend skinning self-intersects in everyday poses (arm into torso, thigh into thigh): in arms-down
and walking poses a few hundred of its visible vertices lie inside another body part. A nearest-face normal test
then calls cloth between the two surfaces "inside", and ray parity (`trimesh.contains`) is undefined on such a
mesh. The generalised winding number (Jacobson et al. 2013) is not: w(p) = sum over triangles of the solid angle
they subtend at p, / 4 pi, is 1 inside a closed surface, 0 outside, 2 where two parts overlap, and degrades
gracefully at small holes.

`inside_report` splits the garment vertices inside the body into those trapped where the body overlaps itself
and those truly inside (cloth that went through skin). The split is part-aware: a point is in the self-overlap when
it lies inside two body parts at once (winding number near 2: the overlap region itself) or within `radius` (a few
millimetres, the cloth's contact thickness and a little more) of the overlap region's surface, i.e. of the body
faces that lie inside another part. A point inside one part only, farther than that from the overlap, went through
the skin, however near an armpit or crotch it sits.
"""
from __future__ import annotations

import numba
import numpy as np

from .binding import vertex_normals

# A garment vertex inside the body counts as trapped by the body's self-overlap when it is inside two parts at once,
# or this close to a body face that lies inside another part: 2.5x the cloth's 2 mm contact thickness (cloth resting
# on skin that has sunk into another part sits about that far from it). The earlier rule, any overlapping body
# vertex within 3 cm, called cloth that went through the skin near an armpit "trapped".
OVERLAP_RADIUS = 0.005
# Winding number above which a point is inside two parts at once (1 inside one part, 2 in their overlap).
TWO_PARTS = 1.5
# Body vertices this far beyond `radius` from an inside point are tested for overlap too: a face can be within
# `radius` while its corners are an edge length away (Anny's body edges are up to about 2 cm).
_FACE_REACH = 0.025
# Body vertices are tested a little outside their own surface, so that their own part contributes ~0 and only
# another part's volume can put them inside.
_SURFACE_LIFT = 1.0e-3


@numba.njit(cache=True, nogil=True)
def _triangle_solid_angle(px, py, pz, vertices, face):
    a0 = vertices[face[0], 0] - px
    a1 = vertices[face[0], 1] - py
    a2 = vertices[face[0], 2] - pz
    b0 = vertices[face[1], 0] - px
    b1 = vertices[face[1], 1] - py
    b2 = vertices[face[1], 2] - pz
    c0 = vertices[face[2], 0] - px
    c1 = vertices[face[2], 1] - py
    c2 = vertices[face[2], 2] - pz
    la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
    denominator = la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (b0 * c0 + b1 * c1 + b2 * c2) * la \
        + (c0 * a0 + c1 * a1 + c2 * a2) * lb
    return 2.0 * np.arctan2(det, denominator)  # Van Oosterom & Strackee


@numba.njit(cache=True, nogil=True)
def _winding_numbers(points, vertices, faces, out):
    inv_four_pi = 1.0 / (4.0 * np.pi)
    for i in range(points.shape[0]):
        total = 0.0
        for f in range(faces.shape[0]):
            total += _triangle_solid_angle(points[i, 0], points[i, 1], points[i, 2], vertices, faces[f])
        out[i] = total * inv_four_pi
    return out


@numba.njit(cache=True, nogil=True)
def _clustered_winding_numbers(points, vertices, faces, order, starts, centres, normals, radii, far, out):
    """Barnes-Hut winding numbers: a cluster of faces seen from farther than `far` x its radius counts as the dipole
    of its area-weighted normal sum (Barill et al. 2018, first order); nearer clusters are summed face by face."""
    inv_four_pi = 1.0 / (4.0 * np.pi)
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        total = 0.0
        for c in range(centres.shape[0]):
            dx, dy, dz = centres[c, 0] - px, centres[c, 1] - py, centres[c, 2] - pz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 > (far * radii[c]) ** 2:
                total += (normals[c, 0] * dx + normals[c, 1] * dy + normals[c, 2] * dz) / (d2 * np.sqrt(d2))
            else:
                for k in range(starts[c], starts[c + 1]):
                    total += _triangle_solid_angle(px, py, pz, vertices, faces[order[k]])
        out[i] = total * inv_four_pi
    return out


# Faces are clustered on a grid of this pitch (metres) for the far field: on the 26k-face body, about 600 clusters.
CLUSTER_PITCH = 0.04
# A cluster farther than this many of its radii counts as one dipole; its first-order error is below a few
# thousandths of a winding number each, far from the 0.5 the tests threshold at.
FAR_FIELD = 3.0


class WindingField:
    """Generalised winding numbers w.r.t. one triangle mesh (vertices (N, 3), faces (F, 3), counter-clockwise seen
    from outside): faces clustered once on a CLUSTER_PITCH grid, far clusters summed as dipoles (10x faster on the
    body than the exact sum, within ~1e-2 of it)."""

    def __init__(self, vertices, faces):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        corners = self.vertices[self.faces]  # (F, 3, 3)
        centroids = corners.mean(axis=1)
        area_normals = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        cells = np.floor((centroids - centroids.min(axis=0)) / CLUSTER_PITCH).astype(np.int64)
        dims = cells.max(axis=0) + 1
        # one integer per cell (row-major, so the clusters come in np.unique(cells, axis=0)'s order, 20x faster: a
        # background check must not hold the GIL for long)
        cluster = np.unique((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2], return_inverse=True)[1]
        counts = np.bincount(cluster)
        self.order = np.argsort(cluster, kind="stable")
        self.starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        weights = np.linalg.norm(area_normals, axis=1) + 1e-30
        centres = np.stack([np.bincount(cluster, weights * centroids[:, j]) for j in range(3)], axis=1)
        self.centres = np.ascontiguousarray(centres / np.bincount(cluster, weights)[:, None])
        self.normals = np.ascontiguousarray(np.stack([np.bincount(cluster, area_normals[:, j]) for j in range(3)],
                                                     axis=1))
        reach = np.linalg.norm(corners - self.centres[cluster][:, None, :], axis=2).max(axis=1)  # farthest corner
        self.radii = np.zeros(len(counts))
        np.maximum.at(self.radii, cluster, reach)

    def __call__(self, points) -> np.ndarray:
        """(P,) winding numbers of points (P, 3)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return _clustered_winding_numbers(points, self.vertices, self.faces, self.order, self.starts, self.centres,
                                          self.normals, self.radii, FAR_FIELD, np.empty(len(points)))


def winding_numbers(points, vertices, faces, exact: bool = False) -> np.ndarray:
    """Generalised winding numbers (P,) of points (P, 3) w.r.t. the triangle mesh vertices (N, 3), faces (F, 3).

    Faces are wound counter-clockwise seen from outside (outward normals): ~1 inside, ~0 outside. exact=True sums
    every face; otherwise far clusters count as dipoles (WindingField).
    """
    if exact:
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return _winding_numbers(points, np.ascontiguousarray(vertices, dtype=np.float64),
                                np.ascontiguousarray(faces, dtype=np.int64), np.empty(len(points)))
    return WindingField(vertices, faces)(points)


def self_overlapping_vertices(vertices, faces, candidates=None, field: WindingField | None = None) -> np.ndarray:
    """Mask (N,) of the mesh's vertices that lie inside another part of the same mesh (its self-overlap).

    candidates (C,) optional vertex indices: test only these (the rest are reported False). field: the mesh's
    WindingField when the caller holds one.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    used = np.zeros(len(vertices), dtype=bool)
    used[np.asarray(faces).ravel()] = True
    ids = np.flatnonzero(used) if candidates is None else np.asarray(candidates, dtype=np.int64)
    ids = ids[used[ids]]
    lifted = vertices[ids] + _SURFACE_LIFT * vertex_normals(vertices, faces)[ids]
    mask = np.zeros(len(vertices), dtype=bool)
    field = field if field is not None else WindingField(vertices, faces)
    mask[ids] = field(lifted) > 0.5
    return mask


class BodyInside:
    """The inside test against one posed body (vertices (N, 3), faces (F, 3), a closed outward surface), for many
    point sets: its winding field is built once, and its self-overlap is found once per body vertex, on demand (only
    body vertices near inside points are tested)."""

    def __init__(self, body_vertices, body_faces, radius: float = OVERLAP_RADIUS):
        from scipy.spatial import cKDTree

        self.vertices = np.asarray(body_vertices, dtype=np.float64)
        self.faces = np.asarray(body_faces)
        self.radius = radius
        self.field = WindingField(self.vertices, self.faces)
        self.tree = cKDTree(self.vertices)
        self.tested = np.zeros(len(self.vertices), dtype=bool)
        self.overlap = np.zeros(len(self.vertices), dtype=bool)

    def inside(self, points) -> np.ndarray:
        """Mask (P,) of the points (P, 3) inside the body (no self-overlap split)."""
        return self.field(np.asarray(points, dtype=np.float64)) > 0.5

    def report(self, points) -> dict:
        """{"inside": mask (P,), "in_overlap": mask (P,) of inside points in the body's self-overlap (inside two
        parts at once, or within `radius` of a body face that lies inside another part), "truly_inside": mask (P,),
        "winding": (P,) winding numbers, and the counts "inside_count", "overlap_count", "truly_inside_count"} for
        points (P, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        winding = self.field(points)
        inside = winding > 0.5
        in_overlap = inside & (winding > TWO_PARTS)
        rest = np.flatnonzero(inside & ~in_overlap)
        if len(rest):
            distance = self.distance_to_overlap(points[rest])
            in_overlap[rest] = distance < self.radius
        truly = inside & ~in_overlap
        return {"inside": inside, "in_overlap": in_overlap, "truly_inside": truly, "winding": winding,
                "inside_count": int(inside.sum()), "overlap_count": int(in_overlap.sum()),
                "truly_inside_count": int(truly.sum())}

    def distance_to_overlap(self, points) -> np.ndarray:
        """(P,) distance of points (P, 3) to the nearest body face with a corner inside another body part (inf where
        none is near): the surface of the overlap region. Body vertices near the points are tested on demand."""
        import trimesh

        near = np.unique(np.concatenate([np.asarray(ids, dtype=np.int64) for ids in
                                         self.tree.query_ball_point(points, self.radius + _FACE_REACH)]
                                        + [np.zeros(0, np.int64)]))
        new = near[~self.tested[near]]
        if len(new):
            self.overlap |= self_overlapping_vertices(self.vertices, self.faces, new, self.field)
            self.tested[new] = True
        faces = self.faces[self.overlap[self.faces].any(axis=1)]
        if not len(faces):
            return np.full(len(points), np.inf)
        used, local = np.unique(faces, return_inverse=True)
        mesh = trimesh.Trimesh(self.vertices[used], local.reshape(-1, 3), process=False)
        return trimesh.proximity.closest_point(mesh, points)[1]


def inside_report(points, body_vertices, body_faces, radius: float = OVERLAP_RADIUS) -> dict:
    """BodyInside(body_vertices, body_faces, radius).report(points): one point set against one posed body."""
    return BodyInside(body_vertices, body_faces, radius).report(points)
