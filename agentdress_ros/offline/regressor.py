"""Training of the `regressor` pose model (Santesteban et al. 2019, Sec. 3-4, at beta0), offline, with scikit-learn.

    agentdress lab regressor --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz

Training data: the frames of a sequence pack (offline.sequences: each frame's garment unposed to the rest frame with
beta0's bones, their Eq. 5) and, optionally, the database's own beta0 drapes (the anchors' and the extra pose-model
examples), unposed the same way. Model: PCA of the rest-frame garment (G components), an MLP from the pose's dofs
(standardised) to the PCA coefficients. Written into the database as the group pose_model/regressor
(engine.database.Regressor); the engine evaluates it with numpy (engine.pose_models.RegressorPoseModel).

Validation holds out whole clips (never frames of a clip seen in training); the test clips of ../shared/mocap are
refused outright. The command is idempotent: a database whose regressor was trained from the same data and
settings is left alone; the file is replaced atomically, so a killed run leaves the old one intact.
"""
from __future__ import annotations

import hashlib
import json
import shutil
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..engine.database import Regressor, read_database, write_model
from ..engine.pose_models import INPUT_CLIP, standardized
from .sequences import check_training_clips, load_sequence_pack

FEATURES = ("all", "sensitive")
#: Inputs whose training standard deviation is below this (rad, or beta units) are left out of the MLP: the
#: retarget holds some dofs nearly fixed at beta0 and moves them on other bodies, where the MLP would extrapolate.
MIN_INPUT_STD = 0.01


@dataclass(frozen=True)
class RegressorSettings:
    components: int = 32  # PCA components of the rest-frame garment (G)
    hidden: tuple = (256,)  # hidden layer widths of the MLP
    activation: str = "tanh"
    alpha: float = 100.0  # L2 penalty of the MLP's weights (strong: a few thousand frames of a few dozen clips)
    features: str = "sensitive"  # "all": every non-root joint rotation; "sensitive": the dofs of the sensitivity
    # distance (README "The regressor pose model": chosen by the clip-held-out validation error)
    examples: int = 100  # copies of the database's beta0 drapes (anchors and pose-model examples) among the training
    # frames: static drapes, like the held-out ground truth, and few beside thousands of dynamic frames (0: not used);
    # 100 chosen by validation on held-out halves of those drapes (README "The regressor pose model")
    max_iter: int = 300
    seed: int = 0
    max_offset: float = 0.5  # metres: frames in which a vertex strays further than this from its skinned place (in
    # the rest frame) are left out - a simulation that lost the garment (trousers off the hips in the dance clips),
    # not a drape to learn
    settled_copies: int = 0  # copies of the settled static drapes (offline.settled) among the frames, when a settled
    # pack is given (0: none given)
    dynamic: bool = True  # train on the sequence pack's dynamic frames; False: on the static drapes only (the settled
    # pack's copies and the database's beta0 drapes), the held-out set's kind of cloth
    ensemble: int = 1  # MLPs trained from seeds seed, seed+1, ... on the same data and stored merged into one wider MLP
    # whose output is their mean (exact; README "Drapes from rest along the training clips": 5 beat 1 by 2-3 %)
    mirror: bool = False  # train on the frames' left-right mirror images too (offline.mirror): twice the poses
    parts: bool = False  # one MLP and PCA per garment region (region_parts), on that region's own pose dofs, blended
    # by the region weights: a pose the training clips never combined (this arm up, that leg out) is then made of
    # parts each of which has seen its own (README "Region parts")


@dataclass(frozen=True)
class Part:
    """One region's share of a parts regressor (RegressorSettings.parts)."""

    vertices: np.ndarray  # (n,) garment vertices the part predicts
    blend: np.ndarray  # (n,) its weight at each of them; every vertex's weights over the parts sum to 1
    dofs: np.ndarray  # (I_p,) the pose dofs it sees


@dataclass
class TrainingData:
    poses: np.ndarray  # (F, B, 3) canonical rotation vectors
    positions: np.ndarray  # (F, V, 3) float64 rest-frame garment at beta0
    groups: np.ndarray  # (F,) str: clip name of each frame ("examples" for the database's drapes)

    def rows(self, index) -> "TrainingData":
        """The frames picked by `index` (indices or a boolean mask)."""
        return TrainingData(self.poses[index], self.positions[index], self.groups[index])


