"""Which body faces a garment covers: the display leaves them out, so no skin shows through the cloth.

Game engines and MakeHuman (`delete_verts` in `.mhclo`) hide the body surface under a garment. Here the covered
region is computed geometrically, once, from the garment and the body at rest: a body vertex is covered when the
closest point of the garment lies in front of it (along its normal, within `max_gap`) and at least `margin` away
(geodesically, over the garment) from the garment's open edges - hems, cuffs, neckline, waist - so that the body
keeps a band of faces under every edge and no gap opens when the cloth slides over the skin. A body face is covered
when all its corners are. A MakeHuman garment's own `delete_verts` are used as it states them.

Pure array functions. Shapes: N body vertices, F body triangles, V garment vertices, G garment triangles.
"""
from __future__ import annotations

import itertools

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from .binding import face_normals, mesh_edges, vertex_normals

#: Defaults: a band of 1.5 cm of body kept under every garment edge; cloth up to 6 cm off the skin still covers it.
MARGIN = 0.015
MAX_GAP = 0.06
#: Body vertices in that band sink up to this far under the cloth (at rest, so it costs nothing per frame).
TUCK = 0.015
NO_EDGE = 1e9
#: poke_through: a cloth point this much closer to another part of the body than to the face judged against it
#: belongs to that part.
OWNER_TOLERANCE = 0.01
#: cloth_over: how far behind a skin point its cloth may lie and still cover it (the skin poking through).
BELOW = 0.03

__all__ = ["BELOW", "MARGIN", "MAX_GAP", "TUCK", "body_part_labels", "boundary_distance", "boundary_loops",
           "cloth_over", "cover_depth", "covered_faces", "covered_vertices", "faces_with_vertices",
           "garment_covered_faces", "poke_through", "sloped", "surface_side", "tuck_depth"]


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) edges of triangles (G, 3) used by one triangle only (sorted vertex pairs)."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The open boundaries of triangles faces (G, 3): a list of (L,) vertex-id loops, each in the direction its
    faces run (edge a->b of a face), so a fan over it on the reverse winding closes the surface consistently."""
    faces = np.asarray(faces, dtype=np.int64)
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = directed[counts[inverse.ravel()] == 1]
    following = {int(a): int(b) for a, b in border}
    loops, done = [], set()
    for start in following:
        if start in done:
            continue
        loop, v = [], start
        while v not in done and v in following:
            done.add(v)
            loop.append(v)
            v = following[v]
        if len(loop) >= 3 and v == start:
            loops.append(np.array(loop, dtype=np.int64))
    return loops


def boundary_distance(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) shortest distance along the mesh edges from each vertex (V, 3) to an open edge of faces (G, 3).

    NO_EDGE (1e9, finite so that it interpolates) for a closed mesh and for components without an open edge."""
    border = np.unique(boundary_edges(faces))
    if len(border) == 0:
        return np.full(len(vertices), NO_EDGE)
    edges, length = _edge_lengths(vertices, faces)
    graph = coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2).tocsr()
    return np.minimum(dijkstra(graph, directed=False, indices=border, min_only=True), NO_EDGE)


def _edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> tuple:
    """(edges (E, 2), their lengths (E,)) of a triangle mesh (V, 3), (F, 3): the graph of its geodesic fields."""
    edges = mesh_edges(faces)
    return edges, np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)


