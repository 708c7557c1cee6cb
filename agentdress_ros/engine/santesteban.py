"""The garment model of Santesteban et al. 2019 (their Sec. 3), beside AgentDress synthesis: `model=santesteban`.

    unposed(beta, theta) = T + R_G(beta) + R_L(beta, theta)        (V, 3), the garment in the rest frame of beta
    garment = W(unposed, J(beta), theta, W_g)                       linear blend skinning with beta's skeleton
    post-process (their Sec. 3.1): a vertex closer to the body than eps along the normal of its body vertex is
    pushed out to eps

T is the database's rest garment (beta0), W_g its skinning weights (interpolated from the closest body triangle, as
their Eq. 3 does); R_G and R_L are the two regressors of the database's garment_model/santesteban group (trained
by `agentdress lab santesteban`, offline.santesteban), evaluated with numpy: no learning library at run time. R_G runs
once per shape. The post-process binds each garment vertex to its closest body vertex once per shape (on the
shape's rest pose, as AgentDress Eq. 10 does) instead of searching the posed body every frame.
"""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field, replace

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..body.kinematics import forward_kinematics, linear_blend_skinning, skin_point
from ..garment.binding import vertex_normals
from .database import Codec, Database, Regressor, register_codec, write_regressor
from .kernels import prepare_pose
from .pose_models import RegressorDecoder

__all__ = ["PUSH_MARGIN", "SantestebanModel", "push_out_of_body"]

#: eps of the post-process, metres (AgentDress's penetration_margin, so the two systems are compared alike).
PUSH_MARGIN = 0.005
N_PHENOTYPES = 6


@numba.njit(cache=True, nogil=True)
def push_out_of_body(garment, bound, body_rest, body_normals, skin_indices, skin_weights, transforms, margin):
    """In place: each garment vertex (V, 3) closer than `margin` to its bound body vertex bound (V,) along that
    vertex's normal moves out along the normal to `margin`. body_rest, body_normals (N, 3): the body's rest
    vertices and unit normals; skin_indices/weights (N, K); transforms (B, 3, 4) of the frame. Returns the count."""
    pushed = 0
    for v in range(garment.shape[0]):
        b = bound[v]
        px, py, pz = skin_point(body_rest[b, 0], body_rest[b, 1], body_rest[b, 2], skin_indices, skin_weights, b,
                                transforms)
        # the blended transform's linear part on the normal: the skinned tip of the normal less the skinned point
        tx, ty, tz = skin_point(body_rest[b, 0] + body_normals[b, 0], body_rest[b, 1] + body_normals[b, 1],
                                body_rest[b, 2] + body_normals[b, 2], skin_indices, skin_weights, b, transforms)
        nx, ny, nz = tx - px, ty - py, tz - pz
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length < 1e-12:
            continue
        nx, ny, nz = nx / length, ny / length, nz / length
        depth = (garment[v, 0] - px) * nx + (garment[v, 1] - py) * ny + (garment[v, 2] - pz) * nz
        if depth < margin:
            garment[v, 0] += (margin - depth) * nx
            garment[v, 1] += (margin - depth) * ny
            garment[v, 2] += (margin - depth) * nz
            pushed += 1
    return pushed


