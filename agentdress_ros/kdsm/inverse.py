"""Inverse embedding (paper Sec. 4-5): the material-space position u^m(theta) of each ground-truth cloth vertex.

A posed vertex u^GT lies in one or more skinned tets (the skinned KDSM inverts and overlaps itself, between arm and
torso above all). `find_candidate_parents` lists every posed tet holding it up to a barycentric weight of -eps
(offline, per frame: the query points are binned in a grid, each tet visits the cells its box covers);
`prune_candidates` keeps, from the deepest tet down, one tet per neighbourhood (the tets sharing a vertex with the
face nearest the point only hold it through round-off). Each surviving candidate c gives an exact
u^m_c = sum_k lambda_k v_k^m.

Methods of Sec. 5 for choosing among them:
- Method 1: a random candidate (exact, high variance).
- Method 2: an offset-from-the-body guess: the posed vertex's closest point on the posed body and its offset
  along the normal, carried to the rest body (Jin et al.'s UVN offsets); low variance, not exact.
- Hybrid: one candidate -> Method 1; several -> the one closest to Method 2's guess if within 1 cm; the rest by
  repeated Poisson (harmonic) morphs of the displacement from Method 2's guess with the defined vertices as
  Dirichlet conditions, validating a vertex when one of its candidates lies within 1 cm of its morphed position;
  when a morph validates nothing new, the remaining vertices take their morphed positions.
A vertex in no posed tet (it left the shell) falls back to skinning: its u^m is its LBS-unposed position, and it
is counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..garment.binding import evaluate_surface_binding, vertex_normals
from .surface import closest_in_groups

#: Hybrid vertex status codes.
SINGLE, AGREED, MORPH_VALIDATED, MORPHED, FALLBACK = 0, 1, 2, 3, 4
STATUS_NAMES = ("single", "agreed", "morph_validated", "morphed", "fallback")


@numba.njit(cache=True, nogil=True)
def find_candidate_parents(posed, tets, points, cell, eps, counts, cand_tets, cand_bary):
    """All posed tets holding each point with every barycentric weight >= -eps.

    posed (N, 3) skinned tet vertices, tets (T, 4), points (P, 3), cell: grid step for binning the points (about
    a tet's size). Writes counts (P,), cand_tets (P, C) and cand_bary (P, C, 4) for up to C candidates per point;
    returns how many candidates did not fit. Degenerate (flat) posed tets are skipped; inverted ones count.
    """
    n_points = points.shape[0]
    capacity = cand_tets.shape[1]
    low = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    for a in range(3):
        low[a] = points[:, a].min() - 0.5 * cell
        dims[a] = int((points[:, a].max() - low[a]) / cell) + 2
    n_cells = dims[0] * dims[1] * dims[2]
    start = np.zeros(n_cells + 1, dtype=np.int64)
    point_cell = np.empty(n_points, dtype=np.int64)
    for p in range(n_points):
        i = int((points[p, 0] - low[0]) / cell)
        j = int((points[p, 1] - low[1]) / cell)
        k = int((points[p, 2] - low[2]) / cell)
        point_cell[p] = (i * dims[1] + j) * dims[2] + k
        start[point_cell[p] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n_points, dtype=np.int64)
    for p in range(n_points):
        order[fill[point_cell[p]]] = p
        fill[point_cell[p]] += 1
    counts[:] = 0
    overflow = 0
    lo = np.empty(3)
    hi = np.empty(3)
    for t in range(tets.shape[0]):
        v0, v1, v2, v3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        size = 0.0
        for a in range(3):
            lo[a] = min(min(posed[v0, a], posed[v1, a]), min(posed[v2, a], posed[v3, a]))
            hi[a] = max(max(posed[v0, a], posed[v1, a]), max(posed[v2, a], posed[v3, a]))
            size = max(size, hi[a] - lo[a])
        pad = eps * size + 1e-12  # the slightly thickened box of the paper: weights down to -eps reach this far
        i0 = max(int((lo[0] - pad - low[0]) / cell), 0)
        j0 = max(int((lo[1] - pad - low[1]) / cell), 0)
        k0 = max(int((lo[2] - pad - low[2]) / cell), 0)
        i1 = min(int((hi[0] + pad - low[0]) / cell), dims[0] - 1)
        j1 = min(int((hi[1] + pad - low[1]) / cell), dims[1] - 1)
        k1 = min(int((hi[2] + pad - low[2]) / cell), dims[2] - 1)
        if hi[0] + pad < low[0] or hi[1] + pad < low[1] or hi[2] + pad < low[2] or i0 > i1 or j0 > j1 or k0 > k1:
            continue
        inverse_ready = False
        degenerate = False
        m00 = m01 = m02 = m10 = m11 = m12 = m20 = m21 = m22 = 0.0
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    c = (i * dims[1] + j) * dims[2] + k
                    for s in range(start[c], start[c + 1]):
                        p = order[s]
                        x, y, z = points[p, 0], points[p, 1], points[p, 2]
                        if (x < lo[0] - pad or x > hi[0] + pad or y < lo[1] - pad or y > hi[1] + pad
                                or z < lo[2] - pad or z > hi[2] + pad):
                            continue
                        if not inverse_ready:
                            inverse_ready = True
                            a0 = posed[v1, 0] - posed[v0, 0]
                            a1 = posed[v1, 1] - posed[v0, 1]
                            a2 = posed[v1, 2] - posed[v0, 2]
                            b0 = posed[v2, 0] - posed[v0, 0]
                            b1 = posed[v2, 1] - posed[v0, 1]
                            b2 = posed[v2, 2] - posed[v0, 2]
                            c0 = posed[v3, 0] - posed[v0, 0]
                            c1 = posed[v3, 1] - posed[v0, 1]
                            c2 = posed[v3, 2] - posed[v0, 2]
                            det = a0 * (b1 * c2 - b2 * c1) - b0 * (a1 * c2 - a2 * c1) + c0 * (a1 * b2 - a2 * b1)
                            if abs(det) < 1e-9 * size * size * size:
                                degenerate = True
                            else:
                                inv = 1.0 / det  # rows of the inverse of the edge-column matrix [a b c]
                                m00 = (b1 * c2 - b2 * c1) * inv
                                m01 = (b2 * c0 - b0 * c2) * inv
                                m02 = (b0 * c1 - b1 * c0) * inv
                                m10 = (a2 * c1 - a1 * c2) * inv
                                m11 = (a0 * c2 - a2 * c0) * inv
                                m12 = (a1 * c0 - a0 * c1) * inv
                                m20 = (a1 * b2 - a2 * b1) * inv
                                m21 = (a2 * b0 - a0 * b2) * inv
                                m22 = (a0 * b1 - a1 * b0) * inv
                        if degenerate:
                            continue
                        dx = x - posed[v0, 0]
                        dy = y - posed[v0, 1]
                        dz = z - posed[v0, 2]
                        l1 = m00 * dx + m01 * dy + m02 * dz
                        l2 = m10 * dx + m11 * dy + m12 * dz
                        l3 = m20 * dx + m21 * dy + m22 * dz
                        l0 = 1.0 - l1 - l2 - l3
                        if min(min(l0, l1), min(l2, l3)) < -eps:
                            continue
                        n = counts[p]
                        if n >= capacity:
                            overflow += 1
                            continue
                        cand_tets[p, n] = t
                        cand_bary[p, n, 0] = l0
                        cand_bary[p, n, 1] = l1
                        cand_bary[p, n, 2] = l2
                        cand_bary[p, n, 3] = l3
                        counts[p] = n + 1
    return overflow


@numba.njit(cache=True, nogil=True)
def prune_candidates(tets, counts, cand_tets, cand_bary):
    """Sec. 5's pruning, in place: per point, candidates sorted by their smallest weight (deepest first); each kept
    tet removes the later candidates that share a vertex with its face across from its smallest-weight vertex.
    counts (P,), cand_tets (P, C), cand_bary (P, C, 4) as written by find_candidate_parents."""
    capacity = cand_tets.shape[1]
    depth = np.empty(capacity)
    order = np.empty(capacity, dtype=np.int64)
    removed = np.empty(capacity, dtype=np.bool_)
    kept_tets = np.empty(capacity, dtype=cand_tets.dtype)
    kept_bary = np.empty((capacity, 4))
    for p in range(counts.shape[0]):
        n = counts[p]
        if n <= 1:
            continue
        for i in range(n):
            depth[i] = cand_bary[p, i].min()
            order[i] = i
            removed[i] = False
        for i in range(1, n):  # insertion sort, deepest first (n is small)
            j = i
            while j > 0 and depth[order[j]] > depth[order[j - 1]]:
                order[j], order[j - 1] = order[j - 1], order[j]
                j -= 1
        kept = 0
        for a in range(n):
            i = order[a]
            if removed[i]:
                continue
            t = cand_tets[p, i]
            kept_tets[kept] = t
            kept_bary[kept] = cand_bary[p, i]
            kept += 1
            shallow = np.argmin(cand_bary[p, i])
            for b in range(a + 1, n):
                j = order[b]
                if removed[j]:
                    continue
                other = cand_tets[p, j]
                for c in range(4):
                    if c == shallow:
                        continue
                    v = tets[t, c]
                    if (tets[other, 0] == v or tets[other, 1] == v or tets[other, 2] == v
                            or tets[other, 3] == v):
                        removed[j] = True
                        break
        counts[p] = kept
        for i in range(kept):
            cand_tets[p, i] = kept_tets[i]
            cand_bary[p, i] = kept_bary[i]


@dataclass(frozen=True)
class Candidates:
    """Candidate parents of P posed points after pruning; C slots per point, the first counts[p] valid."""

    counts: np.ndarray  # (P,) int
    tets: np.ndarray  # (P, C) int32
    barycentric: np.ndarray  # (P, C, 4)
    material: np.ndarray  # (P, C, 3) u^m of each candidate (NaN in unused slots)
    overflow: int  # candidates that did not fit the C slots (before pruning)


def candidate_parents(kdsm, posed_vertices, points, eps: float = 1e-4, capacity: int = 48) -> Candidates:
    """Pruned candidate parent tets of points (P, 3) in the KDSM posed to posed_vertices (N, 3)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    counts = np.zeros(len(points), dtype=np.int64)
    tets = np.full((len(points), capacity), -1, dtype=np.int32)
    bary = np.zeros((len(points), capacity, 4))
    overflow = find_candidate_parents(np.ascontiguousarray(posed_vertices, dtype=np.float64), kdsm.tets, points,
                                      2.0 * kdsm.spacing, eps, counts, tets, bary)
    prune_candidates(kdsm.tets, counts, tets, bary)
    valid = np.arange(capacity)[None, :] < counts[:, None]
    material = np.full((len(points), capacity, 3), np.nan)
    material[valid] = np.einsum("ck,ckd->cd", bary[valid], kdsm.vertices[kdsm.tets[tets[valid]]])
    return Candidates(counts, tets, bary, material, int(overflow))


def surface_offset_guess(posed_body, rest_body, faces, points, face_groups=None, point_groups=None) -> np.ndarray:
    """Method 2's material-space guess (P, 3): each posed point's closest point on the posed body surface
    (posed_body (N, 3), faces (F, 3)) and its offset along the interpolated normal, carried to the rest body
    rest_body (N, 3) with the rest normals.

    face_groups (F,) int and point_groups (P, G) bool restrict each point to the faces of its groups (e.g. the bone
    regions it is skinned to): a torso vertex never takes its offset from a hand resting on the torso, whose rest
    place is far away. Without them, every face is a candidate.
    """
    binding = closest_in_groups(points, posed_body, faces, face_groups, point_groups)
    return evaluate_surface_binding(binding, rest_body, vertex_normals(rest_body, faces))


def region_groups(body, skin_indices, skin_weights, minimum: float = 0.05):
    """(face_groups (F,) the dominant bone region of each visible body face, point_groups (P, R) the regions that
    carry at least `minimum` of each point's skin weight (skin_indices/skin_weights (P, K)), its dominant one
    always): the restriction of surface_offset_guess."""
    from ..garment.binding import region_weights

    body_regions = region_weights(body.skin_indices, body.skin_weights, body.bone_names)
    face_groups = body_regions[body.body_faces].mean(axis=1).argmax(axis=1)
    point_regions = region_weights(skin_indices, skin_weights, body.bone_names)
    point_groups = point_regions >= minimum
    point_groups[np.arange(len(point_groups)), point_regions.argmax(axis=1)] = True
    return face_groups, point_groups


def graph_laplacian(edges: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Uniform (graph) Laplacian D - A (V, V) of a mesh's edges (E, 2)."""
    i, j = edges[:, 0], edges[:, 1]
    adjacency = sp.coo_matrix((np.ones(2 * len(edges)), (np.concatenate([i, j]), np.concatenate([j, i]))),
                              shape=(n_vertices, n_vertices)).tocsr()
    return (sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()


def harmonic_fill(laplacian: sp.csr_matrix, values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(V, 3) `values` kept where `known` (V,) and filled elsewhere by the harmonic (Laplace) interpolation with the
    known vertices as Dirichlet conditions: the Poisson morph of Cong et al. 2015 applied to a displacement field.
    A mesh piece with no known vertex gets zero (a tiny diagonal keeps its system regular)."""
    out = np.where(known[:, None], values, 0.0)
    unknown = np.flatnonzero(~known)
    if len(unknown) == 0:
        return out
    known_ids = np.flatnonzero(known)
    system = laplacian[unknown][:, unknown] + sp.identity(len(unknown)) * 1e-9
    rhs = -(laplacian[unknown][:, known_ids] @ values[known_ids])
    out[unknown] = splu(system.tocsc()).solve(rhs)
    return out


def choose_nearest(candidates: Candidates, targets: np.ndarray, rows: np.ndarray):
    """For the points `rows`, (index of their candidate nearest to targets (P, 3), its distance)."""
    gap = np.linalg.norm(candidates.material[rows] - targets[rows][:, None, :], axis=2)
    gap = np.where(np.isnan(gap), np.inf, gap)
    best = gap.argmin(axis=1)
    return best, gap[np.arange(len(rows)), best]


def method1_material(candidates: Candidates, fallback: np.ndarray, rng: np.random.Generator):
    """Method 1: (u^m (P, 3), status (P,)) with a random candidate per point; fallback (P, 3) where none."""
    material = np.asarray(fallback, dtype=np.float64).copy()
    status = np.full(len(material), FALLBACK, dtype=np.int8)
    some = np.flatnonzero(candidates.counts > 0)
    pick = (rng.random(len(some)) * candidates.counts[some]).astype(np.int64)
    material[some] = candidates.material[some, pick]
    status[some] = np.where(candidates.counts[some] == 1, SINGLE, AGREED)
    return material, status


def hybrid_material(candidates: Candidates, guess: np.ndarray, fallback: np.ndarray, laplacian: sp.csr_matrix,
                    threshold: float = 0.01, relaxed: tuple = (), max_rounds: int = 100):
    """The hybrid method of Sec. 5: (u^m (P, 3), status (P,) of SINGLE ... FALLBACK, morph rounds).

    guess (P, 3) Method 2's material positions, fallback (P, 3) the LBS-unposed positions used for points in no
    tet, laplacian (P, P) the garment's mesh Laplacian, threshold 1 cm as in the paper. relaxed: larger thresholds
    tried in turn once the morphs stop validating vertices at the previous one (not in the paper, which stops at
    1 cm; each still picks an exact candidate, the one nearest a smooth morph, instead of an inexact morph value).
    """
    guess = np.asarray(guess, dtype=np.float64)
    material = guess.copy()
    status = np.full(len(guess), MORPHED, dtype=np.int8)
    counts = candidates.counts
    single = np.flatnonzero(counts == 1)
    material[single] = candidates.material[single, 0]
    status[single] = SINGLE
    multi = np.flatnonzero(counts > 1)
    best, gap = choose_nearest(candidates, guess, multi)
    agreed = gap < threshold
    material[multi[agreed]] = candidates.material[multi[agreed], best[agreed]]
    status[multi[agreed]] = AGREED
    none = counts == 0
    status[none] = FALLBACK
    schedule = [threshold, *relaxed]
    rounds = 0
    morphed = guess
    while rounds < max_rounds and schedule:
        known = (status == SINGLE) | (status == AGREED) | (status == MORPH_VALIDATED)
        open_rows = np.flatnonzero((status == MORPHED) & (counts > 0))
        if len(open_rows) == 0 or not known.any():
            break
        rounds += 1
        morphed = guess + harmonic_fill(laplacian, material - guess, known)
        best, gap = choose_nearest(candidates, morphed, open_rows)
        valid = gap < schedule[0]
        if not valid.any():
            schedule.pop(0)
            continue
        rows = open_rows[valid]
        material[rows] = candidates.material[rows, best[valid]]
        status[rows] = MORPH_VALIDATED
    if (status == MORPHED).any() and (status != MORPHED).any():
        known = (status == SINGLE) | (status == AGREED) | (status == MORPH_VALIDATED)
        morphed = guess + harmonic_fill(laplacian, material - guess, known)
    left = status == MORPHED
    material[left] = morphed[left]
    material[none] = np.asarray(fallback, dtype=np.float64)[none]
    return material, status, rounds
