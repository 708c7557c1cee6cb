"""Clothing pose models f(beta0, theta) behind one small interface, and their registry by name (AgentDress Sec. 3.3).

A pose model answers `evaluate(theta, root, frame) -> (3, V)` for a canonical pose theta (B, 3) float64 (rotation
vectors with angles in [-pi, pi], see kernels.prepare_pose). Models with `skinned = True` return rest-frame
(canonical) positions that the engine skins with beta0's transforms in its fused frame kernel (cheaper than skinning
twice); the others return posed world positions. The layout is (3, V) (x, y and z rows: the frame kernels stream
them) in the engine's internal vertex order (the context's database is already permuted so); Engine.pose_model_output
gives (V, 3) in output order. The returned array may be an internal buffer or a constant array: the caller only
reads it before the next call. Later models (learned, volumetric) register the same way:

    @register_pose_model("mine")
    def _make(context: PoseModelContext) -> PoseModel: ...

A model with arrays of its own stores them in a database group through a Codec registered beside its code
(engine.database.register_codec, its module listed in engine.codecs), as the learned models at the end of this
module do; the database reads it into `db.<codec name>`.

Many agents' models of one kind answer together through `predict_batch` (a crowd's frame): a model class with an
`evaluate_batch(models, thetas, roots, frames)` classmethod runs them as one batch, any other one at a time.
"""
from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from ..body.kinematics import forward_kinematics
from .database import (N_INFLUENCES, POINTS, REGRESSOR_GROUP, Codec, Database, Regressor, create_dataset,
                       register_codec, shown, write_regressor)
from .kernels import add_to_columns, block_accumulate, prepare_pose, region_neighbours, unpose


@runtime_checkable
class PoseModel(Protocol):
    name: str
    skinned: bool  # evaluate returns rest-frame positions to be skinned with beta0's transforms

    def evaluate(self, theta: np.ndarray, root: np.ndarray, frame: int | None) -> np.ndarray:
        """(3, V) garment at beta0 for pose theta (B, 3), root translation (3,), optional sequence frame index."""


@dataclass(frozen=True)
class PoseModelContext:
    """What a pose model may use: the (level-of-detail sliced) database, beta0's rest skeleton, run dtype, and the
    engine's neighbour machinery (the same sensitivity distance as the anchors)."""

    db: Database
    reference_heads: np.ndarray  # (B, 3) beta0 rest joint positions
    parents: np.ndarray  # (B,) int64
    dtype: type
    neighbours: int  # K of the examples pose model (EngineConfig.pose_neighbors)
    dofs: np.ndarray  # (Da,) active pose dofs of the sensitivity distance
    region_dof: np.ndarray  # (R, Da) float64 Q_{g,m}, degenerate regions already replaced
    eps: np.ndarray  # (R,)
    power: float
    decay: bool
    damping: float
    block_start: np.ndarray  # (nb + 1,) vertex blocks of equal region sets (kernels.block_accumulate)
    block_regions: np.ndarray  # (nb, 4) int32
    region_w: np.ndarray  # (4, V)


POSE_MODELS: dict[str, Callable[[PoseModelContext], PoseModel]] = {}


def register_pose_model(name: str):
    """Decorator registering a factory `context -> PoseModel` under `name`."""

    def wrap(factory):
        POSE_MODELS[name] = factory
        return factory

    return wrap


def make_pose_model(name: str, context: PoseModelContext) -> PoseModel:
    if name not in POSE_MODELS:
        raise ValueError(f"unknown pose model {name!r}; choose one of {sorted(POSE_MODELS)}")
    return POSE_MODELS[name](context)


def predict_batch(models, thetas, roots, frames=None) -> list:
    """[(3, V)] of each agent's pose model `models[i]` (forks: their own buffers) for its pose thetas[i] (B, 3), root
    translation roots[i] (3,) and sequence frame frames[i] (None: none): the models' `evaluate_batch` classmethod
    where they are all of one class that has it (one product per layer over the batch), else each `evaluate` in
    turn (the same numbers either way)."""
    models = list(models)
    frames = [None] * len(models) if frames is None else list(frames)
    if not (len(thetas) == len(roots) == len(frames) == len(models)):
        raise ValueError(f"predict_batch: {len(models)} models for {len(thetas)} poses, {len(roots)} roots and "
                         f"{len(frames)} frames")
    kinds = {type(model) for model in models}
    batch = getattr(next(iter(kinds)), "evaluate_batch", None) if len(kinds) == 1 else None
    if batch is not None:
        return list(batch(models, thetas, roots, frames))
    return [model.evaluate(theta, root, frame) for model, theta, root, frame in zip(models, thetas, roots, frames)]


def canonical_poses(poses: np.ndarray) -> np.ndarray:
    """(M, B, 3) poses with every rotation vector's angle mapped into [-pi, pi] (same rotations)."""
    out = np.empty(poses.shape, dtype=np.float64)
    root = np.empty(3)
    for i, pose in enumerate(np.asarray(poses, dtype=np.float64)):
        prepare_pose(pose, np.zeros(3), 1.0, out[i], root)
    return out