class SantestebanModel:
    """Santesteban et al.'s system on a database that holds garment_model/santesteban (see the module docstring),
    under the node's garment-model protocol (models.garment_models): name, faces (F, 3), n_vertices, kind;
    set_shape(beta (6,)) -> clamped; synthesize(rotvecs (B, 3), root (3,)) -> (V, 3) float32 in the database's
    vertex order (an internal buffer); reset() (no frame history); clone() (buffers of its own)."""

    kind = "santesteban"

    def __init__(self, db: Database, body, margin: float = PUSH_MARGIN, name: str | None = None, path=None):
        if db.santesteban is None:
            raise ValueError("model 'santesteban' needs a database with garment_model/santesteban (train it with "
                             "`agentdress lab santesteban`)")
        self.db, self.body, self.margin = db, body, float(margin)
        self.name, self.path = name or db.garment, path
        self.faces = np.ascontiguousarray(db.faces, dtype=np.int32)
        self.fit = RegressorDecoder(db.santesteban.fit)
        self.wrinkles = RegressorDecoder(db.santesteban.wrinkles)
        self.rest = np.asarray(db.rest, dtype=np.float64)
        self.skin_indices = np.ascontiguousarray(db.skin_indices, dtype=np.int32)
        self.skin_weights = np.ascontiguousarray(db.skin_weights, dtype=np.float64)
        self.parents = np.asarray(db.parents, dtype=np.int64)
        self.n_pose = 3 * len(self.parents)
        ids = body.body_vertex_ids
        self._body_ids = ids
        self._body_skin_i = np.ascontiguousarray(body.skin_indices[ids], dtype=np.int32)
        self._body_skin_w = np.ascontiguousarray(body.skin_weights[ids], dtype=np.float64)
        self._allocate()
        self.set_shape(db.beta0)

    def _allocate(self):
        self.inputs = np.zeros(self.n_pose + N_PHENOTYPES)
        self.transforms = np.empty((len(self.parents), 3, 4))
        self.theta = np.empty((len(self.parents), 3))
        self.root = np.empty(3)
        self.unposed = np.empty_like(self.rest)
        self.out = np.empty(self.rest.shape, dtype=np.float64)
        self.out32 = np.empty(self.rest.shape, dtype=np.float32)
        self.pushed = 0

    @property
    def n_vertices(self) -> int:
        return len(self.rest)

    def set_shape(self, beta) -> bool:
        """Fit to a body shape: R_G(beta), beta's skeleton, and the post-process's binding. Phenotypes outside
        [0, 1] are clamped (returns True)."""
        beta = np.asarray(beta, dtype=np.float64).reshape(-1)
        if beta.shape != (N_PHENOTYPES,) or not np.isfinite(beta).all():
            raise ValueError(f"beta must be {N_PHENOTYPES} finite phenotype values, got {beta.tolist()}")
        shape = self.body.shape(beta)
        self.inputs[self.n_pose:] = shape.beta
        self.fitted = self.rest + self.fit.decode(self.inputs).T
        self.heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
        body_rest = shape.vertices[self._body_ids]
        normals = vertex_normals(shape.vertices, self.body.body_faces)[self._body_ids]
        self._body_rest = np.ascontiguousarray(body_rest)
        self._body_normals = np.ascontiguousarray(normals / np.maximum(np.linalg.norm(normals, axis=1,
                                                                                      keepdims=True), 1e-12))
        self._bound = cKDTree(body_rest).query(self.fitted)[1].astype(np.int64)
        return bool(shape.clamped)

    def reset(self) -> None:
        """Nothing to forget: the model has no frame history."""

    def clone(self) -> "SantestebanModel":
        twin = copy.copy(self)
        twin.fit, twin.wrinkles = self.fit.fork(), self.wrinkles.fork()
        twin._allocate()
        twin.inputs[:] = self.inputs
        return twin

    def synthesize(self, rotvecs, root_translation=None) -> np.ndarray:
        root = np.zeros(3) if root_translation is None else np.asarray(root_translation, dtype=np.float64)
        prepare_pose(np.asarray(rotvecs, dtype=np.float64), root, 1.0e4, self.theta, self.root)
        self.inputs[:self.n_pose] = self.theta.reshape(-1)
        np.add(self.fitted, self.wrinkles.decode(self.inputs).T, out=self.unposed)
        forward_kinematics(self.theta, self.root, self.heads, self.parents, self.transforms)
        linear_blend_skinning(self.unposed, self.skin_indices, self.skin_weights, self.transforms, self.out)
        self.pushed = push_out_of_body(self.out, self._bound, self._body_rest, self._body_normals,
                                       self._body_skin_i, self._body_skin_w, self.transforms, self.margin)
        self.out32[:] = self.out
        return self.out32


# ---------------------------------------------------------------- storage of the garment_model/santesteban group


SANTESTEBAN_GROUP = "garment_model/santesteban"


@dataclass(frozen=True)
class SantestebanArrays:
    """The garment model of Santesteban et al. 2019 (group garment_model/santesteban): two regressors whose input is
    the pose's D dofs followed by the 6 phenotypes (their `dofs` index that vector), each predicting a rest-frame
    displacement (V, 3) of the garment: `fit` R_G(beta) and `wrinkles` R_L(beta, theta).

    | path | shape, dtype | meaning |
    |---|---|---|
    | garment_model/santesteban/fit/..., .../wrinkles/... | as pose_model/regressor, dofs in [0, D + 6) | R_G(beta) and R_L(beta, theta), both rest-frame displacements of the garment; attrs info (JSON) |
    """

    fit: Regressor
    wrinkles: Regressor
    info: dict = field(default_factory=dict)

    def vertex_rows(self, ids) -> "SantestebanArrays":
        return replace(self, fit=self.fit.vertex_rows(ids), wrinkles=self.wrinkles.vertex_rows(ids))


def _write_santesteban(h5, arrays: SantestebanArrays) -> None:
    write_regressor(h5, arrays.fit, SANTESTEBAN_GROUP + "/fit")
    write_regressor(h5, arrays.wrinkles, SANTESTEBAN_GROUP + "/wrinkles")
    h5[SANTESTEBAN_GROUP].attrs["info"] = json.dumps(arrays.info)


def _read_santesteban(reader) -> SantestebanArrays:
    """Its regressors checked like pose_model/regressor, with inputs the D pose dofs and the 6 phenotypes."""
    info = reader.json(SANTESTEBAN_GROUP, "info", "{}", dict)
    fit = reader.with_phenotype_inputs(SANTESTEBAN_GROUP + "/fit", required=True)
    wrinkles = reader.with_phenotype_inputs(SANTESTEBAN_GROUP + "/wrinkles", required=True)
    return SantestebanArrays(fit=fit, wrinkles=wrinkles, info=info)


register_codec(Codec("santesteban", SANTESTEBAN_GROUP, 1, _write_santesteban, _read_santesteban,
                     upgrade="agentdress lab santesteban --database FILE --drapes DRAPES"))
