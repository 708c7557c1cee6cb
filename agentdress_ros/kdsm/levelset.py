"""A signed distance (level set) of the rest body on the lattice nodes, and body-surface skin weights in space.

The body surface is sampled densely (a barycentric grid on every triangle); a KD-tree of the samples gives, for any
point, the distance to the surface (to within the sample gap, a few millimetres, enough for a boundary that only
marks where the parameterization ends), the closest surface point's interpolated normal and skin weights. The sign
comes from a flood fill: lattice nodes farther than half a lattice step from the surface and connected to the box's
border are outside (a 6-connected path cannot cross the closed surface without passing a node within h/2 of it),
the other far nodes are inside; nodes near the surface take the sign of the closest sample's normal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..garment.binding import interpolate_skin_weights, vertex_normals


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on a triangle mesh with what they inherit from its vertices. S samples."""

    points: np.ndarray  # (S, 3)
    normals: np.ndarray  # (S, 3) unit interpolated vertex normals
    skin_indices: np.ndarray  # (S, 4) int32 interpolated skin weights (max 4 influences)
    skin_weights: np.ndarray  # (S, 4) float64
    tree: cKDTree

    def query(self, points: np.ndarray, bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """(distance (P,), nearest sample (P,)) of points (P, 3); points farther than `bound` get inf and S (the
        KD-tree answers far points slowly, and only a band around the body is needed)."""
        distance, nearest = self.tree.query(np.asarray(points, dtype=np.float64), k=1, distance_upper_bound=bound)
        return distance, nearest


def barycentric_grid(level: int) -> np.ndarray:
    """(n, 3) barycentric coordinates (i, j, k) / level with i + j + k = level (the triangle's corners included)."""
    rows = [(i, j, level - i - j) for i in range(level + 1) for j in range(level + 1 - i)]
    return np.asarray(rows, dtype=np.float64) / level


def sample_surface(vertices, faces, skin_indices, skin_weights, n_bones: int, level: int = 3) -> SurfaceSamples:
    """Samples of the mesh vertices (N, 3), faces (F, 3) on a barycentric grid of `level` per triangle, with their
    interpolated normals and skin weights (skin_indices/skin_weights (N, K) of the mesh vertices)."""
    faces = np.asarray(faces)
    grid = barycentric_grid(level)
    triangles = np.repeat(faces, len(grid), axis=0)
    barycentric = np.tile(grid, (len(faces), 1))
    points = np.einsum("sk,skd->sd", barycentric, vertices[triangles])
    normals = np.einsum("sk,skd->sd", barycentric, vertex_normals(vertices, faces)[triangles])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    indices, weights = interpolate_skin_weights(triangles, barycentric, skin_indices, skin_weights, n_bones)
    return SurfaceSamples(points, normals, indices, weights, cKDTree(points))


def outside_far(distance_grid: np.ndarray, threshold: float) -> np.ndarray:
    """Mask of grid nodes (nx, ny, nz) farther than `threshold` from the surface and 6-connected to the border
    through such nodes: certainly outside a closed surface when threshold >= half the node spacing."""
    far = distance_grid > threshold
    labels, _ = ndimage.label(far)
    border = np.concatenate([labels[0].ravel(), labels[-1].ravel(), labels[:, 0].ravel(), labels[:, -1].ravel(),
                             labels[:, :, 0].ravel(), labels[:, :, -1].ravel()])
    outside_labels = np.unique(border[border > 0])
    return np.isin(labels, outside_labels)


def signed_distance_grid(points_grid: np.ndarray, samples: SurfaceSamples, spacing: float, bound: float = np.inf):
    """Signed distance (nx, ny, nz), negative inside, and the nearest sample (nx, ny, nz) of the grid nodes
    points_grid (nx, ny, nz, 3) spaced `spacing` apart. Nodes farther than `bound` (> spacing) from the surface get
    +-inf and nearest sample S."""
    shape = points_grid.shape[:3]
    flat = points_grid.reshape(-1, 3)
    distance, nearest = samples.query(flat, bound)
    distance = distance.reshape(shape)
    threshold = 0.5 * spacing + _sample_gap(samples)
    outside = outside_far(distance, threshold)
    near = distance <= threshold
    close = np.minimum(nearest, len(samples.points) - 1)
    facing = np.einsum("pd,pd->p", flat - samples.points[close], samples.normals[close]).reshape(shape) >= 0
    sign = np.where(near, np.where(facing, 1.0, -1.0), np.where(outside, 1.0, -1.0))
    return sign * distance, nearest.reshape(shape)


def _sample_gap(samples: SurfaceSamples) -> float:
    """A bound on how far the closest surface point can be from its nearest sample: the largest nearest-neighbour
    gap between samples (a few mm on the body)."""
    distance, _ = samples.tree.query(samples.points[:: max(1, len(samples.points) // 20000)], k=2)
    return float(distance[:, 1].max())