class LbsPoseModel:
    """f(beta0, theta) = the garment rest mesh skinned (the engine does the skinning): a pose model without wrinkles."""

    name = "lbs"
    skinned = True

    def __init__(self, context: PoseModelContext):
        self.rest = np.ascontiguousarray(context.db.rest.T, dtype=context.dtype)

    def evaluate(self, theta, root, frame):
        return self.rest


class ExamplePoseModel:
    """Sensitivity-weighted blend of beta0 example drapes, in the spirit of SOR without its rigging optimisation.

    At load every example drape is unposed at its own pose (beta0's bones) to the rest frame; per frame the nearest
    examples per region (the anchors' sensitivity distance, K neighbours, power k, optional decay) are blended per
    vertex (Eq. 8 weights) in the rest frame; the engine skins the blend.
    """

    name = "examples"
    skinned = True

    def __init__(self, context: PoseModelContext):
        db = context.db
        if len(db.example_poses) == 0:
            raise ValueError("pose model 'examples' needs pose-model examples; the database (or its anchor subset) "
                             "has none")
        poses = canonical_poses(db.example_poses)
        skin_w = np.ascontiguousarray(db.skin_weights, dtype=np.float64)
        n_examples, n_vertices = db.example_drapes.shape[:2]
        canonical = np.empty((n_examples, 3, n_vertices), dtype=context.dtype)
        transforms = np.empty((len(context.parents), 3, 4))
        unposed = np.empty((n_vertices, 3))
        for m, pose in enumerate(poses):
            forward_kinematics(pose, np.zeros(3), context.reference_heads, context.parents, transforms)
            unpose(db.example_drapes[m].astype(np.float64), db.skin_indices, skin_w, transforms, unposed)
            canonical[m] = unposed.T
        self.canonical = canonical
        self.features = np.ascontiguousarray(poses.reshape(len(poses), -1)[:, context.dofs])
        self.context = context
        k = min(context.neighbours, len(poses))
        n_regions = context.region_dof.shape[0]
        self.state = np.zeros((n_regions, len(poses)))
        self.has_state = False
        self.selected = np.zeros((n_regions, k), dtype=np.int32)
        self.weights = np.zeros((n_regions, k), dtype=context.dtype)
        self.out = np.empty(canonical.shape[1:], dtype=context.dtype)

    def reset(self):
        self.has_state = False

    def fork(self, context: PoseModelContext) -> "ExamplePoseModel":
        """A model sharing the unposed examples, with its own decay history and buffers (another agent, or other
        per-frame knobs in `context`)."""
        twin = copy.copy(self)
        twin.context = context
        k = min(context.neighbours, len(self.features))
        twin.state = np.zeros_like(self.state)
        twin.has_state = False
        twin.selected = np.zeros((self.state.shape[0], k), dtype=np.int32)
        twin.weights = np.zeros((self.state.shape[0], k), dtype=context.dtype)
        twin.out = np.empty_like(self.out)
        return twin

    def continue_from(self, other: "ExamplePoseModel") -> None:
        """Take over another fork's decay history (a refitted clone continues the motion)."""
        self.state[...] = other.state
        self.has_state = other.has_state

    def evaluate(self, theta, root, frame):
        c = self.context
        region_neighbours(theta.reshape(-1), self.features, c.dofs, c.region_dof, c.eps, c.power, c.damping,
                          self.state, c.decay and self.has_state, self.selected, self.weights)
        self.has_state = True
        block_accumulate(c.block_start, c.block_regions, c.region_w, self.selected, self.weights, self.canonical,
                         self.out)
        return self.out


class SequencePoseModel:
    """The simulated beta0 sequence as a pose model (evaluation only): drape of frame `frame`, or of the sequence
    frame whose pose is nearest (sensitivity-weighted, wrapped) when no frame is given; shifted by the difference of
    root translations."""

    name = "sequence"
    skinned = False

    def __init__(self, context: PoseModelContext):
        db = context.db
        if db.sequence_drapes is None:
            raise ValueError("pose model 'sequence' needs a database with pose_model/sequence")
        self.drapes = np.ascontiguousarray(np.transpose(db.sequence_drapes, (0, 2, 1)), dtype=context.dtype)
        poses = canonical_poses(db.sequence_poses)
        self.features = poses.reshape(len(poses), -1)[:, context.dofs]
        self.dof_weight = context.region_dof.sum(axis=0)
        roots = db.sequence_root_translation
        self.roots = np.zeros((len(poses), 3)) if roots is None else np.asarray(roots, dtype=np.float64)
        self.out = np.empty(self.drapes.shape[1:], dtype=context.dtype)
        self.dofs = context.dofs

    def fork(self, context: PoseModelContext) -> "SequencePoseModel":
        twin = copy.copy(self)
        twin.out = np.empty_like(self.out)
        return twin

    def nearest_frame(self, theta) -> int:
        diff = theta.reshape(-1)[self.dofs] - self.features
        diff -= 2 * np.pi * np.floor(diff / (2 * np.pi) + 0.5)
        return int(np.argmin((diff**2) @ self.dof_weight))

    def evaluate(self, theta, root, frame):
        t = self.nearest_frame(theta) if frame is None else int(np.clip(frame, 0, len(self.drapes) - 1))
        np.add(self.drapes[t], (root - self.roots[t]).astype(self.out.dtype)[:, None], out=self.out)
        return self.out


