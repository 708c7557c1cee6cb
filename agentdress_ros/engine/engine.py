"""The runtime engine: AgentDress synthesis (Eq. 4, 7-10) for one garment database on one Anny body.

    engine = load_engine("tshirt.h5", EngineConfig())        # or Engine(db, body, config)
    report = engine.set_shape(beta)                          # rare: re-evaluates every anchor's shape model
    vertices = engine.synthesize(rotvecs, root_translation)  # every frame: (V, 3) view of an internal buffer

Per frame: validate and canonicalise the pose -> forward kinematics for beta0 and beta (shared rotations) ->
sensitivity distance to every anchor per region, decay, top-K, weights -> pose model -> one fused kernel that
skins the pose model, adds the blended re-posed shape deltas and pushes vertices out of the body. No allocation on
the frame path beyond a few small Python objects; a set_shape builds new arrays and swaps one reference, so it may
run in another thread while frames are produced.
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..body import AnnyBody, quads_to_triangles
from ..body.kinematics import forward_kinematics, linear_blend_skinning, linear_blend_skinning_into
from ..garment.binding import SurfaceBinding, evaluate_surface_binding, largest_face_corners, vertex_normals
from .config import PER_FRAME_KNOBS, TAYLOR_MODES, EngineConfig
from .database import Codec, Database, read_database, register_codec, shape_features, write_regressor
from .kernels import (apply_push, block_accumulate, block_push, pose_transforms, prepare_pose, project_out_of_body,
                      region_neighbours, shape_anchors, spaced_candidates, synthesize_vertices, unpose)
from .pose_models import PoseModelContext, RegressorDecoder, canonical_poses, make_pose_model

N_REGION_SLOTS = 4  # a vertex has at most 4 bone influences, so at most 4 non-zero regions


# Phenotype differences below this are not reported as clamped or held: float32 round-off of a shape message and
# 4-digit values in YAML (age 0.6667 for beta0's 2/3) change the body by far less than a millimetre.
SHAPE_REPORT_TOLERANCE = 1e-3


@dataclass(frozen=True)
class ShapeReport:
    """What set_shape did.

    clamped / clamped_names: phenotypes the body and the garment were clamped on (outside Anny's [0, 1]; with an
    "absolute" shape basis, whose garment is the shape models alone, outside the allowed range as well).
    held_names: phenotypes only the shape models were held on, at the edge of their training range (age and
    proportions: trained at beta0 alone); the garment's fit (its surface binding) and the body follow them.
    """

    clamped: bool
    clamped_names: tuple
    requested: np.ndarray  # (P,)
    effective: np.ndarray  # (P,) the beta the body, its skeleton and the garment's fit were evaluated at
    seconds: float
    model_beta: np.ndarray | None = None  # (P,) the beta the shape models were evaluated at
    held_names: tuple = ()


@dataclass(frozen=True)
class _ShapeState:
    """Everything that depends on beta, swapped in as one reference."""

    beta: np.ndarray  # (P,)
    heads: np.ndarray  # (B, 3) rest joints of beta
    deltas: np.ndarray  # (N, 3, V) per-anchor rows for block_accumulate
    clearances: np.ndarray  # (N, V) d0^s (or (1, 1) when penetration is off)
    body_points: np.ndarray  # (V, 3) bound body vertex at rest
    body_normals: np.ndarray  # (V, 3)
    rest: np.ndarray  # (V, 3) config dtype: the garment fitted to beta at rest (its binding; beta0's rest without one)
    projection_points: np.ndarray | None = None  # (U', 3) the projection's body vertices at rest (projection > 0)


def select_database(db: Database, config: EngineConfig) -> Database:
    """The database restricted to the config's anchors subset, PCA components and vertex subset (level of detail)."""
    changes = {}
    if config.anchors is not None:
        if np.isscalar(config.anchors):
            count = int(np.clip(int(config.anchors), 1, db.n_anchors))
            keep = np.unique(np.linspace(0, db.n_anchors - 1, count).round().astype(int))
        else:
            keep = np.asarray(config.anchors, dtype=int).reshape(-1)
            if keep.size == 0 or keep.min() < -db.n_anchors or keep.max() >= db.n_anchors:
                raise ValueError(f"anchors subset must index 0..{db.n_anchors - 1}")
        examples = anchor_examples(db, keep)
        changes.update(anchor_poses=db.anchor_poses[keep], pca_mean=db.pca_mean[keep],
                       pca_components=db.pca_components[keep], ridge=db.ridge[keep],
                       explained_variance_ratio=db.explained_variance_ratio[keep],
                       example_poses=db.example_poses[examples], example_drapes=db.example_drapes[examples])
    if config.components is not None and config.components < db.n_components:
        c = int(config.components)
        changes.update(pca_components=changes.get("pca_components", db.pca_components)[:, :c],
                       ridge=changes.get("ridge", db.ridge)[:, :, :c],
                       explained_variance_ratio=changes.get("explained_variance_ratio",
                                                            db.explained_variance_ratio)[:, :c])
    if config.vertices is not None:
        ids = np.asarray(config.vertices, dtype=int).reshape(-1)
        if ids.size == 0 or ids.min() < 0 or ids.max() >= db.n_vertices:
            raise ValueError(f"vertex subset must index 0..{db.n_vertices - 1}")
        remap = np.full(db.n_vertices, -1)
        remap[ids] = np.arange(len(ids))
        faces = remap[db.faces]
        changes.update(
            faces=faces[(faces >= 0).all(axis=1)].astype(np.int32),
            rest=db.rest[ids], skin_indices=db.skin_indices[ids], skin_weights=db.skin_weights[ids],
            regions=db.regions[ids],
            pca_mean=changes.get("pca_mean", db.pca_mean)[:, ids],
            pca_components=changes.get("pca_components", db.pca_components)[:, :, ids],
            example_drapes=changes.get("example_drapes", db.example_drapes)[:, ids],
            sequence_drapes=None if db.sequence_drapes is None else db.sequence_drapes[:, ids],
            regressor=None if db.regressor is None else db.regressor.vertex_rows(ids),
            santesteban=None if db.santesteban is None else db.santesteban.vertex_rows(ids),
            shape_residual=None if db.shape_residual is None else db.shape_residual.vertex_rows(ids),
            **_binding_rows(db, ids),
        )
    return replace(db, **changes) if changes else db