@numba.njit(cache=True, nogil=True)
def _closest_on_triangles(points, vertices, faces, offsets, candidates, directions, normals, closest, barycentric,
                          distance, face_ids):
    """For each point p (P, 3): the closest point on the triangles candidates[offsets[p]:offsets[p + 1]] of faces
    (G, 3) over vertices (V, 3), only those whose normal (G, 3) faces the point's direction (P, 3) when directions
    has rows (else every candidate). Writes closest (P, 3), barycentric (P, 3), distance (P,) (inf: no candidate)
    and face_ids (P,) (-1). The closest point on a triangle by its Voronoi regions (Ericson, Real-Time Collision
    Detection, 5.1.5)."""
    use_directions = directions.shape[0] > 0
    for p in range(points.shape[0]):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        best = np.inf
        face_ids[p] = -1
        for i in range(offsets[p], offsets[p + 1]):
            f = candidates[i]
            if use_directions and (normals[f, 0] * directions[p, 0] + normals[f, 1] * directions[p, 1]
                                   + normals[f, 2] * directions[p, 2]) <= 0.0:
                continue
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
            abx, aby, abz = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
            acx, acy, acz = vertices[c, 0] - ax, vertices[c, 1] - ay, vertices[c, 2] - az
            apx, apy, apz = px - ax, py - ay, pz - az
            d1 = abx * apx + aby * apy + abz * apz
            d2 = acx * apx + acy * apy + acz * apz
            bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
            d3 = abx * bpx + aby * bpy + abz * bpz
            d4 = acx * bpx + acy * bpy + acz * bpz
            cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
            d5 = abx * cpx + aby * cpy + abz * cpz
            d6 = acx * cpx + acy * cpy + acz * cpz
            va = d3 * d6 - d5 * d4
            vb = d5 * d2 - d1 * d6
            vc = d1 * d4 - d3 * d2
            if d1 <= 0.0 and d2 <= 0.0:
                v, w = 0.0, 0.0
            elif d3 >= 0.0 and d4 <= d3:
                v, w = 1.0, 0.0
            elif d6 >= 0.0 and d5 <= d6:
                v, w = 0.0, 1.0
            elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
                v, w = d1 / (d1 - d3), 0.0
            elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
                v, w = 0.0, d2 / (d2 - d6)
            elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
                w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                v = 1.0 - w
            else:
                denominator = 1.0 / (va + vb + vc)
                v, w = vb * denominator, vc * denominator
            qx = ax + abx * v + acx * w
            qy = ay + aby * v + acy * w
            qz = az + abz * v + acz * w
            d = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
            if d < best:
                best = d
                face_ids[p] = f
                closest[p, 0], closest[p, 1], closest[p, 2] = qx, qy, qz
                barycentric[p, 0], barycentric[p, 1], barycentric[p, 2] = 1.0 - v - w, v, w
        distance[p] = np.sqrt(best)


def _triangles_near(points, vertices, faces, reach):
    """(offsets (P + 1,), candidates) CSR: for each point (P, 3), the triangles (G, 3) whose centre lies within
    `reach` (scalar or (P,)) plus the largest triangle's radius - every triangle with a point within `reach`."""
    corners = vertices[faces]
    centres = corners.mean(axis=1)
    radius = float(np.linalg.norm(corners - centres[:, None], axis=2).max()) if len(faces) else 0.0
    lists = cKDTree(centres).query_ball_point(points, np.asarray(reach) + radius) if len(points) else []
    counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(points))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return offsets, np.fromiter(itertools.chain.from_iterable(lists), dtype=np.int64, count=int(offsets[-1]))


@numba.njit(cache=True, nogil=True)
def ray_triangle(ox, oy, oz, dx, dy, dz, vertices, a, b, c):
    """(t, u, v): where the ray o + t d meets the triangle of vertices (V, 3) rows a, b, c, at barycentric
    (1 - u - v, u, v); t = -inf where it misses (parallel, or outside the triangle). Moeller-Trumbore."""
    ax, ay, az = vertices[a, 0], vertices[a, 1], vertices[a, 2]
    e1x, e1y, e1z = vertices[b, 0] - ax, vertices[b, 1] - ay, vertices[b, 2] - az
    e2x, e2y, e2z = vertices[c, 0] - ax, vertices[c, 1] - ay, vertices[c, 2] - az
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if abs(det) < 1e-20:
        return -np.inf, 0.0, 0.0
    inverse = 1.0 / det
    tx, ty, tz = ox - ax, oy - ay, oz - az
    u = (tx * px + ty * py + tz * pz) * inverse
    if u < 0.0 or u > 1.0:
        return -np.inf, 0.0, 0.0
    qx, qy, qz = ty * e1z - tz * e1y, tz * e1x - tx * e1z, tx * e1y - ty * e1x
    v = (dx * qx + dy * qy + dz * qz) * inverse
    if v < 0.0 or u + v > 1.0:
        return -np.inf, 0.0, 0.0
    return (e2x * qx + e2y * qy + e2z * qz) * inverse, u, v


