"""A garment: topology, how it follows the body shape, its skin weights and bone regions."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..body import AnnyBody, BodyShape, quads_to_triangles
from .binding import SurfaceBinding, evaluate_surface_binding, vertex_normals


@dataclass(frozen=True)
class Garment:
    """V vertices, F triangles, B bones, 7 regions.

    `binding` places the garment on any body shape: a SurfaceBinding on the hm08 surface group `surface`
    (the project's own garments) or an MhcloBinding (MakeHuman clothes).
    """

    name: str
    faces: np.ndarray  # (F, 3) int32
    binding: object  # SurfaceBinding | MhcloBinding
    surface: str  # hm08 face group whose normals a SurfaceBinding offsets along
    skin_indices: np.ndarray  # (V, 4) int32
    skin_weights: np.ndarray  # (V, 4) float64, rows sum to 1
    regions: np.ndarray  # (V, 7) region weights w_{g,y}
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (P,) held by a drape

    @property
    def n_vertices(self) -> int:
        return len(self.skin_indices)

    def rest_vertices(self, body: AnnyBody, shape: BodyShape) -> np.ndarray:
        """The garment (V, 3) fitted to the rest pose of `shape`."""
        if isinstance(self.binding, SurfaceBinding):
            faces = quads_to_triangles(body.assets.group_faces[self.surface])
            return evaluate_surface_binding(self.binding, shape.vertices, vertex_normals(shape.vertices, faces))
        return self.binding.evaluate(shape.vertices)
