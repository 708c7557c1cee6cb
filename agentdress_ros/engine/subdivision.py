"""Display refinement: Loop subdivision of the synthesised garment as one fixed sparse matrix.

A garment of ~1,200 vertices has ~3 cm triangles: its silhouette is faceted. Loop subdivision (Loop 1987) splits
every triangle into four; each new vertex is a fixed linear combination of the coarse vertices (the stencils
below), so `levels` rounds of it are one sparse matrix S (V', V) built once per topology, and refining a frame is a
sparse product. Loop's surface lies inside the coarse control mesh where that is convex (a body, a sleeve), so the
refined vertices are moved `offset` metres along the coarse vertex normals (carried by the same stencils) to keep
the refined cloth off the skin. Applied after penetration handling, on what the node publishes.

Stencils (Warren's beta for interior vertices of valence n: 3 / (8 n) for n > 3, 3/16 for n = 3):
  new edge vertex, interior edge (a, b) with opposite corners c, d:  3/8 (a + b) + 1/8 (c + d)
  new edge vertex, open edge (hem, cuff, neckline):                   1/2 (a + b)
  old vertex, interior:  (1 - n beta) v + beta sum(neighbours)
  old vertex, on an open edge:  3/4 v + 1/8 (its two neighbours along the edge)   (edges are kept as curves)
Edges of more than two triangles, or vertices with other than two open-edge neighbours, are kept as creases.

Open boundaries are smoothed first (boundary_smoothing): a template cut along a level set leaves a saw-tooth hem
(every other boundary vertex a few millimetres off the curve), which Loop's boundary rule only halves per round. Each
closed boundary loop is filtered by a Gaussian of `boundary_sigma` metres of arc length (at rest) along it,
shrink-compensated (2 G - G G), so a round cuff keeps its radius. It is linear in the coarse vertices too, so it is
folded into S: no cost per frame.
The display also smooths the drawn boundaries each frame along their arc length as posed (smooth_posed_boundaries,
POSED_SIGMA): what a pose bunches, and what the display's per-vertex pushes leave, the rest-time weights cannot see.

Pure array functions; shapes: V coarse vertices, F coarse triangles, V' and F' = 4^levels F refined.
"""
from __future__ import annotations

import numba
import numpy as np
from scipy import sparse

from .layering import face_vertex_normals

__all__ = ["BOUNDARY_SIGMA", "BOUNDARY_SPREAD", "OFFSET", "POSED_SIGMA", "BoundaryLoops", "LoopSubdivision",
           "boundary_smoothing", "loop_stencils", "smooth_posed_boundaries", "spread_edge_moves"]

#: Default offset of the refined surface along the normals, metres.
OFFSET = 0.002
#: Default width of the boundary smoothing along the loop, metres of arc length at rest (a coarse garment's boundary
#: edges are 3-55 mm long: spacing in edges would smooth its short stretches hardly at all). The shipped T-shirt's
#: worst jag, a notch 3 cm deep at the front of the collar, is 8 cm wide: 2 cm left it at 9 mm, 5 cm takes it to 3 mm.
BOUNDARY_SIGMA = 0.05
#: The share of its boundary neighbours' move the first ring inside takes (display_check, drawn body faces poking per
#: frame: the edge moved alone 1.13, half 0.41, all 0.24; before the smoothing 0.16).
BOUNDARY_SPREAD = 1.0
#: Width of the per-frame smoothing of the drawn boundaries along their posed arc length, metres: the scale below
#: which the viewer's-eye check calls an edge rough. A pose can bunch a cuff's vertices (27 mm apart at rest, 9 mm
#: posed at the top of a swinging sleeve) into a bump that the smoothing at rest arc length cannot see.
POSED_SIGMA = 0.02