def pose_dofs(db, features: str) -> np.ndarray:
    """(I,) the pose dofs the MLP sees: every non-root joint's rotation, or those of the sensitivity distance."""
    from ..engine.engine import distance_metric

    n_bones = len(db.bone_names)
    if features == "all":
        return np.arange(3, 3 * n_bones, dtype=np.int32)
    if features == "sensitive":
        return distance_metric(db.region_dof, n_bones, 1e-6)[0].astype(np.int32)
    raise ValueError(f"features must be one of {FEATURES}, got {features!r}")


def region_parts(db, min_vertices: int = 20) -> tuple:
    """The Parts of a parts regressor: one per garment region holding at least min_vertices vertices (the database's
    region weights, renormalised over those regions; a vertex only in smaller regions joins the part of its nearest
    covered vertex at rest), each seeing the pose dofs its region's sensitivity names (region_dof > 0)."""
    from scipy.spatial import cKDTree

    weights = np.asarray(db.regions, dtype=np.float64)
    kept = np.flatnonzero((weights > 0).sum(axis=0) >= min_vertices)
    weights = weights[:, kept]
    covered = weights.sum(axis=1) > 0
    if not covered.all():
        rest = np.asarray(db.rest, dtype=np.float64)
        _, nearest = cKDTree(rest[covered]).query(rest[~covered])
        weights[~covered] = weights[np.flatnonzero(covered)[nearest]]
    weights /= weights.sum(axis=1, keepdims=True)
    region_dof = np.asarray(db.region_dof)
    return tuple(Part(np.flatnonzero(weights[:, j] > 0).astype(np.int64), weights[weights[:, j] > 0, j],
                      np.flatnonzero(region_dof[r] > 0).astype(np.int32)) for j, r in enumerate(kept))


def model_inputs(db, settings: RegressorSettings):
    """What fit() maps from: the pose dofs (pose_dofs), or with settings.parts the region Parts."""
    return region_parts(db) if settings.parts else pose_dofs(db, settings.features)


def example_data(db) -> TrainingData:
    """The database's beta0 drapes (anchors and extra pose-model examples) unposed to the rest frame with beta0's
    bones, as the sequence packs store their frames."""
    from ..body import AnnyBody
    from ..body.kinematics import forward_kinematics
    from ..engine.kernels import unpose
    from ..engine.pose_models import canonical_poses

    shape = AnnyBody().shape(db.beta0)
    heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
    parents = np.asarray(db.parents, dtype=np.int64)
    poses = canonical_poses(db.example_poses)
    weights = np.asarray(db.skin_weights, dtype=np.float64)
    transforms = np.empty((len(parents), 3, 4))
    positions = np.empty((len(poses), db.n_vertices, 3))
    for m, pose in enumerate(poses):
        forward_kinematics(pose, np.zeros(3), heads, parents, transforms)
        unpose(np.asarray(db.example_drapes[m], dtype=np.float64), db.skin_indices, weights, transforms, positions[m])
    return TrainingData(poses, positions, np.array(["examples"] * len(poses)))


def data_mirror(db, settings: RegressorSettings):
    """The offline.mirror.Mirror of the database's garment when settings.mirror, else None."""
    if not settings.mirror:
        return None
    from ..body import AnnyBody
    from .mirror import Mirror

    return Mirror.of(db, AnnyBody())


def example_copies(db, settings: RegressorSettings) -> TrainingData | None:
    """settings.examples copies of the database's beta0 drapes (example_data), or None for none."""
    return join(*[example_data(db)] * settings.examples) if settings.examples else None


def kept_frames(pack: dict, frames: np.ndarray, max_offset: float | None) -> np.ndarray:
    """The pack frames (indices) the `regressor` trains on: those whose garment strays at most max_offset (m) from
    its skinned place (a sequence that lost the garment is no drape to hold or learn); all with None."""
    if max_offset is None:
        return frames
    stray = np.linalg.norm(np.asarray(pack["offsets"][frames], dtype=np.float32), axis=2).max(axis=1)
    return frames[stray <= max_offset]