#: Standardised MLP inputs are clipped to this many training standard deviations: a guard, never reached by the
#: shipped models on the held-out set. A dof nearly constant in the training data (a clavicle or hip-joint rotation
#: set by the retarget at beta0) had a tiny scale, and the same motion retargeted to another body moved it 30 of
#: them: the MLP extrapolated the trousers 10 cm off (training now leaves such inputs out). Not tighter: the
#: phenotypes of Santesteban et al.'s wrinkle regressor, trained mostly at beta0, sit 6 deviations out on shapes
#: of the training range, and clipping them at 4 cost 0.2 cm.
INPUT_CLIP = 8.0


def standardized(values, mean, scale) -> np.ndarray:
    """(..., I) inputs standardised with the training mean and scale (I,), clipped to +-INPUT_CLIP: what every
    regressor MLP sees, in training and at run time."""
    z = (values - mean) / scale
    return np.clip(z, -INPUT_CLIP, INPUT_CLIP, out=z)


class RegressorDecoder:
    """A stored Regressor evaluated with numpy: an input vector's `dofs`, standardised, through the MLP to PCA
    coefficients, decoded to a (3, V) array (x, y and z rows; `out`, an internal buffer). The output's
    standardisation is folded into basis and mean: value = mean' + sum_g y_g (scale_g basis_g)."""

    def __init__(self, reg, dtype=np.float64):
        self.dofs = np.asarray(reg.dofs, dtype=np.int64)
        self.input_mean = np.asarray(reg.input_mean, dtype=np.float64)
        self.input_scale = np.asarray(reg.input_scale, dtype=np.float64)
        self.weights = [np.ascontiguousarray(w, dtype=np.float64) for w in reg.weights]
        self.biases = [np.asarray(b, dtype=np.float64) for b in reg.biases]
        self.relu = reg.activation == "relu"
        n_vertices = reg.mean.shape[0]
        unit = np.asarray(reg.basis, dtype=np.float64)
        basis = unit * np.asarray(reg.coefficient_scale, dtype=np.float64)[:, None, None]
        mean = np.asarray(reg.mean, dtype=np.float64) + np.einsum("g,gvk->vk", reg.coefficient_mean.astype(np.float64),
                                                                 unit)
        self.basis = np.ascontiguousarray(np.transpose(basis, (0, 2, 1)).reshape(len(basis), 3 * n_vertices),
                                          dtype=dtype)  # (G, 3V): x row, y row, z row
        self.mean = np.ascontiguousarray(mean.T.reshape(-1), dtype=dtype)
        blocks = mlp_blocks(self.weights, unit)
        # a parts regressor (offline.regressor.merged_parts): each block alone, none of the zeros between them
        self.blocks = None if blocks is None else _Blocks(self.weights, self.biases, basis, dtype, self.relu, blocks)
        self._allocate()

    def _allocate(self):
        self.hidden = [np.empty(w.shape[1]) for w in self.weights]
        self.coefficients = np.empty(self.basis.shape[0], dtype=self.basis.dtype)
        self.flat = np.empty(self.basis.shape[1], dtype=self.basis.dtype)
        self.out = self.flat.reshape(3, -1)
        self.outputs = np.empty(self.weights[-1].shape[1])

    def fork(self) -> "RegressorDecoder":
        """A decoder sharing the weights, with buffers of its own."""
        twin = copy.copy(self)
        twin._allocate()
        if self.blocks is not None:
            twin.blocks = self.blocks.fork()
        return twin

    def standardize(self, inputs) -> np.ndarray:
        """(I,) the MLP's standardised input for an input vector (whose `dofs` it reads), clipped to
        +-INPUT_CLIP."""
        return standardized(inputs.reshape(-1)[self.dofs], self.input_mean, self.input_scale)

    def coefficients_of(self, inputs) -> np.ndarray:
        """The MLP's standardised output y (G,) for an input vector (an internal buffer)."""
        return self.mlp(self.standardize(inputs))

    def mlp(self, x) -> np.ndarray:
        """The MLP's standardised output y (G,) for a standardised input x (I,) (an internal buffer)."""
        if self.blocks is not None:
            self.blocks.mlp(x, self.outputs)
            return self.outputs
        last = len(self.weights) - 1
        for n, (w, b, h) in enumerate(zip(self.weights, self.biases, self.hidden)):
            np.dot(x, w, out=h)
            h += b
            if n < last:
                if self.relu:
                    np.maximum(h, 0.0, out=h)
                else:
                    np.tanh(h, out=h)
            x = h
        return x

    def decode(self, inputs) -> np.ndarray:
        """(3, V) output for an input vector."""
        return self.decode_outputs(self.coefficients_of(inputs))

    def decode_outputs(self, outputs) -> np.ndarray:
        """(3, V) output for standardised MLP outputs y (G,)."""
        self.coefficients[:] = outputs
        if self.blocks is not None:
            self.flat[:] = self.mean
            self.blocks.decode(self.coefficients, self.out)
            return self.out
        np.dot(self.coefficients, self.basis, out=self.flat)
        self.flat += self.mean
        return self.out