def boundary_smoothing(faces: np.ndarray, rest: np.ndarray, sigma: float = BOUNDARY_SIGMA,
                       spread: float = BOUNDARY_SPREAD) -> sparse.csr_matrix:
    """(V, V) csr: the identity, except that each vertex of a closed open-boundary loop of faces (F, 3) becomes
    2 g - G g of its loop, g the loop smoothed by a Gaussian of `sigma` metres of arc length along the loop as it
    lies in `rest` (V, 3) (the weights are fixed once, like the rest of S); each vertex of the first ring inside
    moves by `spread` times the mean move of its boundary neighbours. sigma 0: the identity."""
    n_vertices = len(rest)
    rows, cols, vals = [np.arange(n_vertices)], [np.arange(n_vertices)], [np.ones(n_vertices)]
    on_loop = np.zeros(n_vertices, dtype=bool)
    boundary = BoundaryLoops(faces)
    if sigma > 0:
        rest = np.asarray(rest, dtype=np.float64)
        for loop in boundary.each():
            lengths = np.linalg.norm(np.roll(rest[loop], -1, axis=0) - rest[loop], axis=1)
            position = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
            gap = np.abs(position[:, None] - position[None, :])
            gap = np.minimum(gap, lengths.sum() - gap)  # along the closed loop
            width = loop_width(sigma, lengths.sum())
            # each vertex stands for half of each of its two edges (uneven spacing)
            gauss = np.where(gap <= 4 * width, np.exp(-0.5 * (gap / width) ** 2), 0.0) \
                * (lengths + np.roll(lengths, 1))[None, :]
            gauss /= gauss.sum(axis=1, keepdims=True)
            weights = 2 * gauss - gauss @ gauss
            r, c = np.nonzero(np.abs(weights) > 1e-9)
            rows.append(loop[r]), cols.append(loop[c]), vals.append(weights[r, c])
            on_loop[loop] = True
    vals[0] = np.where(on_loop, 0.0, 1.0)
    matrix = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(n_vertices, n_vertices))
    if on_loop.any() and spread > 0 and len(boundary.ring):
        # the first ring inside follows its boundary neighbours' move by `spread`: moving the edge alone would tilt
        # the edge's triangles (a collar raised 2 cm over the neck lets the skin under its band out through it)
        move = matrix - sparse.identity(n_vertices, format="csr")
        inside, edge = boundary.ring[:, 0], boundary.loops[boundary.ring_edge]
        ring = sparse.csr_matrix((spread / boundary.count, (inside, edge)), shape=(n_vertices, n_vertices))
        matrix = matrix + ring @ move
    matrix.sum_duplicates()
    matrix.eliminate_zeros()
    return matrix


class BoundaryLoops:
    """The closed open-boundary loops of a topology, flat: loops (N,) int64 vertex ids, loop k at
    loops[starts[k]:starts[k + 1]]; the first ring inside as (vertex inside, its boundary neighbour) pairs, sorted by
    the inside vertex: ring (R, 2) int64, ring_edge (R,) the neighbour's position in `loops`, count (R,) the inside
    vertex's number of boundary neighbours."""

    def __init__(self, faces: np.ndarray):
        from ..garment.coverage import boundary_loops

        loops = boundary_loops(faces)
        self.loops = np.concatenate(loops) if loops else np.zeros(0, dtype=np.int64)
        self.starts = np.cumsum([0] + [len(loop) for loop in loops]).astype(np.int64)
        faces = np.asarray(faces, dtype=np.int64)
        position = np.full(int(faces.max()) + 1 if len(faces) else 0, -1, dtype=np.int64)
        position[self.loops] = np.arange(len(self.loops))
        pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        pairs = np.concatenate([pairs, pairs[:, ::-1]])
        pairs = np.unique(pairs[(position[pairs[:, 0]] < 0) & (position[pairs[:, 1]] >= 0)], axis=0)
        self.ring = pairs.astype(np.int64).reshape(-1, 2)
        self.ring_edge = position[self.ring[:, 1]]
        self.count = np.bincount(self.ring[:, 0])[self.ring[:, 0]].astype(np.float64) if len(pairs) else np.zeros(0)

    def each(self) -> list[np.ndarray]:
        """The loops one by one: (L,) vertex ids each."""
        return np.split(self.loops, self.starts[1:-1])


