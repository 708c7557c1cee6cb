"""Mesh operations for garment making: refine to a vertex count and cut along a scalar field's zero level.

Pure array functions on triangle meshes: vertices (N, 3) float64, faces (F, 3) int.
"""
from __future__ import annotations

import numpy as np


def _unique_edges(faces: np.ndarray):
    """(E, 2) sorted unique edges and, per face corner-edge (F, 3), its edge id (edge k joins corners k, k+1)."""
    corner_edges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(np.sort(corner_edges, axis=1), axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


def refine_to_vertex_count(vertices: np.ndarray, faces: np.ndarray, target: int):
    """Split the longest edges (conforming bisection, no T-junctions) until the mesh has `target` vertices.

    Returns (vertices (target, 3), faces (F', 3)). A mesh already at or above the target is returned unchanged.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    while len(vertices) < target:
        edges, face_edges = _unique_edges(faces)
        lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
        edge_faces = [[] for _ in range(len(edges))]
        for f, ids in enumerate(face_edges):
            for e in ids:
                edge_faces[e].append(f)
        busy = np.zeros(len(faces), dtype=bool)
        chosen = []
        longest = lengths.max()
        for e in np.argsort(-lengths, kind="stable"):
            if len(chosen) >= target - len(vertices) or lengths[e] < 0.7 * longest:
                break  # split only the longest edges in one pass, to keep triangles well shaped
            adjacent = edge_faces[e]
            if busy[adjacent].any():
                continue
            busy[adjacent] = True
            chosen.append(e)
        midpoints = 0.5 * (vertices[edges[chosen, 0]] + vertices[edges[chosen, 1]])
        new_id = {e: len(vertices) + i for i, e in enumerate(chosen)}
        vertices = np.vstack([vertices, midpoints])
        kept, added = [], []
        for f, ids in enumerate(face_edges):
            split = [k for k in range(3) if ids[k] in new_id]
            if not split:
                kept.append(f)
                continue
            k = split[0]  # busy faces get exactly one split edge
            a, b, c = faces[f, k], faces[f, (k + 1) % 3], faces[f, (k + 2) % 3]
            m = new_id[ids[k]]
            added += [(a, m, c), (m, b, c)]
        faces = np.vstack([faces[kept], np.asarray(added, dtype=np.int64).reshape(-1, 3)])
    return vertices, faces


def cut_by_field(vertices: np.ndarray, faces: np.ndarray, field: np.ndarray, snap: float = 0.25):
    """Keep the part of the surface where `field` (N,) <= 0, cutting triangles exactly along field = 0.

    The boundary runs along the zero level set (a clean hem). Where the level set passes within `snap` (fraction
    of the edge) of a vertex, that vertex slides along the edge onto the level set, so no sliver triangle is made.
    Returns (vertices (N', 3), faces (F', 3)) with unused vertices removed.
    """
    field = np.asarray(field, dtype=np.float64).copy()
    edges, _ = _unique_edges(np.asarray(faces))
    fa, fb = field[edges[:, 0]], field[edges[:, 1]]
    crossing_edges = (fa <= 0) != (fb <= 0)
    t = np.where(crossing_edges, fa / np.where(crossing_edges, fa - fb, 1.0), 0.5)  # from vertex 0 to vertex 1
    vertices = np.asarray(vertices, dtype=np.float64).copy()
    # Move each snapped vertex along its nearest crossing edge onto the level set (it stays on the surface).
    # Process the closest crossings last so they win when a vertex has several.
    near = np.concatenate([np.flatnonzero(crossing_edges & (t < snap)), np.flatnonzero(crossing_edges & (t > 1 - snap))])
    side = np.concatenate([np.zeros(np.count_nonzero(crossing_edges & (t < snap)), dtype=int),
                           np.ones(np.count_nonzero(crossing_edges & (t > 1 - snap)), dtype=int)])
    gap = np.where(side == 0, t[near], 1.0 - t[near])
    points = vertices[edges[near, 0]] + t[near, None] * (vertices[edges[near, 1]] - vertices[edges[near, 0]])
    order = np.argsort(-gap)
    moved = edges[near, side][order]
    vertices[moved] = points[order]
    field[moved] = 0.0
    inside = field <= 0.0
    crossing_id: dict = {}
    new_points: list = []

    def crossing(a, b):
        i, o = (a, b) if inside[a] else (b, a)
        if field[i] == 0.0:
            return i  # the level set passes through this vertex
        key = (min(a, b), max(a, b))
        if key not in crossing_id:
            t = field[i] / (field[i] - field[o])
            crossing_id[key] = len(vertices) + len(new_points)
            new_points.append(vertices[i] + t * (vertices[o] - vertices[i]))
        return crossing_id[key]

    out = []
    for tri in faces:
        flags = inside[tri]
        count = int(flags.sum())
        if count == 3:
            out.append(tuple(tri))
        elif count == 1:
            k = int(np.flatnonzero(flags)[0])
            a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            out.append((a, crossing(a, b), crossing(a, c)))
        elif count == 2:
            k = int(np.flatnonzero(~flags)[0])
            c, a, b = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]  # c outside; a, b inside, orientation kept
            p_bc, p_ca = crossing(b, c), crossing(a, c)
            out += [(a, b, p_bc), (a, p_bc, p_ca)]
    vertices = np.vstack([vertices, np.asarray(new_points).reshape(-1, 3)])
    kept = np.asarray(out, dtype=np.int64).reshape(-1, 3)
    kept = kept[(kept[:, 0] != kept[:, 1]) & (kept[:, 1] != kept[:, 2]) & (kept[:, 2] != kept[:, 0])]
    return compact(vertices, kept)


def compact(vertices: np.ndarray, faces: np.ndarray):
    """Drop unreferenced vertices: (vertices (N', 3), faces (F, 3)) renumbered."""
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def largest_component(vertices: np.ndarray, faces: np.ndarray):
    """The connected component with the most faces (drops islands a cut may leave)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(vertices)
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    _, labels = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)
    face_labels = labels[faces[:, 0]]
    keep = face_labels == np.bincount(face_labels).argmax()
    return compact(vertices, faces[keep])