def pack_data(pack: dict, db, max_offset: float | None = None) -> TrainingData:
    """The frames of a loaded sequence pack (load_sequence_pack); refuses test clips and another garment. With
    max_offset (m), frames whose largest rest-frame offset exceeds it are left out (see RegressorSettings)."""
    from ..engine.pose_models import canonical_poses

    names = [str(n) for n in pack["clips"]]
    check_training_clips(names)
    if pack["rest"].shape != db.rest.shape or np.abs(pack["rest"] - db.rest).max() > 1e-5:
        raise ValueError(f"the pack's rest garment ({str(pack['garment'])}) is not the database's ({db.garment})")
    offsets = np.asarray(pack["offsets"])
    keep = kept_frames(pack, np.arange(len(offsets)), max_offset)
    positions = offsets[keep].astype(np.float64) + np.asarray(pack["rest"], dtype=np.float64)
    return TrainingData(canonical_poses(pack["rotvecs"][keep]), positions, np.array(names)[pack["clip"][keep]])


def settled_paths(settled) -> list:
    """The settled packs named by `settled`: one path, several, or None."""
    if settled is None:
        return []
    return [settled] if isinstance(settled, (str, Path)) else list(settled)


def settled_data(settled, db, max_offset: float | None) -> tuple:
    """(static drapes of one or several settled packs (offline.settled) as TrainingData, drapes left out by
    max_offset)."""
    parts, dropped = [], 0
    for path in settled_paths(settled):
        pack = load_sequence_pack(path)
        parts.append(pack_data(pack, db, max_offset))
        dropped += len(pack["offsets"]) - len(parts[-1].poses)
    return join(*parts), dropped


def join(*parts: TrainingData) -> TrainingData:
    return TrainingData(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("poses", "positions", "groups")))


def fit(data: TrainingData, dofs, settings: RegressorSettings, progress=None):
    """(Regressor, sklearn MLPRegressors) trained on `data`, from the pose dofs `dofs` (I,), or per part for a tuple
    of Parts (model_inputs). Deterministic given settings.seed (one BLAS thread)."""
    if isinstance(dofs, tuple) and dofs and isinstance(dofs[0], Part):
        members = [fit(TrainingData(data.poses, data.positions[:, part.vertices], data.groups), part.dofs,
                       replace(settings, parts=False)) for part in dofs]
        regressor = merged_parts([m[0] for m in members], dofs, data.positions.shape[1])
        return replace(regressor, info={**regressor.info, "settings": asdict(settings)}), [m[1] for m in members]
    import warnings

    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from threadpoolctl import threadpool_limits

    n_frames, n_vertices = data.positions.shape[:2]
    flat = data.positions.reshape(n_frames, -1)
    mean = flat.mean(axis=0)
    k = int(min(settings.components, n_frames - 1, flat.shape[1]))
    with threadpool_limits(limits=1):
        _, _, basis = np.linalg.svd(flat - mean, full_matrices=False)
        basis = basis[:k]
        # the sign of each component fixed (largest entry positive): the same data give the same stored basis
        basis *= np.sign(basis[np.arange(k), np.abs(basis).argmax(axis=1)])[:, None]
        coefficients = (flat - mean) @ basis.T
        # one scale for every coefficient: the MLP's squared error is then the rest-frame vertex error
        scale = np.full(k, coefficients[:, 0].std() + 1e-12)
        x = data.poses.reshape(n_frames, -1)[:, dofs]
        varies = x.std(axis=0) >= MIN_INPUT_STD  # a nearly constant input carries no information, only risk
        dofs, x = np.asarray(dofs)[varies], x[:, varies]
        x_mean, x_scale = x.mean(axis=0), x.std(axis=0)
        mlps = []
        for member in range(max(1, settings.ensemble)):
            mlp = MLPRegressor(hidden_layer_sizes=tuple(settings.hidden), activation=settings.activation,
                               solver="lbfgs", alpha=settings.alpha, max_iter=settings.max_iter,
                               max_fun=10 * settings.max_iter, random_state=settings.seed + member, tol=1e-7)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                mlp.fit(standardized(x, x_mean, x_scale), coefficients / scale)
            mlps.append(mlp)
    weights, biases = merged_layers([m.coefs_ for m in mlps], [m.intercepts_ for m in mlps])
    regressor = Regressor(
        dofs=np.asarray(dofs, dtype=np.int32), input_mean=x_mean.astype(np.float32),
        input_scale=x_scale.astype(np.float32), weights=tuple(w.astype(np.float32) for w in weights),
        biases=tuple(b.astype(np.float32) for b in biases), coefficient_mean=np.zeros(k, np.float32),
        coefficient_scale=scale.astype(np.float32), mean=mean.reshape(n_vertices, 3).astype(np.float32),
        basis=basis.reshape(k, n_vertices, 3).astype(np.float32), activation=settings.activation,
        info=json.loads(json.dumps({"settings": asdict(settings), "frames": int(n_frames),
                                    "iterations": int(max(m.n_iter_ for m in mlps))})))
    return regressor, mlps