@numba.njit(cache=True, nogil=True)
def loop_width(sigma, total):
    """The smoothing width of a closed loop `total` metres long: sigma, at most half the radius of the loop's circle
    (a round loop then keeps 98.6 % of its radius)."""
    return min(sigma, total / (4.0 * np.pi))


@numba.njit(cache=True, nogil=True)
def _loop_arc(points, loop):
    """(arc (L,) from the loop's first vertex, total length) of the closed loop of vertex ids loop (L,) over
    points (V, 3)."""
    n = loop.shape[0]
    arc = np.empty(n)
    total = 0.0
    for i in range(n):
        arc[i] = total
        a, b = loop[i], loop[(i + 1) % n]
        total += np.sqrt((points[b, 0] - points[a, 0]) ** 2 + (points[b, 1] - points[a, 1]) ** 2
                         + (points[b, 2] - points[a, 2]) ** 2)
    return arc, total


@numba.njit(cache=True, nogil=True)
def _loop_span(points, loops, starts, k, sigma):
    """(first position, length, arc (L,), total length, smoothing width) of loop k of the flat loops (starts (K+1,))
    over points (V, 3)."""
    a, n = starts[k], starts[k + 1] - starts[k]
    arc, total = _loop_arc(points, loops[a:a + n])
    return a, n, arc, total, loop_width(sigma, total)


@numba.njit(cache=True, nogil=True)
def _gauss_weights(arc, total, width):
    """The Gaussian of `width` over the arc length arc (L,) of a closed loop (arc[0] = 0, total its length) as a
    sparse (L, L) matrix (starts (L + 1,), columns, weights; rows sum to 1): each vertex weighs the half of each edge
    beside it; each row walks both ways from its vertex to 3 widths (weights beyond are under 1.2 %)."""
    n = arc.shape[0]
    reach = min(3.0 * width, 0.5 * total)
    spans = np.empty((n, 2), dtype=np.int64)  # how far each row reaches forward and back, in vertices
    for i in range(n):
        for side in range(2):
            step = 1
            while step < n:
                j = (i + step) % n if side == 0 else (i - step) % n
                gap = abs(arc[j] - arc[i])
                if min(gap, total - gap) > reach:
                    break
                step += 1
            spans[i, side] = step - 1
    starts = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        starts[i + 1] = starts[i] + min(spans[i, 0] + spans[i, 1] + 1, n)
    columns = np.empty(starts[n], dtype=np.int64)
    weights = np.empty(starts[n])
    for i in range(n):
        k, wsum = starts[i], 0.0
        for step in range(-spans[i, 1], spans[i, 0] + 1):
            if k == starts[i + 1]:
                break
            j = (i + step) % n
            gap = abs(arc[j] - arc[i])
            gap = min(gap, total - gap)
            before = arc[j] - arc[j - 1] if j > 0 else total - arc[n - 1]
            after = arc[j + 1] - arc[j] if j + 1 < n else total - arc[j]
            columns[k] = j
            weights[k] = np.exp(-0.5 * (gap / width) ** 2) * (before + after)
            wsum += weights[k]
            k += 1
        for k in range(starts[i], starts[i + 1]):
            weights[k] /= wsum
    return starts, columns, weights


@numba.njit(cache=True, nogil=True)
def _apply_sparse(starts, columns, weights, points, out):
    for i in range(starts.shape[0] - 1):
        a0 = a1 = a2 = 0.0
        for k in range(starts[i], starts[i + 1]):
            j, w = columns[k], weights[k]
            a0 += w * points[j, 0]
            a1 += w * points[j, 1]
            a2 += w * points[j, 2]
        out[i, 0], out[i, 1], out[i, 2] = a0, a1, a2