@numba.njit(cache=True, nogil=True)
def _rays_hit(points, directions, vertices, faces, normals, offsets, candidates, near, far, edges, edge_band, out):
    """out (P,) bool: the ray from each point (P, 3) along its unit direction (P, 3) meets, between `near` and
    `far` along it, one of its candidate triangles (CSR offsets/candidates) that faces the same way (normals
    (G, 3)) at a point at least edge_band inside the open edges (edges (V,): boundary_distance, interpolated)."""
    for p in range(points.shape[0]):
        dx, dy, dz = directions[p, 0], directions[p, 1], directions[p, 2]
        out[p] = False
        for i in range(offsets[p], offsets[p + 1]):
            f = candidates[i]
            if normals[f, 0] * dx + normals[f, 1] * dy + normals[f, 2] * dz <= 0.0:
                continue
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            t, u, v = ray_triangle(points[p, 0], points[p, 1], points[p, 2], dx, dy, dz, vertices, a, b, c)
            if t < near or t > far:
                continue
            if (1.0 - u - v) * edges[a] + u * edges[b] + v * edges[c] >= edge_band:
                out[p] = True
                break


def _closest_facing(points, vertices, faces, reach, directions=None, normals=None):
    """(closest (P, 3), barycentric (P, 3), distance (P,), face ids (P,)) of points (P, 3) on the triangles (G, 3)
    whose centre lies within `reach` (a scalar, or (P,): e.g. each point's distance to the nearest vertex, which
    bounds its distance to the surface) plus the largest triangle's radius: exact for points within `reach` of the
    surface. With directions (P, 3) and face normals (G, 3), only triangles facing each point's direction count.
    Distance inf and face -1 where no triangle qualifies."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    offsets, candidates = _triangles_near(points, vertices, faces, reach)
    closest = np.full((len(points), 3), np.nan)
    barycentric = np.zeros((len(points), 3))
    distance = np.full(len(points), np.inf)
    face_ids = np.full(len(points), -1, dtype=np.int64)
    no_rows = np.zeros((0, 3))
    _closest_on_triangles(points, vertices, faces, offsets, candidates,
                          no_rows if directions is None else np.ascontiguousarray(directions, dtype=np.float64),
                          no_rows if normals is None else np.ascontiguousarray(normals, dtype=np.float64),
                          closest, barycentric, distance, face_ids)
    return closest, barycentric, distance, face_ids


def _closest(points, vertices, faces, max_gap, edges=None):
    """Closest points of the surface (V, 3), (G, 3) to the points (P, 3) within about max_gap: (candidate ids (C,),
    closest (C, 3), distance (C,), face ids (C,), geodesic distance of the closest point to the open edges (C,)).
    edges: boundary_distance of the surface, if known."""
    near = cKDTree(vertices).query(points, distance_upper_bound=max_gap + 0.05)[0]
    candidates = np.flatnonzero(np.isfinite(near))
    if len(candidates) == 0:
        return candidates, np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0)
    closest, barycentric, distance, face_ids = _closest_facing(points[candidates], vertices, faces, near[candidates])
    edges = boundary_distance(vertices, faces) if edges is None else edges
    edge_distance = (edges[faces[face_ids]] * barycentric).sum(axis=1)
    return candidates, closest, distance, face_ids, edge_distance


def cover_depth(body_vertices, body_faces, garment_vertices, garment_faces, max_gap: float = MAX_GAP) -> np.ndarray:
    """(N,) how far inside a garment's footprint each body vertex (N, 3) of the surface body_faces (F, 3) lies: the
    geodesic distance from the garment's open edges to the vertex's closest garment point (interpolated from the
    vertices of its triangle), where that point is within max_gap and outside the skin (along the body normal);
    -1 where the garment (V, 3), (G, 3) does not cover the vertex."""
    body_vertices = np.asarray(body_vertices, dtype=np.float64)
    out = np.full(len(body_vertices), -1.0)
    used = np.unique(body_faces)
    ids, closest, distance, _, edge_distance = _closest(
        body_vertices[used], np.asarray(garment_vertices, dtype=np.float64), garment_faces, max_gap)
    ids = used[ids]
    normals = vertex_normals(body_vertices, body_faces)[ids]
    in_front = ((closest - body_vertices[ids]) * normals).sum(axis=1) >= -1e-4
    out[ids] = np.where((distance <= max_gap) & in_front, edge_distance, -1.0)
    return out


def covered_vertices(body_vertices, body_faces, garment_vertices, garment_faces, margin: float = MARGIN,
                     max_gap: float = MAX_GAP) -> np.ndarray:
    """(N,) bool: body vertices (N, 3) of the surface body_faces (F, 3) that garment (V, 3), (G, 3) covers with
    at least `margin` of cloth to its open edges (see cover_depth)."""
    return cover_depth(body_vertices, body_faces, garment_vertices, garment_faces, max_gap) >= margin


def tuck_depth(depth: np.ndarray, margin: float = MARGIN, tuck: float = TUCK) -> np.ndarray:
    """(N,) how far to sink each body vertex under the cloth, from cover_depth (N,): 0 outside the garment and at
    its edges, rising linearly to `tuck` at `margin` inside them (where the faces are hidden anyway). The band of
    body faces kept under a hem then sits below the cloth instead of cutting through its flat triangles."""
    return np.where(depth < 0, 0.0, tuck * np.clip(depth / max(margin, 1e-9), 0.0, 1.0))


def sloped(sink: np.ndarray, vertices: np.ndarray, faces: np.ndarray, slope: float = TUCK / MARGIN) -> np.ndarray:
    """(N,) the largest field under sink (N,) that changes by at most `slope` per metre along the edges of the
    surface (N, 3), (F, 3): min over u of sink[u] + slope * geodesic(u, v), by one Dijkstra run from a virtual
    source joined to each vertex u at sink[u] / slope. A sunk vertex next to one left in place would cut a crease
    into the drawn skin (where the closest cloth of two neighbours lies on opposite sides of a collar); the
    default slope is tuck_depth's own, so a hem's band keeps its ramp."""
    n = len(vertices)
    edges, length = _edge_lengths(vertices, faces)
    rows = np.concatenate([edges[:, 0], edges[:, 1], np.full(n, n)])
    cols = np.concatenate([edges[:, 1], edges[:, 0], np.arange(n)])
    weights = np.concatenate([length, length, np.maximum(sink, 0.0) / slope + 1e-12])  # 0 would drop the edge
    graph = coo_matrix((weights, (rows, cols)), shape=(n + 1, n + 1)).tocsr()
    reach = dijkstra(graph, directed=True, indices=n)[:n]
    return np.minimum(sink, np.where(np.isfinite(reach), slope * reach, sink))


def faces_with_vertices(faces: np.ndarray, hidden: np.ndarray, every: bool = True) -> np.ndarray:
    """(F,) bool: triangles (F, 3) whose corners are all (every) or any (not every) in the vertex mask (N,)."""
    corner = hidden[faces]
    return corner.all(axis=1) if every else corner.any(axis=1)


def covered_faces(body_vertices, body_faces, garment_vertices, garment_faces, margin: float = MARGIN,
                  max_gap: float = MAX_GAP) -> np.ndarray:
    """(F,) bool: the body triangles (F, 3) a garment covers (see covered_vertices)."""
    hidden = covered_vertices(body_vertices, body_faces, garment_vertices, garment_faces, margin, max_gap)
    return faces_with_vertices(body_faces, hidden)


def garment_covered_faces(garment, body, shape=None, margin: float = MARGIN, max_gap: float = MAX_GAP,
                          rest=None) -> np.ndarray:
    """(F,) bool over `body.body_faces` (hm08 triangles): what `garment` (a Garment, or anything with `faces`)
    covers on `shape` (default: the reference shape) at rest.

    rest: the garment's rest vertices (V, 3) on that shape if known (a database's drape at beta0); else the
    garment's binding fits it. A MakeHuman garment with `delete_verts` hides the faces touching those vertices,
    as MakeHuman does."""
    from ..body import REFERENCE_SHAPE

    deleted = getattr(getattr(garment, "binding", None), "delete_verts", np.zeros(0, dtype=np.int64))
    if len(deleted):
        mask = np.zeros(len(body.assets.template), dtype=bool)
        mask[deleted] = True
        return faces_with_vertices(body.body_faces, mask, every=False)
    shape = shape if shape is not None else body.shape(REFERENCE_SHAPE)
    rest = garment.rest_vertices(body, shape) if rest is None else rest
    return covered_faces(shape.vertices, body.body_faces, rest, garment.faces, margin, max_gap)


def surface_side(points, vertices, faces, max_gap: float = MAX_GAP, edge_band: float = MARGIN,
                 directions=None, edges=None, return_closest: bool = False):
    """(P,) int8 side of each point (P, 3) relative to an open surface (V, 3), (G, 3) whose normals face outwards:
    +1 outside, -1 inside, 0 where the surface does not cover the point - its closest surface point is further than
    max_gap, or within edge_band (geodesically) of an open edge: the band kept drawn under hems and cuffs.

    directions (P, 3): the points' own outward normals (skin, an outer garment). Then a point is judged against the
    closest part of the surface facing its way (positive dot product of the normals): the surface that lies over
    it, not a panel it meets face to face (the inner arm against a shirt's side in the armpit lies outside the side
    panel and inside its sleeve). edges (V,): the surface's boundary_distance, if known (it changes little with
    the pose). With return_closest: (sides, closest (P, 3): the surface point each was judged against, NaN where
    none)."""
    points = np.asarray(points, dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    edges = boundary_distance(vertices, faces) if edges is None else edges
    out = np.zeros(len(points), dtype=np.int8)
    ids, closest, distance, face_ids, edge_distance = _closest(points, vertices, faces, max_gap, edges)
    normals = face_normals(vertices, faces)  # not unit: only their signs against other vectors are read
    if directions is not None and len(ids):
        own = np.asarray(directions, dtype=np.float64)[ids]
        facing = np.flatnonzero((normals[face_ids] * own).sum(axis=1) <= 0)
        if len(facing):  # judged again against the closest triangle facing the point's way
            near, barycentric, far, faced = _closest_facing(points[ids[facing]], vertices, faces, max_gap,
                                                            own[facing], normals)
            found = faced >= 0
            distance[facing] = far
            closest[facing[found]], face_ids[facing[found]] = near[found], faced[found]
            edge_distance[facing[found]] = (edges[faces[faced[found]]] * barycentric[found]).sum(axis=1)
    side = np.where(((points[ids] - closest) * normals[face_ids]).sum(axis=1) > 0, 1, -1)
    out[ids] = np.where((distance <= max_gap) & (edge_distance >= edge_band), side, 0)
    if return_closest:
        judged = np.full((len(points), 3), np.nan)
        judged[ids] = closest
        return out, judged
    return out


def cloth_over(points, directions, vertices, faces, max_gap: float = MAX_GAP, edge_band: float = MARGIN,
               edges=None, below: float = BELOW) -> np.ndarray:
    """(P,) bool: cloth (V, 3), (G, 3) lies over each point (P, 3) - the line from the point along its outward
    direction (P, 3), where a viewer outside looks at it, meets cloth facing the same way within max_gap in front of
    it (or up to `below` behind it: skin poking through its cloth), at least edge_band inside the cloth's open edges.
    The closest facing cloth is not enough: the chest panel 4 cm below the throat is within max_gap of the neck's
    skin but shows it."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    unit = np.asarray(directions, dtype=np.float64)
    unit = np.ascontiguousarray(unit / np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-20))
    edges = boundary_distance(vertices, faces) if edges is None else np.asarray(edges, dtype=np.float64)
    normals = face_normals(vertices, faces)
    offsets, candidates = _triangles_near(points, vertices, faces, max(max_gap, below))
    out = np.zeros(len(points), dtype=np.bool_)
    _rays_hit(points, unit, vertices, faces, normals, offsets, candidates, -below, max_gap, edges, edge_band, out)
    return out