def mlp_blocks(weights: list, basis: np.ndarray) -> list | None:
    """[(input rows, hidden units, outputs, vertices)] of a one-hidden-layer MLP whose units fall into independent
    blocks (a parts regressor, offline.regressor.merged_parts: no weight joins two blocks, each block's outputs decode
    onto its own vertices of basis (G, V, 3)); None when it is one block. Found from the exact zeros."""
    if len(weights) != 2:
        return None
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    first, last = (np.asarray(w) != 0 for w in weights)
    n_hidden, n_outputs = last.shape
    units, outputs = np.nonzero(last)  # hidden units joined through a common output are one block
    graph = coo_matrix((np.ones(len(units)), (units, n_hidden + outputs)), shape=(n_hidden + n_outputs,) * 2)
    roots = connected_components(graph, directed=False)[1][:n_hidden]
    blocks = []
    for label in np.unique(roots):
        units = np.flatnonzero(roots == label)
        outputs = np.flatnonzero(last[units].any(axis=0))
        if len(outputs):  # a unit that feeds no output (its weights all zero) changes nothing
            if outputs[-1] - outputs[0] + 1 != len(outputs):
                return None  # not laid out as merged_parts does: the dense product is exact as well
            rows = np.flatnonzero(first[:, units].any(axis=1))
            vertices = np.flatnonzero(np.abs(basis[outputs]).sum(axis=(0, 2)) > 0)
            blocks.append((rows, units, outputs, vertices))
    return blocks if len(blocks) > 1 else None


class _Blocks:
    """The blocks of mlp_blocks evaluated alone, in the decoder's dtype (float32 in the node: half the time of
    float64): per block only its inputs, hidden units and outputs, and its outputs decoded onto its own vertices (the
    scaled basis (G, V, 3) restricted). Per-call overhead, not arithmetic, dominates at these sizes, so the hidden
    units of all blocks share one buffer (one bias and one activation call) and each block's outputs are a contiguous
    range of G (as merged_parts lays them out; mlp_blocks checks)."""

    def __init__(self, weights, biases, basis, dtype, relu, blocks):
        self.relu, self.dtype, self.n_inputs = relu, dtype, weights[0].shape[0]
        self.rows = [r for r, _, _, _ in blocks]
        self.vertices = [v for _, _, _, v in blocks]
        self.units = np.cumsum([0] + [len(u) for _, u, _, _ in blocks])
        self.outputs = [(int(o[0]), int(o[-1]) + 1) for _, _, o, _ in blocks]
        self.first = [np.ascontiguousarray(weights[0][np.ix_(r, u)], dtype=dtype) for r, u, _, _ in blocks]
        self.last = [np.ascontiguousarray(weights[1][np.ix_(u, o)], dtype=dtype) for _, u, o, _ in blocks]
        self.first_bias = np.ascontiguousarray(np.concatenate([biases[0][u] for _, u, _, _ in blocks]), dtype=dtype)
        self.last_bias = np.asarray(biases[1], dtype=np.float64)
        self.basis = [np.ascontiguousarray(np.transpose(basis[np.ix_(o, v)], (0, 2, 1)).reshape(len(o), 3 * len(v)),
                                           dtype=dtype) for _, _, o, v in blocks]  # (G_b, 3 V_b): x, y, z rows
        self._allocate()

    def _allocate(self):  # the per-frame arrays (each block's gathered inputs excepted, below)
        self.x = np.empty(self.n_inputs, dtype=self.dtype)
        self.hidden = np.empty(self.units[-1], dtype=self.dtype)
        self.result = np.empty(len(self.last_bias), dtype=self.dtype)
        self.coefficients = np.empty(len(self.last_bias), dtype=self.dtype)
        self.flats = [np.empty(b.shape[1], dtype=self.dtype) for b in self.basis]

    def fork(self) -> "_Blocks":
        twin = copy.copy(self)
        twin._allocate()
        return twin

    def mlp(self, x, outputs):
        """outputs (G,) = the MLP's standardised output for a standardised input x (I,)."""
        np.copyto(self.x, x, casting="same_kind")
        for b, (rows, first) in enumerate(zip(self.rows, self.first)):
            # a fancy-index gather allocates its <= 49 floats in 0.3 us; np.take into a buffer takes 1.8 us
            np.dot(self.x[rows], first, out=self.hidden[self.units[b]:self.units[b + 1]])
        self.hidden += self.first_bias
        if self.relu:
            np.maximum(self.hidden, 0.0, out=self.hidden)
        else:
            np.tanh(self.hidden, out=self.hidden)
        for b, ((g0, g1), last) in enumerate(zip(self.outputs, self.last)):
            np.dot(self.hidden[self.units[b]:self.units[b + 1]], last, out=self.result[g0:g1])
        np.add(self.result, self.last_bias, out=outputs)

    def decode(self, coefficients, out):
        """out (3, V) += every block's coefficients times its basis, on its vertices."""
        np.copyto(self.coefficients, coefficients, casting="same_kind")
        for (g0, g1), basis, vertices, flat in zip(self.outputs, self.basis, self.vertices, self.flats):
            np.dot(self.coefficients[g0:g1], basis, out=flat)
            add_to_columns(out, vertices, flat.reshape(3, -1))