@numba.njit(cache=True, nogil=True)
def _smooth_loops(vertices, loops, starts, ring, ring_edge, count, sigma):
    move = np.zeros((loops.shape[0], 3))
    for k in range(starts.shape[0] - 1):
        a, n, arc, total, width = _loop_span(vertices, loops, starts, k, sigma)
        if width <= 0.0:
            continue
        points = np.empty((n, 3))
        for i in range(n):
            for c in range(3):
                points[i, c] = vertices[loops[a + i], c]
        rows, columns, weights = _gauss_weights(arc, total, width)
        once = np.empty((n, 3))
        twice = np.empty((n, 3))
        _apply_sparse(rows, columns, weights, points, once)
        _apply_sparse(rows, columns, weights, once, twice)
        for i in range(n):
            for c in range(3):
                move[a + i, c] = 2.0 * once[i, c] - twice[i, c] - points[i, c]  # shrink-compensated
    for r in range(ring.shape[0]):  # the first ring inside follows its boundary neighbours (the edge keeps its slope)
        for c in range(3):
            vertices[ring[r, 0], c] += move[ring_edge[r], c] / count[r]
    for i in range(loops.shape[0]):
        for c in range(3):
            vertices[loops[i], c] += move[i, c]


@numba.njit(cache=True, nogil=True)
def _spread_moves(vertices, before, loops, starts, ring, ring_edge, count, sigma):
    n_loop = loops.shape[0]
    moves = np.empty((n_loop, 3))  # each loop vertex's move by the push
    sizes = np.empty(n_loop)
    for i in range(n_loop):
        for c in range(3):
            moves[i, c] = vertices[loops[i], c] - before[loops[i], c]
        sizes[i] = np.sqrt(moves[i, 0] ** 2 + moves[i, 1] ** 2 + moves[i, 2] ** 2)
    chosen = np.arange(n_loop)  # whose move each loop vertex takes, and faded by how much
    fade = np.ones(n_loop)
    for k in range(starts.shape[0] - 1):
        a, n, arc, total, width = _loop_span(before, loops, starts, k, sigma)
        if width <= 0.0:
            continue
        reach = min(3.0 * width, 0.5 * total)
        for j in range(n):  # each pushed vertex offers its faded move to the vertices within reach
            if sizes[a + j] == 0.0:
                continue
            for side in range(2):
                for step in range(0 if side == 0 else 1, n):
                    i = (j + step) % n if side == 0 else (j - step) % n
                    gap = abs(arc[j] - arc[i])
                    gap = min(gap, total - gap)
                    if gap > reach:
                        break
                    g = np.exp(-0.5 * (gap / width) ** 2)
                    if g * sizes[a + j] > fade[a + i] * sizes[chosen[a + i]]:
                        chosen[a + i], fade[a + i] = a + j, g
    # the first ring inside: the larger of its own move and the mean of its boundary neighbours' (the edge keeps its
    # slope, and no vertex moves more than the largest move); pairs are sorted by the inside vertex
    r = 0
    while r < ring.shape[0]:
        inside = ring[r, 0]
        f0 = f1 = f2 = 0.0
        while r < ring.shape[0] and ring[r, 0] == inside:
            e, share = ring_edge[r], fade[ring_edge[r]] / count[r]
            f0 += share * moves[chosen[e], 0]
            f1 += share * moves[chosen[e], 1]
            f2 += share * moves[chosen[e], 2]
            r += 1
        own = ((vertices[inside, 0] - before[inside, 0]) ** 2 + (vertices[inside, 1] - before[inside, 1]) ** 2
               + (vertices[inside, 2] - before[inside, 2]) ** 2)
        if f0 * f0 + f1 * f1 + f2 * f2 > own:
            vertices[inside, 0] = before[inside, 0] + f0
            vertices[inside, 1] = before[inside, 1] + f1
            vertices[inside, 2] = before[inside, 2] + f2
    for i in range(n_loop):
        for c in range(3):
            vertices[loops[i], c] = before[loops[i], c] + fade[i] * moves[chosen[i], c]


