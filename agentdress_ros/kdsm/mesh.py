"""The kinematically deforming skinned mesh (KDSM, paper Sec. 3): a BCC tet mesh of a thickened level set of the body.

Built once per garment database, at beta0's rest pose: the body's signed distance phi on a BCC lattice, the region
phi <= thickness (the thickened level set, interior included as in the paper, optionally hollowed below
`inner_depth`), cropped to within `reach` of the rest garment so that a T-shirt's KDSM does not mesh the legs and
head; the lattice tets with a node in the region form the mesh, and each tet vertex takes the skin weights of its
closest body surface point (max 4 influences, like the body). Posing is plain linear blend skinning of the vertices.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from ..body.kinematics import linear_blend_skinning
from .lattice import TETS_PER_CUBE, lattice_tet_nodes, node_positions, signed_volumes
from .levelset import sample_surface, signed_distance_grid


@dataclass(frozen=True)
class KDSMSettings:
    spacing: float = 0.025  # m: lattice step h (BCC tets have edges h and h sqrt(3) / 2)
    thickness: float = 0.21  # m: the level set is thickened this far outside the body (see drape_clearance)
    reach: float | None = 0.21  # m: keep only tets within this distance of the crop points (None: no crop)
    inner_depth: float | None = None  # m: drop tets deeper than this inside the body (None: keep the interior)
    sample_level: int = 3  # barycentric samples per body triangle edge for the distance and weights
    # Jacobi iterations of weight diffusion over the tet edges for the vertices farther than one lattice step from
    # the body (0: every vertex keeps its closest body point's weights, which jump where the closest point changes
    # limb, as in the gap between arm and torso)
    smoothing: int = 0


@dataclass(frozen=True)
class KDSM:
    """A skinned tet mesh on a BCC lattice. N vertices, T tets, box of dims = (nx, ny, nz) cubes from origin."""

    origin: np.ndarray  # (3,) float64
    spacing: float
    dims: np.ndarray  # (3,) int64
    vertices: np.ndarray  # (N, 3) float64 rest (material space) positions
    tets: np.ndarray  # (T, 4) int32, positively oriented at rest
    class_inverse: np.ndarray  # (12, 3, 3) inverse of [v1 - v0, v2 - v0, v3 - v0] (edge columns) of the rest tets
    # of each lattice class (lattice tet id % 12): tets of a class are translates of each other, so 12 matrices
    # serve the whole mesh (a per-tet table would cost 72 bytes a tet and a cache miss a point per frame)
    lattice_tets: np.ndarray  # (nx ny nz 12,) int32 mesh tet of each lattice tet, -1 where not meshed
    skin_indices: np.ndarray  # (N, 4) int32
    skin_weights: np.ndarray  # (N, 4) float64, rows sum to 1
    body_distance: np.ndarray  # (N,) signed distance of each vertex to the rest body (negative inside)
    settings: KDSMSettings
    info: dict = field(default_factory=dict)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def posed_vertices(self, transforms: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) vertices skinned with bone transforms (B, 3, 4)."""
        out = np.empty_like(self.vertices) if out is None else out
        return linear_blend_skinning(self.vertices, self.skin_indices, self.skin_weights,
                                     np.ascontiguousarray(transforms, dtype=np.float64), out)

    def rest_volumes(self) -> np.ndarray:
        """(T,) signed rest volumes (all h^3 / 12 > 0 by construction)."""
        return signed_volumes(self.vertices, self.tets)


def _boxes(body_points, crop_points, settings: KDSMSettings):
    """The lattice box of the thickened body (origin (3,), dims (3,) cubes) and the sub-box of cubes [low, high) cut
    to the crop's bounds. The level set's sign needs the whole body box: a crop box cuts through the body."""
    h = settings.spacing
    pad = settings.thickness + 2.0 * h
    origin = body_points.min(axis=0) - pad
    dims = np.ceil((body_points.max(axis=0) + pad - origin) / h).astype(np.int64) + 1
    low, high = np.zeros(3, dtype=np.int64), dims.copy()
    if crop_points is not None and settings.reach is not None:
        pad = settings.reach + 2.0 * h
        low = np.clip(np.floor((crop_points.min(axis=0) - pad - origin) / h).astype(np.int64), 0, dims)
        high = np.clip(np.ceil((crop_points.max(axis=0) + pad - origin) / h).astype(np.int64), low, dims)
    return origin, dims, low, high