class RegressorPoseModel:
    """The learned pose model of the database's pose_model/regressor group (Santesteban et al. 2019, Sec. 3-4, at
    beta0): the pose's dofs, standardised, through an MLP to PCA coefficients of the garment unposed to the rest
    frame (their Eq. 5); the engine skins the result. A few small matrix products per frame, no learning library.

    Not exact at the anchors: the engine folds each anchor's residual into its shape delta (EngineConfig.fold).
    """

    name = "regressor"
    skinned = True
    fold_anchor_residuals = True

    def __init__(self, context: PoseModelContext):
        reg = context.db.regressor
        if reg is None:
            raise ValueError("pose model 'regressor' needs a database with pose_model/regressor (train one with "
                             "`agentdress lab regressor`)")
        self.decoder = RegressorDecoder(reg, context.dtype)

    def fork(self, context: PoseModelContext) -> "RegressorPoseModel":
        twin = copy.copy(self)
        twin.decoder = self.decoder.fork()
        return twin

    def coefficients_of(self, theta) -> np.ndarray:
        """The MLP's standardised output y (G,) for a canonical pose theta (B, 3)."""
        return self.decoder.coefficients_of(theta)

    def evaluate(self, theta, root, frame):
        return self.decoder.decode(theta)


#: A pose whose largest joint rotation component moves more than this (rad) in one frame is a cut: the recurrent
#: state restarts.
JUMP_RAD = 1.0


class RecurrentPoseModel:
    """The `regressor` with memory (Santesteban et al. 2019's R_L is a GRU over the pose sequence): a GRU of the
    database's pose_model/recurrent group runs over the regressor's standardised inputs, one step per frame, and its
    state adds a correction to the regressor's standardised outputs before they are decoded. The state belongs to
    this model (a fork starts its own), restarts on reset() (the node resets on a stamp jump) and on a pose jump
    (JUMP_RAD). Trained on 30 fps sequences (offline.recurrent): one step per new pose at about that rate."""

    name = "recurrent"
    skinned = True
    fold_anchor_residuals = False  # a residual at the anchors depends on the state: nothing fixed to fold

    def __init__(self, context: PoseModelContext):
        reg, rec = context.db.regressor, context.db.recurrent
        if reg is None or rec is None:
            raise ValueError("pose model 'recurrent' needs a database with pose_model/regressor and "
                             "pose_model/recurrent (train them with `agentdress lab regressor` and "
                             "`agentdress lab recurrent`)")
        self.decoder = RegressorDecoder(reg, context.dtype)
        self.input_weights = np.asarray(rec.input_weights, dtype=np.float64)
        self.state_weights = np.asarray(rec.state_weights, dtype=np.float64)
        self.bias = np.asarray(rec.bias, dtype=np.float64)
        self.output_weights = np.asarray(rec.output_weights, dtype=np.float64)
        self.output_bias = np.asarray(rec.output_bias, dtype=np.float64)
        self._allocate()

    def _allocate(self):
        self.state = np.zeros(self.state_weights.shape[0])
        self._last = self._change = None  # (B, 3) buffers: the last pose, its change to this frame's (first frame)
        self._has_last = False  # no frame since the last reset

    def fork(self, context: PoseModelContext) -> "RecurrentPoseModel":
        twin = copy.copy(self)
        twin.decoder = self.decoder.fork()
        twin._allocate()
        return twin

    def reset(self) -> None:
        self.state[:] = 0.0
        self._has_last = False

    def continue_from(self, other: "RecurrentPoseModel") -> None:
        """Take over another fork's recurrent state and last pose (a refitted clone continues the motion)."""
        self.state[...] = other.state
        self._has_last = other._has_last
        if other._last is not None:
            self._last, self._change = other._last.copy(), np.empty_like(other._last)

    def evaluate(self, theta, root, frame):
        if self._last is None:
            self._last, self._change = np.empty_like(theta), np.empty_like(theta)
        elif self._has_last:
            np.subtract(theta, self._last, out=self._change)
            if np.abs(self._change, out=self._change).max() > JUMP_RAD:
                self.reset()
        np.copyto(self._last, theta)
        self._has_last = True
        x = self.decoder.standardize(theta)
        self.state[:] = gru_step(x, self.state, self.input_weights, self.state_weights, self.bias)
        outputs = self.decoder.mlp(x)  # the decoder's buffer: corrected in place
        outputs += self.state @ self.output_weights
        outputs += self.output_bias
        return self.decoder.decode_outputs(outputs)