def spread_edge_moves(vertices: np.ndarray, before: np.ndarray, loops: BoundaryLoops, sigma: float = POSED_SIGMA):
    """After a per-vertex push of vertices (V, 3) (changed in place) that stood at before (V, 3): each open boundary
    vertex takes the largest of its neighbours' moves along the loop, faded by a Gaussian of `sigma` metres of arc
    length (its own if that is larger), so a vertex pushed alone becomes a smooth bump, not a tooth; each vertex of
    the first ring inside the larger of its own move and the mean of its boundary neighbours'. No vertex moves less
    than the push moved it, or more than the largest move."""
    if len(loops.loops) and sigma > 0:
        _spread_moves(vertices, before, loops.loops, loops.starts, loops.ring, loops.ring_edge, loops.count,
                      float(sigma))


def smooth_posed_boundaries(vertices: np.ndarray, loops: BoundaryLoops, sigma: float = POSED_SIGMA) -> None:
    """Smooth each open boundary loop of vertices (V, 3) (changed in place) by a shrink-compensated Gaussian of
    `sigma` metres along its arc length as posed (2 G x - G G x), the first ring of vertices inside moving by the mean
    of its boundary neighbours' moves."""
    if len(loops.loops) and sigma > 0:
        _smooth_loops(vertices, loops.loops, loops.starts, loops.ring, loops.ring_edge, loops.count, float(sigma))


def loop_stencils(faces: np.ndarray, n_vertices: int):
    """One round of Loop subdivision: (S (V + E, V) csr float64, refined faces (4F, 3) int32, edges (E, 2)).

    Rows 0..V-1 are the old vertices, row V + e the new vertex on edge e (edges sorted pairs, np.unique order)."""
    faces = np.asarray(faces, dtype=np.int64)
    f = len(faces)
    half = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)  # (3F, 2)
    opposite = faces[:, [2, 0, 1]].reshape(-1)  # corner opposite each half-edge
    key = np.sort(half, axis=1)
    edges, edge_of, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    edge_of = edge_of.reshape(-1)
    n_edges = len(edges)
    interior = counts == 2

    rows, cols, vals = [], [], []
    # new edge vertices
    e_ids = np.arange(n_edges)
    rows += [n_vertices + e_ids] * 2
    cols += [edges[:, 0], edges[:, 1]]
    w_end = np.where(interior, 3.0 / 8.0, 0.5)
    vals += [w_end, w_end]
    inner_half = interior[edge_of]
    rows.append(n_vertices + edge_of[inner_half])
    cols.append(opposite[inner_half])
    vals.append(np.full(inner_half.sum(), 1.0 / 8.0))

    # old vertices: neighbours from the edges; open-edge neighbours from the edges used once
    open_edges = edges[counts == 1]
    crease = edges[counts > 2]
    neighbours = [[] for _ in range(n_vertices)]
    for a, b in edges:
        neighbours[a].append(b)
        neighbours[b].append(a)
    rim = [[] for _ in range(n_vertices)]
    for a, b in np.concatenate([open_edges, crease]):
        rim[a].append(b)
        rim[b].append(a)
    for v in range(n_vertices):
        ring = neighbours[v]
        if not ring:
            rows.append(np.array([v])), cols.append(np.array([v])), vals.append(np.array([1.0]))
        elif rim[v]:
            if len(rim[v]) == 2:
                rows.append(np.array([v, v, v])), cols.append(np.array([v, *rim[v]]))
                vals.append(np.array([0.75, 0.125, 0.125]))
            else:  # a corner or a non-manifold vertex: keep it
                rows.append(np.array([v])), cols.append(np.array([v])), vals.append(np.array([1.0]))
        else:
            n = len(ring)
            beta = 3.0 / 16.0 if n == 3 else 3.0 / (8.0 * n)
            rows.append(np.full(n + 1, v)), cols.append(np.array([v, *ring]))
            vals.append(np.array([1.0 - n * beta] + [beta] * n))
    matrix = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(n_vertices + n_edges, n_vertices))
    matrix.sum_duplicates()

    mid = n_vertices + edge_of.reshape(f, 3)  # new vertex on edges (0,1), (1,2), (2,0) of each face
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
    refined = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1), np.stack([c, ca, bc], 1),
                              np.stack([ab, bc, ca], 1)]).astype(np.int32)
    return matrix, refined, edges


