"""The body-centred-cubic (BCC) tetrahedral lattice of the KDSM (Molino et al. 2003: the red level of red/green).

The lattice covers a box of `dims` = (nx, ny, nz) cubes of edge `spacing` from `origin`. Its nodes are the cube
corners and the cube centres. Every BCC tetrahedron joins the centres of two face-adjacent cubes (an edge of length
h along an axis) with one edge of their shared square face (length h), so each tet is identified by the upper cube
of its face pair, the face's axis a and the face edge e (4 per face): 12 lattice tets per cube, all congruent
(volume h^3 / 12).

Because the material space (the rest pose) is this regular lattice, the tet holding a point is found in O(1) with
no search structure: the cube's centre splits the cube into six pyramids (one per face, the dominant axis of the
offset from the centre); the pyramid's four quarters (split through the face diagonals) are the halves of the four
tets of that face. `locate_lattice_tets` is that rule, shared by the build, the embedding and the per-frame kernel.

Node ids: corner (i, j, k) -> (i (ny+1) + j) (nz+1) + k, centre (i, j, k) -> n_corners + (i ny + j) nz + k.
Lattice tet id: ((i ny + j) nz + k) 12 + 4 a + e for its upper cube (i, j, k) (index >= 1 along a).
"""
from __future__ import annotations

import numba
import numpy as np

TETS_PER_CUBE = 12


def n_corners(dims) -> int:
    nx, ny, nz = (int(d) for d in dims)
    return (nx + 1) * (ny + 1) * (nz + 1)


def n_nodes(dims) -> int:
    nx, ny, nz = (int(d) for d in dims)
    return n_corners(dims) + nx * ny * nz


def node_positions(origin, spacing: float, dims) -> np.ndarray:
    """(n_nodes, 3) positions of every corner, then every centre, in node-id order."""
    nx, ny, nz = (int(d) for d in dims)
    corners = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"),
                       axis=-1).reshape(-1, 3).astype(np.float64)
    centres = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"),
                       axis=-1).reshape(-1, 3).astype(np.float64) + 0.5
    return np.asarray(origin, dtype=np.float64) + spacing * np.concatenate([corners, centres])


def _other_axes(a: int) -> tuple[int, int]:
    return {0: (1, 2), 1: (0, 2), 2: (0, 1)}[a]


def lattice_tet_nodes(dims) -> tuple[np.ndarray, np.ndarray]:
    """Every lattice tet of the box: (ids (L,) lattice tet ids, nodes (L, 4) node ids [c_lower, c_upper, k1, k2]).

    Only face pairs with both cubes inside the box exist (tets of the box's outer faces would be half tets).
    """
    nx, ny, nz = (int(d) for d in dims)
    i, j, k = (g.reshape(-1) for g in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    cube = np.stack([i, j, k], axis=1)
    corner_base = n_corners(dims)
    corner = lambda c: (c[:, 0] * (ny + 1) + c[:, 1]) * (nz + 1) + c[:, 2]  # noqa: E731
    centre = lambda c: corner_base + (c[:, 0] * ny + c[:, 1]) * nz + c[:, 2]  # noqa: E731
    ids, nodes = [], []
    for a in range(3):
        upper = cube[cube[:, a] >= 1]
        lower = upper.copy()
        lower[:, a] -= 1
        cube_id = (upper[:, 0] * ny + upper[:, 1]) * nz + upper[:, 2]
        b1, b2 = _other_axes(a)
        for e in range(4):
            fixed, free = (b1, b2) if e < 2 else (b2, b1)
            k1 = upper.copy()  # the face's corners: coordinate a of the upper cube's lower face
            k1[:, fixed] += 1 if e % 2 == 0 else 0
            k2 = k1.copy()
            k2[:, free] += 1
            ids.append(cube_id * TETS_PER_CUBE + 4 * a + e)
            nodes.append(np.stack([centre(lower), centre(upper), corner(k1), corner(k2)], axis=1))
    return np.concatenate(ids).astype(np.int64), np.concatenate(nodes).astype(np.int64)


@numba.njit(cache=True, nogil=True)
def locate_lattice_tet(x, y, z, origin, spacing, dims):
    """Lattice tet id holding the point (x, y, z), or -1 outside the box's complete tets (see module docstring)."""
    q0 = (x - origin[0]) / spacing
    q1 = (y - origin[1]) / spacing
    q2 = (z - origin[2]) / spacing
    # compared as floats before any integer conversion: NaN and huge values are rejected, never converted
    if not (0.0 <= q0 < dims[0] and 0.0 <= q1 < dims[1] and 0.0 <= q2 < dims[2]):
        return -1
    c0 = min(int(q0), dims[0] - 1)
    c1 = min(int(q1), dims[1] - 1)
    c2 = min(int(q2), dims[2] - 1)
    r0 = q0 - c0 - 0.5
    r1 = q1 - c1 - 0.5
    r2 = q2 - c2 - 0.5
    a0, a1, a2 = abs(r0), abs(r1), abs(r2)
    # the dominant axis picks the cube face (pyramid); ties go to the lowest axis, consistently everywhere
    if a0 >= a1 and a0 >= a2:
        axis = 0
        ra, u, v = r0, r1, r2
    elif a1 >= a2:
        axis = 1
        ra, u, v = r1, r0, r2
    else:
        axis = 2
        ra, u, v = r2, r0, r1
    if ra >= 0.0:
        if axis == 0:
            c0 += 1
        elif axis == 1:
            c1 += 1
        else:
            c2 += 1
    cu = c0 if axis == 0 else (c1 if axis == 1 else c2)
    if cu < 1 or cu >= dims[axis]:
        return -1
    if abs(u) >= abs(v):
        edge = 0 if u >= 0.0 else 1
    else:
        edge = 2 if v >= 0.0 else 3
    return ((c0 * dims[1] + c1) * dims[2] + c2) * 12 + 4 * axis + edge


@numba.njit(cache=True, nogil=True)
def locate_lattice_tets(points, origin, spacing, dims, out):
    """out (P,) int64 = lattice tet id of each point (P, 3), -1 outside the box."""
    for p in range(points.shape[0]):
        out[p] = locate_lattice_tet(points[p, 0], points[p, 1], points[p, 2], origin, spacing, dims)
    return out


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T,) signed volumes det[v1-v0, v2-v0, v3-v0] / 6 of tets (T, 4) over vertices (N, 3)."""
    corners = vertices[tets]
    edges = corners[:, 1:] - corners[:, :1]
    return np.einsum("ti,ti->t", edges[:, 0], np.cross(edges[:, 1], edges[:, 2])) / 6.0