def gru_step(x, h, input_weights, state_weights, bias):
    """One GRU step: the new state (H,) for input x (I,) and state h (H,); weights (I, 3H), (H, 3H), bias (3H,) with
    the gates z (update), r (reset), n (candidate) in that order (the candidate's state term is gated by r)."""
    size = len(h)
    a = x @ input_weights + bias
    s = h @ state_weights
    z = 1.0 / (1.0 + np.exp(-(a[:size] + s[:size])))
    r = 1.0 / (1.0 + np.exp(-(a[size:2 * size] + s[size:2 * size])))
    n = np.tanh(a[2 * size:] + r * s[2 * size:])
    return (1.0 - z) * n + z * h


class KdsmPoseModel:
    """The learned pose model of the database's pose_model/kdsm group (KDSM paper, Sec. 3-6, at beta0): an MLP of the
    regressor's kind predicts the garment's plastic displacements d(theta) in the KDSM (PCA coefficients, rest
    frame); rest + d is re-embedded in the KDSM's rest lattice (O(1) a vertex) and each vertex moves with its parent
    tet's four skinned vertices (kdsm.embedding.pose_displaced); vertices that leave the shell are skinned with the
    garment's own weights. Returns posed world positions at beta0 (`skinned = False`).

    The group's rest garment is matched to the context's vertex order (the engine reorders and slices vertices).
    """

    name = "kdsm"
    skinned = False

    def __init__(self, context: PoseModelContext):
        from dataclasses import replace

        from scipy.spatial import cKDTree

        from ..kdsm.embedding import KdsmPoser
        from ..kdsm.mesh import spatially_ordered

        db = context.db
        model = db.kdsm_model
        if model is None:
            raise ValueError("pose model 'kdsm' needs a database with pose_model/kdsm (train one with "
                             "`python -m agentdress_ros.evaluate.kdsm_comparison`)")
        distance, ids = cKDTree(np.asarray(model.rest, dtype=np.float64)).query(np.asarray(db.rest, dtype=np.float64))
        if len(ids) and distance.max() > 1e-6:
            raise ValueError("pose model 'kdsm': the database's garment is not the one its KDSM group was trained "
                             f"for (a rest vertex {distance.max():.3g} m from the group's)")
        model = model.vertex_rows(ids)
        # d in the run dtype: float32 halves the MLP's and decoder's cost; the lattice needs no more than 0.1 um
        self.displacements = RegressorPoseModel(replace(context, db=replace(db, regressor=model.regressor)))
        # Z order (kdsm.mesh.spatially_ordered): a KDSM stored before builds made it so reads faster
        self.poser = KdsmPoser(spatially_ordered(model.kdsm), model.rest, db.skin_indices, db.skin_weights)
        self.heads = np.ascontiguousarray(context.reference_heads, dtype=np.float64)
        self.parents = np.asarray(context.parents, dtype=np.int64)
        self.dtype = context.dtype
        self._allocate()

    def _allocate(self):
        self.transforms = np.empty((len(self.parents), 3, 4))
        self.out = np.empty((3, len(self.poser.rest)), dtype=self.dtype)

    def fork(self, context: PoseModelContext) -> "KdsmPoseModel":
        from ..kdsm.embedding import KdsmPoser

        twin = copy.copy(self)
        twin.displacements = self.displacements.fork(context)
        old = self.poser
        twin.poser = KdsmPoser(old.kdsm, old.rest, old.skin_indices, old.skin_weights)
        twin._allocate()
        return twin

    @property
    def fallback_count(self) -> int:
        """Vertices skinned outside the shell in the last frame."""
        return self.poser.fallback_count

    def evaluate(self, theta, root, frame):
        d = self.displacements.evaluate(theta, root, frame)  # (3, V) rest-frame d
        forward_kinematics(theta, np.asarray(root, dtype=np.float64), self.heads, self.parents, self.transforms)
        self.poser.pose(self.transforms, d.T, out=self.out.T)
        return self.out


register_pose_model("lbs")(LbsPoseModel)
register_pose_model("examples")(ExamplePoseModel)
register_pose_model("sequence")(SequencePoseModel)
register_pose_model("regressor")(RegressorPoseModel)
register_pose_model("recurrent")(RecurrentPoseModel)
register_pose_model("kdsm")(KdsmPoseModel)