def build_kdsm(body, shape, settings: KDSMSettings = KDSMSettings(), crop_points=None) -> KDSM:
    """The KDSM of the body `shape` (a BodyShape, usually beta0's) of `body` (AnnyBody), see the module docstring.

    crop_points (M, 3), e.g. the rest garment: with settings.reach, only tets within reach of them are kept.
    A point whose body distance is at most `thickness` (and within `reach` of the crop) lies in a meshed tet: a
    node is in the region with a slack of one lattice step, the longest edge of a BCC tet.
    """
    started = time.perf_counter()
    h = float(settings.spacing)
    vertices_all = np.asarray(shape.vertices, dtype=np.float64)
    body_points = vertices_all[body.body_vertex_ids]
    crop = None if crop_points is None else np.asarray(crop_points, dtype=np.float64)
    samples = sample_surface(vertices_all, body.body_faces, body.skin_indices, body.skin_weights, body.n_bones,
                             settings.sample_level)
    full_origin, full_dims, low, high = _boxes(body_points, crop, settings)
    full_nodes = node_positions(full_origin, h, full_dims)
    n_corner = int(np.prod(full_dims + 1))
    # every vertex of a kept tet is within thickness + 2h of the body: farther distances are never needed
    bound = settings.thickness + 3.0 * h
    corner_phi, corner_nearest = signed_distance_grid(full_nodes[:n_corner].reshape(*(full_dims + 1), 3), samples, h,
                                                      bound)
    centre_phi, centre_nearest = signed_distance_grid(full_nodes[n_corner:].reshape(*full_dims, 3), samples, h, bound)
    corners, centres = tuple(slice(a, b + 1) for a, b in zip(low, high)), tuple(slice(a, b) for a, b in zip(low, high))
    phi = np.concatenate([corner_phi[corners].ravel(), centre_phi[centres].ravel()])
    nearest = np.concatenate([corner_nearest[corners].ravel(), centre_nearest[centres].ravel()])
    origin, dims = full_origin + h * low, high - low
    nodes = node_positions(origin, h, dims)

    inside_region = phi <= settings.thickness + h
    if settings.inner_depth is not None:
        inside_region &= phi >= -(settings.inner_depth + h)
    if crop is not None and settings.reach is not None:
        crop_distance, _ = cKDTree(crop).query(nodes, k=1, distance_upper_bound=settings.reach + h + 1e-9)
        inside_region &= np.isfinite(crop_distance)

    lattice_ids, lattice_nodes = lattice_tet_nodes(dims)
    keep = inside_region[lattice_nodes].any(axis=1)
    lattice_ids, lattice_nodes = lattice_ids[keep], lattice_nodes[keep]
    negative = signed_volumes(nodes, lattice_nodes) < 0
    lattice_nodes[negative] = lattice_nodes[negative][:, [0, 1, 3, 2]]  # one swap flips the orientation

    used, tets = np.unique(lattice_nodes, return_inverse=True)
    tets = tets.reshape(-1, 4).astype(np.int32)
    vertices = nodes[used]
    lattice_tets = np.full(int(np.prod(dims)) * TETS_PER_CUBE, -1, dtype=np.int32)
    lattice_tets[lattice_ids] = np.arange(len(tets), dtype=np.int32)
    class_inverse = np.full((TETS_PER_CUBE, 3, 3), np.nan)
    classes = lattice_ids % TETS_PER_CUBE
    for c in np.unique(classes):
        corners = vertices[tets[np.flatnonzero(classes == c)[0]]]
        class_inverse[c] = np.linalg.inv((corners[1:] - corners[0]).T)
    volumes = signed_volumes(vertices, tets)
    skin_indices, skin_weights = samples.skin_indices[nearest[used]], samples.skin_weights[nearest[used]]
    if settings.smoothing > 0:
        skin_indices, skin_weights = diffused_weights(tets, skin_indices, skin_weights, phi[used] > h,
                                                      settings.smoothing)
    kdsm = KDSM(origin=origin, spacing=h, dims=dims, vertices=vertices, tets=tets, class_inverse=class_inverse,
                lattice_tets=lattice_tets, skin_indices=np.ascontiguousarray(skin_indices, dtype=np.int32),
                skin_weights=np.ascontiguousarray(skin_weights, dtype=np.float64), body_distance=phi[used],
                settings=settings)
    kdsm.info.update({"tets": int(len(tets)), "vertices": int(len(vertices)), "dims": dims.tolist(),
                      "min_rest_volume": float(volumes.min()), "build_seconds": time.perf_counter() - started,
                      "settings": asdict(settings)})
    return spatially_ordered(kdsm)