def anchor_examples(db: Database, keep) -> np.ndarray:
    """Indices of the pose-model examples that are the beta0 drapes of anchors `keep` (an example whose pose equals
    the anchor's), in anchor order: an anchor subset restricts the pose model to its own anchors' drapes, as the
    paper builds its pose model at its sample points. Anchors without such an example (synthetic databases) add
    none."""
    found = [example_of(db, s) for s in np.arange(db.n_anchors)[keep]]
    return np.asarray([m for m in found if m is not None], dtype=int)


def example_of(db: Database, anchor: int) -> int | None:
    """The index of the pose-model example whose pose is anchor `anchor`'s (its beta0 drape), or None."""
    examples = np.asarray(db.example_poses, dtype=np.float64).reshape(len(db.example_poses), -1)
    pose = np.asarray(db.anchor_poses[anchor], dtype=np.float64).reshape(-1)
    same = np.flatnonzero(np.abs(examples - pose).max(axis=1) <= 1e-6)
    return int(same[0]) if len(same) else None


def _binding_rows(db: Database, ids) -> dict:
    """The garment binding arrays (when the database has them) at vertex indices `ids`."""
    if db.binding_triangles is None:
        return {}
    return dict(binding_triangles=db.binding_triangles[ids], binding_barycentric=db.binding_barycentric[ids],
                binding_offset=db.binding_offset[ids])


def region_blocks(regions: np.ndarray, slots: int = N_REGION_SLOTS):
    """Sort vertices by their set of non-zero regions (at most `slots`, renormalised) for the block kernels.

    regions (V, R) -> order (V,) internal -> caller vertex index, block_start (nb + 1,), block_regions (nb, slots)
    int32 (-1 padded), region_w (slots, V) float64 in internal order. A vertex with no region weight follows the
    torso (region 0) rather than dropping its shape term.
    """
    regions = np.clip(np.nan_to_num(np.asarray(regions, dtype=np.float64)), 0.0, None)
    top = np.argsort(-regions, axis=1, kind="stable")[:, :slots]
    top_w = np.take_along_axis(regions, top, axis=1)
    keep = top_w > 0
    signatures, weights = [], []
    for ids, w, k in zip(top, top_w, keep):
        if not k.any():
            ids, w, k = np.array([0]), np.array([1.0]), np.array([True])
        pairs = sorted(zip(ids[k].tolist(), (w[k] / w[k].sum()).tolist()))
        signatures.append(tuple(g for g, _ in pairs))
        weights.append([x for _, x in pairs])
    order = np.array(sorted(range(len(regions)), key=lambda v: (signatures[v], v)), dtype=np.int64)
    starts, block_regions = [], []
    region_w = np.zeros((slots, len(regions)))
    for i, v in enumerate(order):
        if i == 0 or signatures[v] != signatures[order[i - 1]]:
            starts.append(i)
            block_regions.append(list(signatures[v]) + [-1] * (slots - len(signatures[v])))
        region_w[: len(weights[v]), i] = weights[v]
    starts.append(len(order))
    return order, np.array(starts, dtype=np.int64), np.array(block_regions, dtype=np.int32), region_w


def permute_vertices(db: Database, order: np.ndarray) -> Database:
    """The database with every per-vertex array in `order` (faces are left in the caller's numbering)."""
    return replace(
        db, rest=db.rest[order], skin_indices=db.skin_indices[order], skin_weights=db.skin_weights[order],
        regions=db.regions[order], pca_mean=db.pca_mean[:, order], pca_components=db.pca_components[:, :, order],
        example_drapes=db.example_drapes[:, order],
        sequence_drapes=None if db.sequence_drapes is None else db.sequence_drapes[:, order],
        regressor=None if db.regressor is None else db.regressor.vertex_rows(order),
        santesteban=None if db.santesteban is None else db.santesteban.vertex_rows(order),
        shape_residual=None if db.shape_residual is None else db.shape_residual.vertex_rows(order),
        **_binding_rows(db, order))