# ---------------------------------------------------------------- storage of the learned pose models' groups


def _read_regressor(reader) -> Regressor:
    return reader.regressor(REGRESSOR_GROUP, required=True)


register_codec(Codec(
    "regressor", REGRESSOR_GROUP, 1, lambda h5, regressor: write_regressor(h5, regressor), _read_regressor,
    upgrade="agentdress lab regressor --database FILE --pack PACK"))


RECURRENT_GROUP = "pose_model/recurrent"
RECURRENT_ARRAYS = ("input_weights", "state_weights", "bias", "output_weights", "output_bias")


@dataclass(frozen=True)
class Recurrent:
    """The recurrent pose model's GRU (group pose_model/recurrent): its input is the regressor's standardised input
    x (I,), its state h (H,); the regressor's standardised output y (G,) becomes y + output_weights h + output_bias.

    | path | shape, dtype | meaning |
    |---|---|---|
    | pose_model/recurrent/input_weights, .../state_weights, .../bias | (I, 3H), (H, 3H), (3H,) f32 | the GRU (gates z, r, n in that order); attrs hidden (H), info (JSON) |
    | pose_model/recurrent/output_weights, .../output_bias | (H, G), (G,) f32 | the state's correction of the regressor's standardised outputs |
    """

    input_weights: np.ndarray  # (I, 3H) f32: gates z, r, n
    state_weights: np.ndarray  # (H, 3H) f32
    bias: np.ndarray  # (3H,) f32
    output_weights: np.ndarray  # (H, G) f32
    output_bias: np.ndarray  # (G,) f32
    info: dict = field(default_factory=dict)

    @property
    def hidden(self) -> int:
        return self.state_weights.shape[0]


def _write_recurrent(h5, recurrent: Recurrent) -> None:
    group = h5.require_group(RECURRENT_GROUP)
    for name in RECURRENT_ARRAYS:
        create_dataset(group, name, np.ascontiguousarray(getattr(recurrent, name), dtype=np.float32))
    group.attrs["hidden"] = recurrent.hidden
    group.attrs["info"] = json.dumps(recurrent.info)


def _read_recurrent(reader) -> Recurrent:
    """Its sizes tied to pose_model/regressor's inputs (I) and outputs (G), which it needs."""
    regressor = reader.stored.get("regressor")
    if regressor is None:
        reader.fail(f"needs the group '{REGRESSOR_GROUP}', which is missing")
    hidden = reader.attribute(RECURRENT_GROUP, "hidden")
    if not (np.ndim(hidden) == 0 and np.asarray(hidden).dtype.kind in "iu" and 1 <= hidden <= 4096):
        reader.fail(f"is {shown(hidden)!r}, expected a state size in [1, 4096]")
    info = reader.json(RECURRENT_GROUP, "info", "{}", dict)
    h, i, g = int(hidden), len(regressor.dofs), len(regressor.coefficient_scale)  # tied to the regressor
    shapes = {"input_weights": (i, 3 * h), "state_weights": (h, 3 * h), "bias": (3 * h,),
              "output_weights": (h, g), "output_bias": (g,)}
    values = {}
    for name in RECURRENT_ARRAYS:
        field_name = f"{RECURRENT_GROUP}/{name}"
        array = reader.numeric(field_name, np.float32, shapes[name])
        reader.check_range(field_name, array, (-1.0e6, 1.0e6), np.float32)
        values[name] = reader.cast(array, np.float32)
    return Recurrent(**values, info=info)


register_codec(Codec(
    "recurrent", RECURRENT_GROUP, 1, _write_recurrent, _read_recurrent, trained_on="regressor",
    upgrade="agentdress lab recurrent --database FILE --pack PACK"))


KDSM_GROUP = "pose_model/kdsm"
KDSM_ARRAYS = ("origin", "dims", "vertices", "tets", "class_inverse", "lattice_tets", "skin_indices", "skin_weights",
               "body_distance")


@dataclass(frozen=True)
class KdsmModel:
    """The `kdsm` pose model's arrays (group pose_model/kdsm): the KDSM (kdsm.mesh.KDSM), the rest garment its
    displacements belong to, and the regressor of d(theta) (rest-frame displacements instead of positions).

    | path | shape, dtype | meaning |
    |---|---|---|
    | pose_model/kdsm/origin, .../dims, .../vertices, .../tets, .../class_inverse, .../lattice_tets | (3,) f64, (3,) int64, (Nk, 3) f64, (Tk, 4) int32, (12, 3, 3) f64, (Lk,) int32 | the KDSM; attrs spacing, settings (JSON), kdsm_info (JSON), info (JSON) |
    | pose_model/kdsm/skin_indices, .../skin_weights, .../body_distance | (Nk, 4) int32, (Nk, 4) f64, (Nk,) f64 | the tet vertices' skinning and rest distance to the body |
    | pose_model/kdsm/rest | (V, 3) f32 | u^{m_o}: the rest garment the displacements are learned for (in this file's vertex order) |
    | pose_model/kdsm/regressor/... | as pose_model/regressor | the learned d(theta): PCA of the plastic displacements d, MLP from the pose |
    """

    kdsm: object  # kdsm.mesh.KDSM
    rest: np.ndarray  # (V, 3) f32
    regressor: Regressor
    info: dict = field(default_factory=dict)

    def vertex_rows(self, ids) -> "KdsmModel":
        """The model restricted to (or reordered by) garment vertex indices `ids`."""
        return replace(self, rest=self.rest[ids], regressor=self.regressor.vertex_rows(ids))