def merged_layers(weights: list, biases: list) -> tuple[list, list]:
    """The layers of one MLP whose output is the mean of N MLPs of the same shape (weights[n][layer] (H_l, H_l+1),
    biases[n][layer] (H_l+1,)): the first layer's units side by side, hidden layers block-diagonal, the output
    layer's weights divided by N and its biases averaged. Exact, since each unit sees only its own MLP's units."""
    from scipy.linalg import block_diag

    count, last = len(weights), len(weights[0]) - 1
    merged_w, merged_b = [], []
    for layer in range(last + 1):
        ws = [w[layer] for w in weights]
        if layer == last:  # the members' outputs averaged (their inputs side by side, unless the MLP is one layer)
            merged_w.append(np.mean(ws, axis=0) if layer == 0 else np.concatenate(ws, axis=0) / count)
            merged_b.append(np.mean([b[layer] for b in biases], axis=0))
        else:  # the first layer shares the input; deeper ones see only their own member's units
            merged_w.append(np.concatenate(ws, axis=1) if layer == 0 else block_diag(*ws))
            merged_b.append(np.concatenate([b[layer] for b in biases]))
    return merged_w, merged_b


def merged_parts(members: list, parts: tuple, n_vertices: int) -> Regressor:
    """One Regressor (engine.database) exactly equal to the parts' blend sum_p blend_p(v) member_p(v): the members'
    inputs gathered into the union of their dofs, their hidden and output units side by side (the first layer
    reads only each member's own dofs, deeper layers block-diagonal), each member's basis and mean scattered onto its
    vertices times its blend weight. Stored and evaluated as any regressor; the engine's decoder finds the blocks
    again from the zeros (engine.pose_models.RegressorDecoder) and skips them."""
    from scipy.linalg import block_diag

    dofs = np.unique(np.concatenate([m.dofs for m in members]))
    input_mean, input_scale = np.zeros(len(dofs), np.float32), np.ones(len(dofs), np.float32)
    first = []
    for m in members:
        rows = np.searchsorted(dofs, m.dofs)
        input_mean[rows], input_scale[rows] = m.input_mean, m.input_scale  # the same frames: the same statistics
        w = np.zeros((len(dofs), m.weights[0].shape[1]), np.float32)
        w[rows] = m.weights[0]
        first.append(w)
    weights = [np.concatenate(first, axis=1)] + [block_diag(*[m.weights[n] for m in members]).astype(np.float32)
                                                 for n in range(1, len(members[0].weights))]
    biases = [np.concatenate([m.biases[n] for m in members]) for n in range(len(members[0].biases))]
    mean = np.zeros((n_vertices, 3), np.float32)
    basis = []
    for m, part in zip(members, parts):
        blend = part.blend.astype(np.float32)[:, None]
        mean[part.vertices] += blend * m.mean
        scattered = np.zeros((len(m.basis), n_vertices, 3), np.float32)
        scattered[:, part.vertices] = m.basis * blend[None]
        basis.append(scattered)
    info = {"parts": [{"vertices": int(len(part.vertices)), "dofs": int(len(m.dofs)), "components": int(len(m.basis))}
                      for m, part in zip(members, parts)],
            "frames": members[0].info["frames"], "iterations": max(m.info["iterations"] for m in members)}
    return Regressor(dofs=dofs.astype(np.int32), input_mean=input_mean, input_scale=input_scale,
                     weights=tuple(weights), biases=tuple(biases),
                     coefficient_mean=np.concatenate([m.coefficient_mean for m in members]),
                     coefficient_scale=np.concatenate([m.coefficient_scale for m in members]), mean=mean,
                     basis=np.concatenate(basis), activation=members[0].activation, info=info)


def coefficients_of(regressor: Regressor, positions: np.ndarray) -> np.ndarray:
    """(F, G) the PCA coefficients that best restore positions (F, V, 3) (least squares: a parts regressor's
    basis rows overlap where the parts blend; a single PCA's are orthonormal, and this is its projection)."""
    unit = regressor.basis.reshape(len(regressor.basis), -1).astype(np.float64)
    centred = positions.reshape(len(positions), -1) - regressor.mean.reshape(-1)
    return np.linalg.solve(unit @ unit.T, unit @ centred.T).T