def diffused_weights(tets, skin_indices, skin_weights, free, iterations: int, influences: int = 4) -> tuple:
    """Skin weights (N, K) diffused over the edges of tets (T, 4): `iterations` Jacobi steps in which every `free`
    vertex (N,) bool takes the mean of its neighbours' weights while the others keep theirs; then each vertex keeps
    its `influences` largest weights, renormalised. Returns (indices (N, influences) int32, weights float64)."""
    from scipy import sparse

    n, k = skin_indices.shape
    bones = int(skin_indices.max()) + 1
    dense = sparse.csr_matrix((skin_weights.ravel(), (np.repeat(np.arange(n), k), skin_indices.ravel())),
                              shape=(n, bones)).toarray()
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    adjacency = sparse.coo_matrix((np.ones(2 * len(pairs)), (np.r_[pairs[:, 0], pairs[:, 1]],
                                                             np.r_[pairs[:, 1], pairs[:, 0]])), shape=(n, n)).tocsr()
    mean = sparse.diags(1.0 / np.maximum(np.asarray(adjacency.sum(axis=1)).ravel(), 1.0)) @ adjacency
    free = np.asarray(free, dtype=bool)
    for _ in range(iterations):
        dense[free] = (mean @ dense)[free]
    top = np.argsort(-dense, axis=1)[:, :influences]
    weights = np.take_along_axis(dense, top, axis=1)
    weights /= weights.sum(axis=1, keepdims=True)
    return top.astype(np.int32), weights


def _spread_bits(values: np.ndarray) -> np.ndarray:
    """Each of the low 21 bits of values (int64) moved to every third bit: one axis of a 3D Morton code."""
    v = values.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def spatially_ordered(kdsm: KDSM) -> KDSM:
    """The same KDSM with its vertices in Morton (Z-curve) order of their lattice positions, tets renumbered.

    The run-time kernel reads the four vertices of one tet per garment vertex; in the lattice's row-major order
    those sit in rows far apart (the centres after all the corners), a cache miss each. In Z order the vertices of
    a cube and of its neighbours share cache lines. Tets keep their numbers (lattice_tets stays valid); a KDSM
    already in this order is returned as is.
    """
    half_steps = np.rint((kdsm.vertices - kdsm.origin) / (0.5 * kdsm.spacing)).astype(np.int64)  # corners even
    code = (_spread_bits(half_steps[:, 0]) << np.uint64(2)) | (_spread_bits(half_steps[:, 1]) << np.uint64(1)) \
        | _spread_bits(half_steps[:, 2])
    order = np.argsort(code, kind="stable")
    if np.array_equal(order, np.arange(len(order))):
        return kdsm
    renumber = np.empty_like(order)
    renumber[order] = np.arange(len(order))
    return replace(kdsm, vertices=np.ascontiguousarray(kdsm.vertices[order]),
                   tets=np.ascontiguousarray(renumber[kdsm.tets].astype(np.int32)),
                   skin_indices=np.ascontiguousarray(kdsm.skin_indices[order]),
                   skin_weights=np.ascontiguousarray(kdsm.skin_weights[order]),
                   body_distance=np.ascontiguousarray(kdsm.body_distance[order]))


_ARRAYS = ("origin", "dims", "vertices", "tets", "class_inverse", "lattice_tets", "skin_indices", "skin_weights",
           "body_distance")


def save_kdsm(path, kdsm: KDSM) -> None:
    """Write `kdsm` to an .npz file (its arrays, settings and build report)."""
    import json

    np.savez_compressed(path, spacing=np.float64(kdsm.spacing), settings=json.dumps(asdict(kdsm.settings)),
                        info=json.dumps(kdsm.info), **{name: getattr(kdsm, name) for name in _ARRAYS})


def load_kdsm(path) -> KDSM:
    """A KDSM written by save_kdsm."""
    import json

    with np.load(path) as data:
        arrays = {name: data[name] for name in _ARRAYS}
        settings = KDSMSettings(**json.loads(str(data["settings"])))
        return KDSM(spacing=float(data["spacing"]), settings=settings, info=json.loads(str(data["info"])), **arrays)