def _write_kdsm_model(h5, model: KdsmModel) -> None:
    from dataclasses import asdict

    group = h5.require_group(KDSM_GROUP)
    kdsm = model.kdsm
    for name in KDSM_ARRAYS:
        create_dataset(group, name, np.ascontiguousarray(getattr(kdsm, name)))
    create_dataset(group, "rest", np.ascontiguousarray(model.rest, dtype=np.float32))
    group.attrs["spacing"] = float(kdsm.spacing)
    group.attrs["settings"] = json.dumps(asdict(kdsm.settings))
    group.attrs["kdsm_info"] = json.dumps(kdsm.info)
    group.attrs["info"] = json.dumps(model.info)
    write_regressor(h5, model.regressor, KDSM_GROUP + "/regressor")


def _read_kdsm_model(reader) -> KdsmModel:
    """The mesh's arrays checked for shapes, index ranges and weights, its rest garment against V, its regressor like
    pose_model/regressor."""
    from ..kdsm.mesh import KDSM, KDSMSettings

    spacing = reader.attribute(KDSM_GROUP, "spacing")
    if not (np.ndim(spacing) == 0 and np.asarray(spacing).dtype.kind == "f" and 1e-4 <= spacing <= 1.0):
        reader.fail(f"is {shown(spacing)!r}, expected a lattice step in [1e-4, 1] m")
    settings = reader.json(KDSM_GROUP, "settings", "{}", dict)
    kdsm_info = reader.json(KDSM_GROUP, "kdsm_info", "{}", dict)
    info = reader.json(KDSM_GROUP, "info", "{}", dict)
    g = KDSM_GROUP + "/"
    fields = [("origin", np.float64, (3,), POINTS), ("dims", np.int64, (3,), (1, 100_000)),
              ("vertices", np.float64, ("Nk", 3), POINTS), ("tets", np.int32, ("Tk", 4), (0, "Nk")),
              ("class_inverse", np.float64, (12, 3, 3), (None, None)),
              ("lattice_tets", np.int32, ("Lk",), (-1, "Tk")),
              ("skin_indices", np.int32, ("Nk", N_INFLUENCES), (0, "B")),
              ("skin_weights", np.float64, ("Nk", N_INFLUENCES), (0.0, 1.0)),
              ("body_distance", np.float64, ("Nk",), (-1.0e3, 1.0e3)), ("rest", np.float32, ("V", 3), POINTS)]
    values = {}
    for name, dtype, spec, bounds in fields:
        array = reader.numeric(g + name, dtype, spec)
        if name != "class_inverse":  # NaN-free is all: classes not meshed are never read
            reader.check_range(g + name, array, bounds, dtype)
        values[name] = reader.cast(array, dtype)
    reader.where = f"field '{g}lattice_tets'"
    if int(np.prod(values["dims"])) * 12 != len(values["lattice_tets"]):
        reader.fail(f"has {len(values['lattice_tets'])} entries, expected 12 per cube of dims "
                    f"{values['dims'].tolist()}")
    reader.where = f"field '{g}skin_weights'"
    if np.abs(values["skin_weights"].sum(axis=1) - 1.0).max() > 1e-4:
        reader.fail("has rows that do not sum to 1")
    for name in ("Nk", "Tk", "Lk"):
        reader.sizes.pop(name, None)
    regressor = reader.regressor(KDSM_GROUP + "/regressor", required=True)
    rest = values.pop("rest")
    try:
        kdsm_settings = KDSMSettings(**settings)
    except TypeError as error:
        reader.where = f"attribute '{KDSM_GROUP}/settings'"
        reader.fail(f"does not hold KDSM settings ({error})")
    kdsm = KDSM(spacing=float(spacing), settings=kdsm_settings, info=kdsm_info, **values)
    return KdsmModel(kdsm=kdsm, rest=rest, regressor=regressor, info=info)


register_codec(Codec(
    "kdsm_model", KDSM_GROUP, 1, _write_kdsm_model, _read_kdsm_model,
    upgrade="python -m agentdress_ros.evaluate.kdsm_comparison --database FILE --pack PACK --out FILE"))
