"""Which points lie inside the posed body, robust to the body passing into itself.

Anny's linear blend skinning self-intersects in everyday poses (arm into torso, thigh into thigh): in arms-down
and walking poses a few hundred of its visible vertices lie inside another body part. A nearest-face normal test
then calls cloth between the two surfaces "inside", and ray parity (`trimesh.contains`) is undefined on such a
mesh. The generalised winding number (Jacobson et al. 2013) is not: w(p) = sum over triangles of the solid angle
they subtend at p, / 4 pi, is 1 inside a closed surface, 0 outside, 2 where two parts overlap, and degrades
gracefully at small holes.

`inside_report` splits the garment vertices inside the body into those trapped where the body overlaps itself
(near body vertices that lie inside another body part) and those truly inside (cloth that went through skin).
"""
from __future__ import annotations

import numba
import numpy as np

from .binding import vertex_normals

# A garment vertex inside the body counts as trapped by the body's self-overlap when a body vertex that lies inside
# another body part is this close to it (the overlap regions are a few centimetres deep at armpits and thighs).
OVERLAP_RADIUS = 0.03
# Body vertices are tested a little outside their own surface, so that their own part contributes ~0 and only
# another part's volume can put them inside.
_SURFACE_LIFT = 1.0e-3


@numba.njit(cache=True)
def _winding_numbers(points, vertices, faces, out):
    inv_four_pi = 1.0 / (4.0 * np.pi)
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        total = 0.0
        for f in range(faces.shape[0]):
            a0 = vertices[faces[f, 0], 0] - px
            a1 = vertices[faces[f, 0], 1] - py
            a2 = vertices[faces[f, 0], 2] - pz
            b0 = vertices[faces[f, 1], 0] - px
            b1 = vertices[faces[f, 1], 1] - py
            b2 = vertices[faces[f, 1], 2] - pz
            c0 = vertices[faces[f, 2], 0] - px
            c1 = vertices[faces[f, 2], 1] - py
            c2 = vertices[faces[f, 2], 2] - pz
            la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
            dot_ab = a0 * b0 + a1 * b1 + a2 * b2
            dot_bc = b0 * c0 + b1 * c1 + b2 * c2
            dot_ca = c0 * a0 + c1 * a1 + c2 * a2
            denominator = la * lb * lc + dot_ab * lc + dot_bc * la + dot_ca * lb
            total += 2.0 * np.arctan2(det, denominator)  # Van Oosterom & Strackee's solid angle
        out[i] = total * inv_four_pi
    return out


def winding_numbers(points, vertices, faces) -> np.ndarray:
    """Generalised winding numbers (P,) of points (P, 3) w.r.t. the triangle mesh vertices (N, 3), faces (F, 3).

    Faces are wound counter-clockwise seen from outside (outward normals): ~1 inside, ~0 outside.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    return _winding_numbers(points, vertices, faces, np.empty(len(points)))


def self_overlapping_vertices(vertices, faces, candidates=None) -> np.ndarray:
    """Mask (N,) of the mesh's vertices that lie inside another part of the same mesh (its self-overlap).

    candidates (C,) optional vertex indices: test only these (the rest are reported False).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    used = np.zeros(len(vertices), dtype=bool)
    used[np.asarray(faces).ravel()] = True
    ids = np.flatnonzero(used) if candidates is None else np.asarray(candidates, dtype=np.int64)
    ids = ids[used[ids]]
    lifted = vertices[ids] + _SURFACE_LIFT * vertex_normals(vertices, faces)[ids]
    mask = np.zeros(len(vertices), dtype=bool)
    mask[ids] = winding_numbers(lifted, vertices, faces) > 0.5
    return mask


def inside_report(points, body_vertices, body_faces, radius: float = OVERLAP_RADIUS) -> dict:
    """Count points (P, 3) inside the body (body_vertices (N, 3), body_faces (F, 3), a closed outward surface).

    Returns {"inside": mask (P,), "in_overlap": mask (P,) of inside points within `radius` of a body vertex
    that lies inside another body part, "truly_inside": mask (P,), and the counts "inside_count",
    "overlap_count", "truly_inside_count"}. Only body vertices near inside points are tested for self-overlap.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    body_vertices = np.asarray(body_vertices, dtype=np.float64)
    inside = winding_numbers(points, body_vertices, body_faces) > 0.5
    in_overlap = np.zeros(len(points), dtype=bool)
    if inside.any():
        tree = cKDTree(body_vertices)
        near = np.unique(np.concatenate([np.asarray(ids, dtype=np.int64) for ids in
                                         tree.query_ball_point(points[inside], radius)] + [np.zeros(0, int)]))
        overlap = self_overlapping_vertices(body_vertices, body_faces, near)
        if overlap.any():
            distance, _ = cKDTree(body_vertices[overlap]).query(points[inside], k=1)
            in_overlap[np.flatnonzero(inside)] = distance < radius
    truly = inside & ~in_overlap
    return {"inside": inside, "in_overlap": in_overlap, "truly_inside": truly,
            "inside_count": int(inside.sum()), "overlap_count": int(in_overlap.sum()),
            "truly_inside_count": int(truly.sum())}