def distance_metric(region_dof: np.ndarray, n_bones: int, eps_relative: float):
    """(dofs (Da,), Q (R, Da) float64, eps (R,)) of Eq. 7.

    The root's three rotation dofs are dropped (anchors are upright; the root's rotation reaches the garment through
    skinning only), as are dofs no region is sensitive to. A region with no sensitivity at all (e.g. the legs of a
    T-shirt) would see every anchor at distance 0 and blend arbitrary ones: it uses the sum over regions instead.
    """
    q = np.asarray(region_dof, dtype=np.float64).copy()
    q[:, :3] = 0.0
    q = np.clip(np.nan_to_num(q), 0.0, None)
    total = q.sum(axis=0)
    if not (total > 0).any():
        total = np.ones(3 * n_bones)
        total[:3] = 0.0
    scale = total.sum()
    for g in range(len(q)):
        if q[g].sum() <= 1e-9 * scale:
            q[g] = total
    dofs = np.flatnonzero(total > 0)
    q = np.ascontiguousarray(q[:, dofs])
    return dofs.astype(np.int64), q, eps_relative * q.sum(axis=1)


class Engine:
    """AgentDress runtime for database `db` on `body` (the database's rig), with the knobs of `config`.

    Attributes after construction: `db` (the level-of-detail/anchor-subset database actually used), `faces` (F, 3),
    `n_vertices`, `pose_model`, `shape_report` (the last set_shape), `bad_frames` (frames rejected for non-finite
    output; the previous good frame was returned instead: test_faults.py makes it happen).
    """

    def __init__(self, db: Database, body: AnnyBody, config: EngineConfig = EngineConfig()):
        if tuple(db.bone_names) != tuple(body.bone_names):
            raise ValueError(f"database rig {db.bone_names[:3]}... does not match the body's {body.bone_names[:3]}...")
        self.config = config
        self.body = body
        db = select_database(db, config)
        self.faces = db.faces  # (F, 3) in the output's vertex numbering
        # internally, vertices are sorted by region set (block kernels); output is written back in caller order
        self.order, self.block_start, self.block_regions, region_w = region_blocks(db.regions)
        db = permute_vertices(db, self.order)
        self.db = db
        self.dtype = np.dtype(config.dtype).type
        self._zero = self.dtype(0.0)
        self.mode = TAYLOR_MODES.index(config.taylor)
        self.parents = np.ascontiguousarray(body.parents, dtype=np.int64)
        self.n_bones = body.n_bones
        self.n_vertices = db.n_vertices
        self.skin_indices = np.ascontiguousarray(db.skin_indices, dtype=np.int32)
        self.skin_weights = np.ascontiguousarray(db.skin_weights, dtype=self.dtype)
        self._skin_weights64 = np.ascontiguousarray(db.skin_weights, dtype=np.float64)
        self.region_w = np.ascontiguousarray(region_w, dtype=self.dtype)
        self.dofs, self.q, self.eps = distance_metric(db.region_dof, self.n_bones, config.eps_relative)
        self.anchor_poses = canonical_poses(db.anchor_poses)
        self.features = np.ascontiguousarray(self.anchor_poses.reshape(db.n_anchors, -1)[:, self.dofs])
        self.neighbors = min(int(config.neighbors), db.n_anchors)  # anchors blended per region (shape models)

        # beta0: reference skeleton, shape-model coefficients, penetration binding (closest body vertex at rest)
        self.reference = body.shape(db.beta0)
        self._heads0 = np.ascontiguousarray(self.reference.heads, dtype=np.float64)
        self._phi0 = self._coefficients(db.beta0)
        surface = body.body_vertex_ids
        rest_tree = cKDTree(self.reference.vertices[surface])
        _, nearest = rest_tree.query(np.asarray(db.rest, dtype=np.float64))
        self.bound_body_vertex = surface[nearest]  # (V,) hm08 ids
        self._bind_projection(surface, rest_tree)

        # skinned_residual databases: the fitted garment skinned to every anchor at beta0 (the shape models add to it)
        self._residual = db.shape_basis == "skinned_residual"
        self._base0 = np.zeros((1, 1, 3))
        self._anchor_transforms0 = self._anchor_transforms(self._heads0)
        if self._residual:
            if db.binding_surface not in body.assets.group_faces:
                raise ValueError(f"database binding surface {db.binding_surface!r} is not a face group of the body")
            if db.binding_triangles.min() < 0 or db.binding_triangles.max() >= len(self.reference.vertices):
                raise ValueError("database garment binding names vertices the body does not have")
            self._binding = SurfaceBinding(db.binding_triangles, db.binding_barycentric, db.binding_offset)
            self._surface_faces = quads_to_triangles(body.assets.group_faces[db.binding_surface])
            self._base0 = self._skinned_at_anchors(self.reference, self._anchor_transforms0)

        context = PoseModelContext(
            db=db, reference_heads=self._heads0, parents=self.parents, dtype=self.dtype,
            neighbours=int(config.pose_neighbors), dofs=self.dofs, region_dof=self.q, eps=self.eps,
            power=float(config.power), decay=bool(config.decay), damping=float(config.damping),
            block_start=self.block_start, block_regions=self.block_regions, region_w=self.region_w)
        self.pose_model = make_pose_model(config.pose_model, context)
        self._pose_models = {config.pose_model: self.pose_model}  # shared by every fork: one of each loaded
        self._fold = self._anchor_residuals() if config.fold and self.mode == 0 else None
        self._shape_residual = None
        if config.shape_residual:
            if db.shape_residual is None:
                raise ValueError("shape_residual needs a database with shape_model/residual (train it with "
                                 "`agentdress lab shape-residual`)")
            self._shape_residual = RegressorDecoder(db.shape_residual, self.dtype)

        self.pose_model_context = context
        self._allocate_frame_buffers()
        self.bad_frames = 0
        self.shape_report = self.set_shape(db.beta0)

    def _bind_projection(self, surface, rest_tree):
        """config.projection > 0: the candidate body vertices of each output row, as CSR (offsets (V + 1,), local
        indices into the U body vertices any row names, with their skinning): its `projection` nearest at rest
        (beta0), and its `projection_examples` nearest at each pose-model example pose (the example drape against
        the body posed there). A pose brings body parts near that none at rest is near (the arm at the torso's side,
        the upper back under a collar): README "Speed vs accuracy" measures what the examples' candidates add.
        With projection_spacing > 0 a row keeps no two candidates closer than that at rest (the first of them, in
        the order above): neighbours a few millimetres apart add little that the posed normal does not.
        Each candidate's normal comes from its largest incident body face at rest: the face's other two corners
        (partners, (U, 2) local rows) follow the candidates as rows [U, U') where they are no candidate themselves.
        rest_tree: the surface vertices at rest (beta0), as a cKDTree."""
        k = int(self.config.projection)
        if k <= 0:
            self.projection_vertices = None
            return
        db, reference = self.db, self.reference
        _, nearest = rest_tree.query(np.asarray(db.rest, dtype=np.float64), k=k)
        columns = [np.asarray(nearest).reshape(self.n_vertices, k)]
        per_example = int(self.config.projection_examples)
        for pose, drape in zip(db.example_poses, db.example_drapes) if per_example > 0 else ():
            transforms, _ = self.body.pose(reference, np.asarray(pose, dtype=np.float64))
            posed = self.body.posed_vertices(reference, transforms)[surface]
            found = cKDTree(posed).query(np.asarray(drape, dtype=np.float64), k=per_example)[1]
            columns.append(np.asarray(found).reshape(self.n_vertices, per_example))
        table = np.empty((self.n_vertices, sum(c.shape[1] for c in columns)), dtype=np.int64)
        table[self.order] = surface[np.concatenate(columns, axis=1)]  # output row order, nearest at rest first
        table[~spaced_candidates(table, reference.vertices, float(self.config.projection_spacing))] = -1
        table.sort(axis=1)  # ascending ids: neighbouring rows read neighbouring posed points
        kept = table >= 0
        ids, local = np.unique(table[kept], return_inverse=True)
        corners = largest_face_corners(reference.vertices, self.body.body_faces)[ids]  # (U, 2) hm08 ids
        extra = np.setdiff1d(corners, ids)
        rows = np.concatenate([ids, extra])
        self.projection_vertices = rows  # (U',) hm08 ids: the U candidates, then the partners that are none
        self._projection_offsets = np.concatenate([[0], np.cumsum(kept.sum(axis=1))]).astype(np.int32)
        self._projection_candidates = np.ascontiguousarray(local, dtype=np.int32)
        row_of = np.full(len(reference.vertices), -1, dtype=np.int32)
        row_of[rows] = np.arange(len(rows))
        self._projection_partners = np.ascontiguousarray(row_of[corners])
        self._projection_skin = (np.ascontiguousarray(self.body.skin_indices[rows]),
                                 np.ascontiguousarray(self.body.skin_weights[rows], dtype=self.dtype))
        self._projection_count = len(ids)

    def projection_candidates(self, row: int) -> np.ndarray:
        """The body vertices (hm08 ids) the projection searches for output row `row` (config.projection > 0)."""
        start, stop = self._projection_offsets[row], self._projection_offsets[row + 1]
        return self.projection_vertices[self._projection_candidates[start:stop]]

    def _allocate_frame_buffers(self):
        """Per-frame scratch and output buffers (allocated once per engine; a fork gets its own)."""
        b, r, k = self.n_bones, self.q.shape[0], self.neighbors
        self._theta = np.zeros((b, 3))
        self._theta_flat = self._theta.reshape(-1)
        self._root = np.zeros(3)
        self._zero3 = np.zeros(3)
        self._rotations = np.zeros((b, 3, 3))
        self._positions0 = np.zeros((b, 3))
        self._positions = np.zeros((b, 3))
        self._transforms0 = np.zeros((b, 3, 4))
        self._reference_translations = self._transforms0[:, :, 3]
        self.transforms = np.zeros((b, 3, 4), dtype=self.dtype)  # (B, 3, 4) of the last frame, current shape
        self.selected = np.zeros((r, k), dtype=np.int32)
        self.weights = np.zeros((r, k), dtype=self.dtype)
        self._distances = np.zeros((r, self.db.n_anchors))
        self._has_distances = False
        v = self.n_vertices
        self._blended = np.zeros((3, v), dtype=self.dtype)
        self._clearance = np.zeros(v, dtype=self.dtype)
        self._normals = np.zeros((3, v), dtype=self.dtype)
        self._push = np.zeros(v, dtype=self.dtype)
        self._no_pose = np.zeros((3, v), dtype=self.dtype)
        self._residual_inputs = np.zeros(3 * b + len(self.db.beta0))  # the shape residual's: pose dofs, phenotypes
        if self.projection_vertices is not None:
            self._projected = np.zeros((len(self.projection_vertices), 3), dtype=self.dtype)
            self._projected_stamps = np.full(len(self.projection_vertices) - self._projection_count, -1)
            self._projected_frame = 0
        rest = np.empty((v, 3), dtype=self.dtype)
        rest[self.order] = self.db.rest
        self._buffers = (rest, rest.copy())  # double buffer: the last good frame survives a bad one
        self._current = 0

    def _anchor_residuals(self) -> np.ndarray | None:
        """(N, 3, V) f(beta0, theta_s) - pose_model(theta_s) in the rest frame, per anchor, for a pose model that is
        not exact at the anchors (`fold_anchor_residuals`): added to each anchor's shape delta, it makes synthesis
        reproduce f(beta0, theta_s) + the shape term at theta_s, at no cost per frame. f(beta0, theta_s) is the
        anchor's beta0 drape (its pose-model example), or its shape model at beta0 when the database has none."""
        if not getattr(self.pose_model, "fold_anchor_residuals", False):
            return None
        db = self.db
        residuals = np.empty((db.n_anchors, 3, self.n_vertices), dtype=self.dtype)
        unposed = np.empty((self.n_vertices, 3))
        zero = np.zeros(3)
        for s, pose in enumerate(self.anchor_poses):
            example = example_of(db, s)
            if example is not None:
                drape = np.asarray(db.example_drapes[example], dtype=np.float64)
            else:
                drape = (self._base0[s] if self._residual else 0.0) + db.pca_mean[s] + np.einsum(
                    "c,cvk->vk", self._phi0[s], db.pca_components[s, : self._phi0.shape[1]])
            unpose(drape, self.skin_indices, self._skin_weights64, self._anchor_transforms0[s], unposed)
            model = np.asarray(self.pose_model.evaluate(pose, zero, None), dtype=np.float64)
            residuals[s] = unposed.T - model
        self.reset()
        return residuals

    # ---------------------------------------------------------------- shape (rare, off the frame path)
    def _coefficients(self, beta) -> np.ndarray:
        """phi(beta) (N, C) of Eq. 6 for every anchor."""
        features = shape_features(beta, self.db.beta0, self.db.beta_scale)[0]
        return np.einsum("q,nqc->nc", features, self.db.ridge)

    def _anchor_transforms(self, heads) -> np.ndarray:
        """(N, B, 3, 4) skinning transforms of every anchor pose on the skeleton with rest joints `heads`."""
        transforms = np.empty((self.db.n_anchors, self.n_bones, 3, 4))
        for s, pose in enumerate(self.anchor_poses):
            forward_kinematics(pose, np.zeros(3), heads, self.parents, transforms[s])
        return transforms

    def _fitted_rest(self, shape) -> np.ndarray:
        """(V, 3) float64 the garment fitted to `shape` at rest (its surface binding), internal vertex order."""
        return evaluate_surface_binding(self._binding, shape.vertices, vertex_normals(shape.vertices,
                                                                                      self._surface_faces))

    def _skinned_at_anchors(self, shape, transforms) -> np.ndarray:
        """(N, V, 3) the garment fitted to `shape` at rest (its binding) and skinned to every anchor pose."""
        rest = self._fitted_rest(shape)
        out = np.empty((len(transforms), self.n_vertices, 3))
        for s in range(len(transforms)):
            linear_blend_skinning(rest, self.skin_indices, self._skin_weights64, transforms[s], out[s])
        return out

    def set_shape(self, beta) -> ShapeReport:
        """Re-evaluate every anchor's shape model and binding for `beta` (P,), then swap them in atomically.

        Raises ValueError naming the phenotype for non-finite values or a wrong length. The body, its skeleton and
        the garment's fit (the surface binding the skinned_residual basis adds back) follow beta within Anny's
        [0, 1]; only the shape models are held at their training range (unless config.clamp_to_training_range is
        False), so garment and body stay fitted to the same shape. Both are reported (ShapeReport).
        """
        start = time.perf_counter()
        db, config = self.db, self.config
        requested = np.asarray(beta, dtype=np.float64).reshape(-1)
        names = tuple(db.beta_names)
        if requested.shape != (len(names),):
            raise ValueError(f"body shape needs {len(names)} values {names}, got {requested.size}")
        bad = [names[i] for i in np.flatnonzero(~np.isfinite(requested))]
        if bad:
            raise ValueError(f"body shape has non-finite values for {', '.join(bad)}")
        effective = np.clip(requested, 0.0, 1.0)
        model_beta = np.clip(effective, *db.beta_range.T) if config.clamp_to_training_range else effective
        if not self._residual:  # no fit apart from the shape models: the garment, and so the body, are held too
            effective = model_beta
        clamped_names = tuple(names[i] for i in np.flatnonzero(np.abs(effective - requested) > SHAPE_REPORT_TOLERANCE))
        held_names = tuple(names[i] for i in np.flatnonzero(np.abs(model_beta - effective) > SHAPE_REPORT_TOLERANCE))

        shape = self.body.shape(effective)
        heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
        # new arrays only, never the live ones: a frame may be reading them while this runs in another thread
        transforms = self._anchor_transforms(heads)
        base = self._skinned_at_anchors(shape, transforms) if self._residual else self._base0
        rest = np.ascontiguousarray(self._fitted_rest(shape) if self._residual else db.rest, dtype=self.dtype)
        phi = self._coefficients(model_beta)
        normals = vertex_normals(shape.vertices, self.body.body_faces)
        body_points = np.ascontiguousarray(shape.vertices[self.bound_body_vertex], dtype=self.dtype)
        body_normals = np.ascontiguousarray(normals[self.bound_body_vertex], dtype=self.dtype)
        deltas = np.empty((db.n_anchors, 3, self.n_vertices), dtype=self.dtype)
        clearances = (np.empty((db.n_anchors, self.n_vertices), dtype=self.dtype) if config.penetration
                      else np.zeros((1, 1), dtype=self.dtype))
        shape_anchors(phi - self._phi0, phi, db.pca_mean, db.pca_components, transforms, self.skin_indices,
                      self._skin_weights64, self.mode, config.penetration, body_points.astype(np.float64),
                      body_normals.astype(np.float64), config.penetration_margin, deltas, clearances,
                      self._residual, base, self._base0, self._anchor_transforms0)
        if self._fold is not None:
            deltas += self._fold
        projection = None if self.projection_vertices is None else np.ascontiguousarray(
            shape.vertices[self.projection_vertices], dtype=self.dtype)
        self._state = _ShapeState(effective, heads, deltas, clearances, body_points, body_normals, rest, projection)
        report = ShapeReport(bool(clamped_names), clamped_names, requested, effective, time.perf_counter() - start,
                             model_beta, held_names)
        self.shape_report = report
        return report

    # ---------------------------------------------------------------- many agents on one loaded database
    #: EngineConfig fields a fork may change: they act per frame and leave the shape state's meaning unchanged.
    FORK_FIELDS = PER_FRAME_KNOBS

    def fork(self, **changes) -> "Engine":
        """A new engine for another agent (or another level of detail of this one) on the same loaded data.

        Shared, read-only: the database, anchor features, pose-model examples, skin weights, anchor transforms at
        beta0. Own: frame buffers, decay history, the shape state (it starts as this engine's; `set_shape` or
        `follow_shape` replace it). `changes` may set the per-frame knobs in FORK_FIELDS; turning penetration on
        needs a parent that computes the clearances (penetration on). Another pose model (a cheaper one for a far
        level of detail) needs a parent without the anchor fold, and is itself used without it: the shape state
        is then the same for every pose model. It is loaded once per parent and shared by its forks (the body
        projection keeps the parent's candidates). Costs ~100 kB at 1,200 vertices.
        """
        bad = sorted(set(changes) - set(self.FORK_FIELDS))
        if bad:
            raise ValueError(f"a fork can change only {', '.join(self.FORK_FIELDS)}; not {', '.join(bad)}")
        config = replace(self.config, **changes)
        if config.penetration and not self.config.penetration:
            raise ValueError("a fork with penetration handling needs a parent that has it (clearances)")
        if config.projection and config.projection != self.config.projection:
            raise ValueError(f"a fork can turn the body projection off, or keep the parent's "
                             f"{self.config.projection} candidates; not {config.projection}")
        twin = copy.copy(self)
        twin.config = config
        twin.neighbors = min(int(config.neighbors), self.db.n_anchors)
        if not config.projection:
            twin.projection_vertices = None
        context = replace(self.pose_model_context, power=float(config.power), decay=bool(config.decay),
                          damping=float(config.damping))
        twin.pose_model_context = context
        model = self.pose_model
        if config.pose_model != self.config.pose_model:
            if not self.can_fork_pose_model(config.pose_model):
                raise ValueError(f"a fork can change the pose model only where neither it nor the parent folds anchor "
                                 f"residuals (fold=false); {self.config.pose_model} -> {config.pose_model} would")
            model = self._loaded_pose_model(config.pose_model)
        fork_pose_model = getattr(model, "fork", None)
        twin.pose_model = fork_pose_model(context) if callable(fork_pose_model) else model
        if self._shape_residual is not None:
            twin._shape_residual = self._shape_residual.fork()
        twin._allocate_frame_buffers()
        twin._buffers[0][...] = self._buffers[self._current]
        return twin

    def clone(self) -> "Engine":
        """The same agent's engine, to be refitted off the frame path (set_shape on a worker thread) and swapped in:
        a fork, so that nothing it computes meanwhile (a rest-pose drape for a binding) reaches the live engine's
        frame buffers or decay history, that starts from this engine's decay history (a shape refit is no cut in
        the motion)."""
        twin = self.fork()
        twin._distances[...] = self._distances
        twin._has_distances = self._has_distances
        carry = getattr(twin.pose_model, "continue_from", None)
        if callable(carry):
            carry(self.pose_model)
        return twin

    def can_fork_pose_model(self, name: str) -> bool:
        """Whether a fork may run pose model `name`: neither this engine nor the fork folds anchor residuals into
        the shape state (which is then the same for every pose model)."""
        if name == self.config.pose_model:
            return True
        return self._fold is None and not (self.config.fold and getattr(self._loaded_pose_model(name),
                                                                         "fold_anchor_residuals", False))

    def _loaded_pose_model(self, name: str):
        """The pose model `name` on this engine's data, loaded once and shared with every fork."""
        if name not in self._pose_models:
            self._pose_models[name] = make_pose_model(name, self.pose_model_context)
        return self._pose_models[name]

    def follow_shape(self, source: "Engine") -> None:
        """Take `source`'s shape state (an engine forked from the same parent): one set_shape serves every level
        of detail of an agent. Atomic (one reference)."""
        if source.db is not self.db:
            raise ValueError("follow_shape needs an engine on the same loaded database")
        self.shape_report = source.shape_report
        self._state = source._state

    def skin(self, rotvecs, root_translation=None) -> np.ndarray:
        """The garment fitted to the current shape and skinned to the pose (V, 3), output order: no pose model,
        no shape model, no penetration handling (the cheapest level of detail; same vertices and topology as
        `synthesize`). Returns a view of an internal buffer like `synthesize`."""
        state = self._state
        self._pose(rotvecs, root_translation, state)
        out = self._buffers[1 - self._current]
        linear_blend_skinning_into(state.rest, self.skin_indices, self.skin_weights, self.transforms, self.order, out)
        if not np.isfinite(out).all():
            self.bad_frames += 1
            return self._buffers[self._current]
        self._current = 1 - self._current
        return out

    # ---------------------------------------------------------------- frame path
    def _pose(self, rotvecs, root_translation, state: _ShapeState) -> None:
        """Check and canonicalise the pose; forward kinematics on beta0's and the current skeleton (self.transforms).
        Raises ValueError naming the joint for a non-finite input."""
        rotvecs = np.asarray(rotvecs)
        if rotvecs.shape != (self.n_bones, 3):
            raise ValueError(f"rotvecs must have shape ({self.n_bones}, 3), got {rotvecs.shape}")
        root = self._zero3 if root_translation is None else np.asarray(root_translation).reshape(3)
        code = prepare_pose(rotvecs, root, self.config.max_root_translation, self._theta, self._root)
        if code >= 0:
            what = "root translation" if code == self.n_bones else f"joint {self.db.bone_names[code]}"
            raise ValueError(f"non-finite pose input for {what}")
        pose_transforms(self._theta, self._root, self._heads0, state.heads, self.parents, self._rotations,
                        self._positions0, self._positions, self._transforms0, self.transforms)

    def reset(self):
        """Forget the decay history (Eq. 9), e.g. after a cut in the motion."""
        self._has_distances = False
        if hasattr(self.pose_model, "reset"):
            self.pose_model.reset()

    def synthesize(self, rotvecs, root_translation=None, frame: int | None = None) -> np.ndarray:
        """Garment (V, 3) for pose rotvecs (B, 3) and root translation (3,) at the current shape.

        Returns a view of an internal buffer (config dtype), valid until the next-but-one call. `frame` is only
        used by the "sequence" pose model. Raises ValueError naming the joint for a non-finite input.
        """
        state = self._state  # one read: a concurrent set_shape swaps the whole state
        self._pose(rotvecs, root_translation, state)
        config = self.config
        if config.shape_model:
            region_neighbours(self._theta_flat, self.features, self.dofs, self.q, self.eps, config.power,
                              config.damping, self._distances, config.decay and self._has_distances, self.selected,
                              self.weights)
            self._has_distances = True
        if self.mode == 2:
            pose, skinned = self._no_pose, False  # the ablation has no pose model
        else:
            pose = self.pose_model.evaluate(self._theta, self._root, frame)
            skinned = self.pose_model.skinned
        blocks = (self.block_start, self.block_regions, self.region_w, self.selected, self.weights)
        if config.shape_model:  # else _blended stays all zero: the pose model alone
            block_accumulate(*blocks, state.deltas, self._blended)
            if self._shape_residual is not None:
                inputs = self._residual_inputs
                inputs[: self._theta_flat.size] = self._theta_flat
                inputs[self._theta_flat.size:] = state.beta
                self._blended += self._shape_residual.decode(inputs)
        penetration = config.penetration and config.shape_model
        out = self._buffers[1 - self._current]
        bad = synthesize_vertices(self._zero, self.skin_indices, self.skin_weights, self.transforms,
                                  self._reference_translations, pose, skinned, self._blended, self.mode,
                                  penetration, state.body_points, state.body_normals, self._clearance,
                                  self._normals, self.order, out)
        if penetration:
            block_push(self._zero, *blocks, state.clearances, self._clearance, self._push)
            bad = apply_push(self._push, self._normals, self.order, out)
        if self.projection_vertices is not None and not bad:
            self._projected_frame += 1
            bad = project_out_of_body(out, self._projection_offsets, self._projection_candidates,
                                      self._projection_partners, state.projection_points, *self._projection_skin,
                                      self.transforms, self._projected, self._projected_stamps,
                                      self._projected_frame, self.config.penetration_margin)
        if bad:
            self.bad_frames += 1
            return self._buffers[self._current]
        self._current = 1 - self._current
        return out

    def pose_model_output(self, rotvecs, root_translation=None, frame: int | None = None) -> np.ndarray:
        """f(beta0, theta) (V, 3) float64 of the configured pose model alone, in output order (evaluation; allocates).

        Touches the pose model's decay state (if any) like a frame would.
        """
        theta, root = np.zeros((self.n_bones, 3)), np.zeros(3)
        zero = np.zeros(3) if root_translation is None else np.asarray(root_translation, dtype=np.float64)
        if prepare_pose(np.asarray(rotvecs, dtype=np.float64), zero, self.config.max_root_translation, theta,
                        root) >= 0:
            raise ValueError("non-finite pose input")
        values = np.asarray(self.pose_model.evaluate(theta, root, frame), dtype=np.float64).T
        if self.pose_model.skinned:
            transforms = np.empty((self.n_bones, 3, 4))
            forward_kinematics(theta, root, self._heads0, self.parents, transforms)
            blend = np.einsum("vi,virc->vrc", self._skin_weights64, transforms[self.skin_indices])
            values = np.einsum("vrc,vc->vr", blend[:, :, :3], values) + blend[:, :, 3]
        out = np.empty_like(values)
        out[self.order] = values
        return out

    def anchor_weights(self) -> np.ndarray:
        """(N,) each anchor's blend weight averaged over vertices for the last frame (diagnostics, allocates)."""
        per_region = np.zeros((self.q.shape[0], self.db.n_anchors))
        np.put_along_axis(per_region, self.selected.astype(np.int64), self.weights.astype(np.float64), axis=1)
        mass = np.zeros(self.q.shape[0])
        for b in range(len(self.block_regions)):
            lo, hi = self.block_start[b], self.block_start[b + 1]
            for j, g in enumerate(self.block_regions[b]):
                if g >= 0:
                    mass[g] += self.region_w[j, lo:hi].sum()
        return (mass / mass.sum()) @ per_region


def load_engine(path, config: EngineConfig = EngineConfig(), body: AnnyBody | None = None) -> Engine:
    """Read a database file (raises DatabaseError naming the field) and build an Engine on `body` (default Anny)."""
    db = read_database(path)
    return Engine(db, body if body is not None else AnnyBody(), config)


# The learned shape residual (EngineConfig.shape_residual, offline.shape_residual), group shape_model/residual: the
# arrays of pose_model/regressor with dofs in [0, D + 6), its inputs the D pose dofs followed by the 6 phenotypes, its
# output a rest-frame displacement added to the blended shape delta; info (JSON) names the engine configuration it was
# trained against, so a new pose_model/regressor drops it.
SHAPE_RESIDUAL_GROUP = "shape_model/residual"
register_codec(Codec(
    "shape_residual", SHAPE_RESIDUAL_GROUP, 1, lambda h5, residual: write_regressor(h5, residual, SHAPE_RESIDUAL_GROUP),
    lambda reader: reader.with_phenotype_inputs(SHAPE_RESIDUAL_GROUP, required=True), trained_on="regressor",
    upgrade="agentdress lab shape-residual --database FILE --shaped PACK"))