def restored(regressor: Regressor, positions: np.ndarray) -> np.ndarray:
    """(F, V, 3) positions (F, V, 3) as the regressor's PCA holds them (coefficients_of): what G components keep."""
    basis = regressor.basis.reshape(len(regressor.basis), -1).astype(np.float64)
    flat = coefficients_of(regressor, positions) @ basis + regressor.mean.reshape(-1)
    return flat.reshape(positions.shape)


def standardized_inputs(regressor: Regressor, poses: np.ndarray) -> np.ndarray:
    """(F, I) the MLP's standardised inputs for canonical poses (F, B, 3) (or input vectors (F, D))."""
    return standardized(poses.reshape(len(poses), -1)[:, regressor.dofs], regressor.input_mean,
                        regressor.input_scale)


def mlp_outputs(regressor: Regressor, poses: np.ndarray) -> np.ndarray:
    """(F, G) the MLP's standardised outputs y (PCA coefficient = y scale + mean) for canonical poses (F, B, 3)."""
    x = standardized_inputs(regressor, poses)
    for n, (w, b) in enumerate(zip(regressor.weights, regressor.biases)):
        x = x @ w.astype(np.float64) + b
        if n < len(regressor.weights) - 1:
            x = np.maximum(x, 0.0) if regressor.activation == "relu" else np.tanh(x)
    return x


def decode(regressor: Regressor, outputs: np.ndarray) -> np.ndarray:
    """(F, V, 3) rest-frame garment (or displacement) for standardised MLP outputs (F, G)."""
    coefficients = outputs * regressor.coefficient_scale + regressor.coefficient_mean
    return regressor.mean + np.einsum("fg,gvk->fvk", coefficients, regressor.basis.astype(np.float64))


def predict(regressor: Regressor, poses: np.ndarray) -> np.ndarray:
    """(F, V, 3) rest-frame garment for canonical poses (F, B, 3), in numpy (batched; the engine's per-frame path is
    engine.pose_models.RegressorPoseModel)."""
    return decode(regressor, mlp_outputs(regressor, poses))


def vertex_error(predicted: np.ndarray, truth: np.ndarray) -> float:
    """Mean vertex distance (metres)."""
    return float(np.linalg.norm(predicted - truth, axis=-1).mean())


def clip_folds(clips, folds: int) -> list[list[str]]:
    """Clips dealt into `folds` validation sets, in name order (whole clips, never frames)."""
    clips = sorted(clips)
    return [clips[i::folds] for i in range(min(folds, len(clips)))]


def with_mirror(data: TrainingData, mirror=None) -> TrainingData:
    """data and, with an offline.mirror.Mirror, its mirror images."""
    return join(data, mirror(data)) if mirror is not None else data


def cross_validate(frames: TrainingData, extra: TrainingData | None, dofs, settings: RegressorSettings,
                   folds: int = 3, mirror=None) -> dict:
    """Mean rest-frame vertex error (m) on held-out clips: each fold trains on the other clips (and their mirror
    images, with `mirror`; plus `extra`, the database's drapes, when given) and is scored on its own clips' frames;
    also the PCA's own error on them (what any regressor with G components loses) and the mean garment's
    (predicting no pose dependence at all)."""
    errors, pca_errors, mean_errors, weights = [], [], [], []
    for held in clip_folds(np.unique(frames.groups), folds):
        test = np.isin(frames.groups, held)
        train = with_mirror(frames.rows(~test), mirror)
        if extra is not None:
            train = join(train, extra)
        regressor, _ = fit(train, dofs, settings)
        truth = frames.positions[test]
        errors.append(vertex_error(predict(regressor, frames.poses[test]), truth))
        pca_errors.append(vertex_error(restored(regressor, truth), truth))
        mean_errors.append(vertex_error(regressor.mean[None].astype(np.float64), truth))
        weights.append(int(test.sum()))
    w = np.asarray(weights, dtype=np.float64) / sum(weights)
    return {"validation_error_m": float(np.dot(errors, w)), "pca_error_m": float(np.dot(pca_errors, w)),
            "mean_garment_error_m": float(np.dot(mean_errors, w)), "folds": [list(f) for f in
                                                                                clip_folds(np.unique(frames.groups),
                                                                                           folds)],
            "fold_errors_m": [float(e) for e in errors]}