@numba.njit(cache=True, nogil=True, fastmath=True)
def _refine(indptr, indices, data, vertices, normals, offset, out):
    """out (V', 3) = S vertices + offset * normalize(S normals), S in CSR form (indptr, indices, data)."""
    for r in range(out.shape[0]):
        x = y = z = nx = ny = nz = 0.0
        for k in range(indptr[r], indptr[r + 1]):
            c = indices[k]
            w = data[k]
            x += w * vertices[c, 0]
            y += w * vertices[c, 1]
            z += w * vertices[c, 2]
            nx += w * normals[c, 0]
            ny += w * normals[c, 1]
            nz += w * normals[c, 2]
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        s = offset / length if length > 0.0 else 0.0
        out[r, 0] = x + s * nx
        out[r, 1] = y + s * ny
        out[r, 2] = z + s * nz
    return out


class LoopSubdivision:
    """`levels` rounds of Loop subdivision of topology faces (F, 3) on V vertices, as one sparse matrix.

    `faces` (F', 3) int32 and `n_vertices` describe the refined mesh; `apply(vertices (V, 3))` returns the refined
    vertices (V', 3) in an internal buffer (overwritten by the next call) of the input's dtype. rest (V, 3): the
    garment at rest, whose open boundaries are smoothed by boundary_sigma metres (boundary_smoothing) before the
    first round; None or sigma 0: not smoothed."""

    def __init__(self, faces, n_vertices: int, levels: int = 1, offset: float = OFFSET, rest=None,
                 boundary_sigma: float = BOUNDARY_SIGMA):
        if levels not in (0, 1, 2, 3):
            raise ValueError(f"subdivision levels must be 0, 1, 2 or 3, got {levels!r}")
        self.coarse_faces = np.ascontiguousarray(faces, dtype=np.int32)
        self.levels, self.offset = int(levels), float(offset)
        self.boundary_sigma = float(boundary_sigma) if self.levels and rest is not None else 0.0
        if self.boundary_sigma:
            if len(rest) != n_vertices:
                raise ValueError(f"rest has {len(rest)} vertices, the topology {n_vertices}")
            matrix = boundary_smoothing(self.coarse_faces, rest, self.boundary_sigma)
        else:
            matrix = sparse.identity(int(n_vertices), format="csr")
        refined = self.coarse_faces
        for _ in range(self.levels):
            step, refined, _ = loop_stencils(refined, matrix.shape[0])
            matrix = (step @ matrix).tocsr()
        matrix.eliminate_zeros()
        self.matrix = matrix
        self.faces = np.ascontiguousarray(refined, dtype=np.int32)
        self.n_vertices = matrix.shape[0]
        self._csr = (matrix.indptr.astype(np.int64), matrix.indices.astype(np.int64))
        self._data = {}
        self._buffers = {}

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """Refined vertices (V', 3) of coarse vertices (V, 3), offset along the normals."""
        if self.levels == 0:
            return vertices
        dtype = vertices.dtype
        if dtype not in self._buffers:
            self._data[dtype] = self.matrix.data.astype(dtype)
            self._buffers[dtype] = (np.empty((self.n_vertices, 3), dtype=dtype),
                                    np.empty((self.matrix.shape[1], 3), dtype=dtype))
        out, normals = self._buffers[dtype]
        face_vertex_normals(vertices, self.coarse_faces, normals)
        return _refine(*self._csr, self._data[dtype], vertices, normals, dtype.type(self.offset), out)