def poke_through(body_vertices, body_faces, garment_vertices, garment_faces, max_gap: float = MAX_GAP,
                 edge_band: float = MARGIN, owner_tolerance: float = OWNER_TOLERANCE,
                 vertex_parts: np.ndarray | None = None) -> np.ndarray:
    """(F,) bool: body triangles (F, 3) whose centre lies outside the garment's surface where the garment covers it
    (surface_side, judged against the cloth facing the skin's way). The check behind "no skin through the cloth",
    on posed meshes of any frame.

    The cloth a face is judged against must lie on that face's part of the body: where another part of the body
    (body_vertices (N, 3), all of them) is closer to that cloth point than the face's centre is, by more than
    owner_tolerance, the face is skin outside the garment, not skin through it - an arm hanging beside the torso,
    below a short sleeve and 5 cm outside the shirt's side panel, which faces the same way. With vertex_parts (N,)
    (each body vertex's part: body_part_labels), any vertex of another part than the face's closer to the cloth
    point than the face is settles it: a panel floating in the armpit, 5 cm from both arm and torso, is the torso's
    when the torso is nearer, by however little."""
    body_vertices = np.asarray(body_vertices, dtype=np.float64)
    centres = body_vertices[body_faces].mean(axis=1)
    directions = face_normals(body_vertices, body_faces)
    sides, closest = surface_side(centres, garment_vertices, garment_faces, max_gap, edge_band, directions,
                                  return_closest=True)
    poking = sides > 0
    ids = np.flatnonzero(poking)
    if len(ids):
        to_face = np.linalg.norm(closest[ids] - centres[ids], axis=1)
        to_body, _ = cKDTree(body_vertices).query(closest[ids])
        outside = to_body < to_face - owner_tolerance
        if vertex_parts is not None:
            vertex_parts = np.asarray(vertex_parts)
            face_parts = np.array([np.bincount(row).argmax() for row in vertex_parts[body_faces[ids]]])
            for part in np.unique(face_parts):
                rows = np.flatnonzero(face_parts == part)
                others = np.flatnonzero(vertex_parts != part)
                if len(others):
                    to_other, _ = cKDTree(body_vertices[others]).query(closest[ids[rows]])
                    outside[rows] |= to_other < to_face[rows]
        poking[ids[outside]] = False
    return poking


def body_part_labels(body, vertex_ids=None) -> np.ndarray:
    """(N,) int: each body vertex's part - the skinning region (garment.binding.REGIONS: torso, upper arms,
    forearms, legs) that carries most of its skin weight; vertex_ids: hm08 ids of the vertices wanted (all)."""
    from .binding import region_weights

    ids = np.arange(len(body.skin_indices)) if vertex_ids is None else np.asarray(vertex_ids)
    return region_weights(body.skin_indices[ids], body.skin_weights[ids], body.bone_names).argmax(axis=1)