def validate_example_copies(frames: TrainingData, examples: TrainingData, dofs, settings: RegressorSettings,
                            copies, folds: int = 2) -> list[dict]:
    """How many copies of the static beta0 drapes to train on: for each count, the mean rest-frame vertex error (m)
    on held-out drapes, each fold training on every pack frame plus the other folds' drapes (dealt at random with
    settings.seed). The held-out ground truth is static drapes, the pack's frames are dynamic; this weighs them."""
    order = np.random.default_rng(settings.seed).permutation(len(examples.poses))
    parts = np.array_split(order, folds)
    rows = []
    for count in copies:
        errors = []
        for held in parts:
            train = examples.rows(np.setdiff1d(order, held))
            regressor, _ = fit(join(frames, *[train] * count) if count else frames, dofs, settings)
            errors.append(vertex_error(predict(regressor, examples.poses[held]), examples.positions[held]))
        rows.append({"copies": int(count), "validation_error_m": float(np.mean(errors)),
                     "fold_errors_m": [float(e) for e in errors]})
    return rows


def validate_settled_copies(frames: TrainingData | None, settled: TrainingData, extra: TrainingData | None, dofs,
                            settings: RegressorSettings, copies, folds: int = 3, mirror=None) -> list[dict]:
    """How many copies of a settled pack's static drapes (offline.settled) to train on: for each count, the mean
    rest-frame vertex error (m) on the static drapes of held-out clips. Each fold holds out whole clips of the
    settled pack and trains on the other clips' pack frames (none when `frames` is None: static drapes only) and
    static drapes (`count` copies) plus `extra` (the database's beta0 drapes): the held-out set's kind of cloth, in
    poses of clips no fold trained on."""
    rows = []
    for count in copies:
        errors, weights = [], []
        for held in clip_folds(np.unique(settled.groups), folds):
            test = np.isin(settled.groups, held)
            parts = [] if frames is None else [frames.rows(~np.isin(frames.groups, held))]
            parts += [settled.rows(~test)] * count
            train = with_mirror(join(*parts), mirror) if parts else None
            regressor, _ = fit(join(*[p for p in (train, extra) if p is not None]), dofs, settings)
            errors.append(vertex_error(predict(regressor, settled.poses[test]), settled.positions[test]))
            weights.append(int(test.sum()))
        rows.append({"copies": int(count), "dynamic": frames is not None,
                     "validation_error_m": float(np.average(errors, weights=weights)),
                     "fold_errors_m": [float(e) for e in errors]})
    return rows


def training_key(pack_path, db, settings: RegressorSettings, settled_path=None) -> str:
    """What the trained weights depend on: the packs' arrays, the database's drapes used, settings, sklearn."""
    import sklearn

    digest = hashlib.sha256()
    packs = [pack_path] if settings.dynamic else []
    if settings.settled_copies:
        packs += settled_paths(settled_path)
    for path in packs:
        with np.load(path) as data:
            for name in ("coefficients", "basis", "mean", "scale", "rotvecs", "clip", "clips", "rest"):
                digest.update(np.ascontiguousarray(data[name]).tobytes())
    if settings.examples:
        digest.update(np.ascontiguousarray(db.example_drapes).tobytes())
        digest.update(np.ascontiguousarray(db.example_poses).tobytes())
    inputs = {"clip": INPUT_CLIP, "min_std": MIN_INPUT_STD}  # how inputs are prepared: a change retrains
    fields = asdict(settings)
    if not settings.settled_copies:  # regressors trained before settled drapes existed keep their key
        fields.pop("settled_copies")
    if settings.dynamic:  # nor do those trained on the dynamic frames
        fields.pop("dynamic")
    if settings.ensemble == 1:  # nor single MLPs
        fields.pop("ensemble")
    if not settings.mirror:  # nor those trained without mirror images
        fields.pop("mirror")
    if not settings.parts:  # nor single regressors of the whole garment
        fields.pop("parts")
    digest.update(json.dumps({**fields, "sklearn": sklearn.__version__, "inputs": inputs}, sort_keys=True).encode())
    return digest.hexdigest()[:16]


def training_frames(pack_path, db, settings: RegressorSettings, settled_path=None) -> tuple:
    """(frames, frames left out): the pack's frames and, with settled packs (offline.settled) and
    settings.settled_copies, that many copies of its static drapes, each under its source clip's name (so a clip
    held out in validation takes its settled drapes with it). Without settings.dynamic, the static drapes only."""
    static, static_dropped = None, 0
    if settled_path and settings.settled_copies:
        static, static_dropped = settled_data(settled_path, db, settings.max_offset)
    if not settings.dynamic:
        if static is None:
            raise ValueError("training on the static drapes only needs a settled pack and settled_copies > 0")
        return join(*[static] * settings.settled_copies), static_dropped
    pack = load_sequence_pack(pack_path)
    frames = pack_data(pack, db, settings.max_offset)
    dropped = len(pack["offsets"]) - len(frames.poses)
    if static is not None:
        frames = join(frames, *[static] * settings.settled_copies)
    return frames, dropped


def store_in_database(path, write, source=None) -> Path:
    """Add a group to a database atomically: a copy of `source` (default: `path` itself) is changed by write(h5),
    read back through the validating reader, then renamed to `path` (other groups untouched)."""
    import h5py

    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    changed = path.with_name(path.name + ".changed")
    shutil.copyfile(source if source is not None else path, changed)
    with h5py.File(changed, "r+") as h5:
        write(h5)
    compact_copy(changed, partial)
    changed.unlink()
    read_database(partial)
    partial.replace(path)
    return path


def compact_copy(source, target) -> None:
    """Copy an HDF5 file object by object into a new file: a group deleted or replaced in place leaves its bytes
    behind in the file (HDF5 does not give them back), a copy holds only what is live."""
    import h5py

    with h5py.File(source, "r") as old, h5py.File(target, "w") as new:
        for key, value in old.attrs.items():
            new.attrs[key] = value
        for name in old:
            old.copy(old[name], new, name=name)


def store_regressor(path, regressor: Regressor) -> Path:
    """Write `regressor` into the database file at `path` (store_in_database)."""
    return store_in_database(path, lambda h5: write_model(h5, "regressor", regressor))


def train_database_regressor(db_path, pack_path, settings: RegressorSettings, folds: int = 3, force: bool = False,
                             progress: bool = True, settled_path=None) -> dict:
    """Cross-validate by clip, train on every training clip, and store the regressor in the database (idempotent)."""
    from tqdm import tqdm

    db = read_database(db_path)
    key = training_key(pack_path, db, settings, settled_path)
    if db.regressor is not None and db.regressor.info.get("key") == key and not force:
        return {"database": str(db_path), "skipped": "a regressor trained from the same data and settings is "
                "stored already", **db.regressor.info}
    bar = tqdm(total=folds + 2, desc="regressor", unit="fit", disable=not progress)
    frames, dropped = training_frames(pack_path, db, settings, settled_path)
    extra = example_copies(db, settings)
    mirror = data_mirror(db, settings)
    bar.update()
    dofs = model_inputs(db, settings)
    report = cross_validate(frames, extra, dofs, settings, folds, mirror)
    bar.update(folds)
    train = with_mirror(frames, mirror)
    regressor, _ = fit(join(train, extra) if extra is not None else train, dofs, settings)
    bar.update()
    bar.close()
    train_error = vertex_error(predict(regressor, frames.poses), frames.positions)
    info = {**regressor.info, "key": key, "pack": str(pack_path), "clips": sorted(set(frames.groups.tolist())),
            **({"settled_pack": ", ".join(map(str, settled_paths(settled_path)))}
               if settled_path and settings.settled_copies else {}),
            "pack_frames": int(len(frames.poses)), "frames_left_out": int(dropped),
            "example_drapes": int(len(db.example_poses)) if extra is not None else 0,
            "training_error_m": train_error, **report}
    regressor = replace(regressor, info=info)
    before = Path(db_path).stat().st_size
    store_regressor(db_path, regressor)
    return {"database": str(db_path), "bytes_before": before, "bytes_after": Path(db_path).stat().st_size, **info}


def add_network_arguments(parser, defaults: RegressorSettings | None = None, parts: bool = False) -> None:
    """The command-line options of RegressorSettings' network and training data (read back by network_settings);
    with parts, --parts too (for commands whose inputs are the pose alone: model_inputs)."""
    defaults = defaults or RegressorSettings()
    parser.add_argument("--components", type=int, default=defaults.components)
    parser.add_argument("--hidden", type=int, nargs="+", default=list(defaults.hidden))
    parser.add_argument("--activation", choices=("tanh", "relu"), default=defaults.activation)
    parser.add_argument("--alpha", type=float, default=defaults.alpha)
    parser.add_argument("--features", choices=FEATURES, default=defaults.features)
    parser.add_argument("--examples", type=int, default=defaults.examples, help="copies of the database's beta0 "
                        "drapes among the training frames (0: the pack's frames only)")
    parser.add_argument("--max-iter", type=int, default=defaults.max_iter)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--ensemble", type=int, default=defaults.ensemble, help="MLPs from consecutive seeds, "
                        "stored as one whose output is their mean")
    parser.add_argument("--max-offset", type=float, default=defaults.max_offset, help="leave out frames whose garment "
                        "strays further than this (m) from its skinned place: a simulation that lost it")
    if parts:
        parser.add_argument("--parts", action="store_true", help="one MLP and PCA per garment region, on that "
                            "region's own pose dofs, blended by the region weights (region_parts)")


def network_settings(args) -> RegressorSettings:
    """RegressorSettings from the options of add_network_arguments."""
    return RegressorSettings(components=args.components, hidden=tuple(args.hidden), activation=args.activation,
                             alpha=args.alpha, features=args.features, examples=args.examples,
                             max_iter=args.max_iter, seed=args.seed, max_offset=args.max_offset,
                             ensemble=args.ensemble, parts=getattr(args, "parts", False))


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="agentdress lab regressor", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True, help="database file to write the regressor into")
    parser.add_argument("--pack", required=True, help="sequence pack of the training clips (agentdress lab sequences)")
    parser.add_argument("--settled", nargs="+", default=None, help="packs of static drapes settled from the training "
                        "frames (agentdress lab settle), trained on beside the pack's frames")
    parser.add_argument("--settled-copies", type=int, default=1, help="copies of the settled drapes (with --settled)")
    parser.add_argument("--static-only", action="store_true", help="train on the static drapes only (the --settled "
                        "copies and the database's beta0 drapes), not on the pack's dynamic frames")
    parser.add_argument("--mirror", action="store_true", help="train on the frames' left-right mirror images too "
                        "(not the database's drapes')")
    add_network_arguments(parser, parts=True)
    parser.add_argument("--folds", type=int, default=3, help="validation folds of whole clips")
    parser.add_argument("--force", action="store_true", help="retrain even if the stored regressor is up to date")
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--validate-examples", type=int, nargs="+", metavar="COPIES", help="only validate these "
                        "counts of copies of the beta0 drapes on held-out halves of them (JSON), train nothing")
    parser.add_argument("--validate-settled", type=int, nargs="+", metavar="COPIES", help="only validate these "
                        "counts of copies of the --settled drapes on the drapes of held-out clips (JSON), train "
                        "nothing")
    args = parser.parse_args(argv)
    settings = replace(network_settings(args), settled_copies=args.settled_copies if args.settled else 0,
                       dynamic=not args.static_only, mirror=args.mirror)
    if args.validate_examples:
        db = read_database(args.database)
        frames, _ = training_frames(args.pack, db, settings, args.settled)
        rows = validate_example_copies(frames, example_data(db), model_inputs(db, settings), settings,
                                       args.validate_examples)
        json.dump({"database": args.database, "pack": args.pack, "copies": rows,
                   **({"settled": args.settled, "settled_copies": settings.settled_copies} if args.settled else {})},
                  sys.stdout, indent=1)
        print()
        return 0
    if args.validate_settled:
        if not args.settled:
            parser.error("--validate-settled needs --settled")
        db = read_database(args.database)
        frames = training_frames(args.pack, db, replace(settings, settled_copies=0))[0] if settings.dynamic else None
        settled, _ = settled_data(args.settled, db, settings.max_offset)
        rows = validate_settled_copies(frames, settled, example_copies(db, settings), model_inputs(db, settings),
                                       settings, args.validate_settled, args.folds, data_mirror(db, settings))
        json.dump({"database": args.database, "pack": args.pack, "settled": args.settled,
                   "settled_drapes": int(len(settled.poses)), "copies": rows}, sys.stdout, indent=1)
        print()
        return 0
    report = train_database_regressor(args.database, args.pack, settings, folds=args.folds, force=args.force,
                                      progress=not args.quiet, settled_path=args.settled)
    json.dump(report, sys.stdout, indent=1)
    print()
    return 0
