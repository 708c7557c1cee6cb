"""The `kdsm` pose model's training: a learned d(theta) in the KDSM (paper Sec. 6), offline, with scikit-learn.

The KDSM is built at beta0 (2.5 cm lattice, a shell as thick as the farthest drape of the pack from the posed body
plus a margin); `frames` pack frames spread over the training clips (and, as for the `regressor`, the database's
beta0 drapes) are inverse-embedded (kdsm_training.training_targets, about 0.2 s a frame) into plastic displacements
d; the Seed 2 regressor's machinery (offline.regressor.fit: PCA of d, an MLP from the same pose dofs to the PCA
coefficients, the same settings) learns d(theta). The KDSM and the learned model are written into a copy of the
database (group pose_model/kdsm, engine.pose_models.KdsmModel); the engine's `kdsm` pose model
(engine.pose_models.KdsmPoseModel) predicts d, re-embeds rest + d and skins the parent tets (world positions).

`compare` is the paper's comparison on the same frames, the same clip folds and the same network: (a) d learned in
the KDSM against (b) the garment's rest-frame offsets learned from its own skinning (what the `regressor` learns)
and (c) offsets from the skinned body surface (the paper's baseline, Jin et al.; kdsm.surface), all scored as posed
world positions against the held-out clips' drapes. The command that trains, stores and compares (also on the
evaluation's held-out poses) is evaluate.kdsm_comparison.
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..body.kinematics import forward_kinematics, linear_blend_skinning
from ..kdsm.embedding import KdsmPoser
from ..kdsm.mesh import KDSM, KDSMSettings, build_kdsm
from .kdsm_training import (GarmentFrames, TargetSettings, drape_clearance, pack_frames, spread_frames,
                            training_targets)
from .regressor import RegressorSettings, TrainingData, clip_folds, fit, kept_frames, pack_data, predict, restored


@dataclass(frozen=True)
class KdsmModelSettings:
    frames: int = 2000  # pack frames spread evenly over the training clips (inverse embedding: ~0.2 s each)
    spacing: float = 0.025  # m: the KDSM's lattice step
    margin: float = 0.02  # m: shell thickness = the pack's farthest drape vertex from the posed body + margin
    smoothing: int = 0  # KDSMSettings.smoothing: weight diffusion in the air away from the body
    clearance_frames: int = 0  # frames measured for the clearance (0: every frame of the pack)
    guess: str = "surface"  # training.TargetSettings.guess: the hybrid's guess among candidate parents
    regressor: RegressorSettings = field(default_factory=RegressorSettings)  # PCA + MLP, as the `regressor`


def database_kdsm(db, body, shape, pack, settings: KdsmModelSettings) -> KDSM:
    """The database garment's KDSM at beta0, thick enough to hold every drape of the pack (plus the margin)."""
    measured = kept_frames(pack, spread_frames(pack, settings.clearance_frames or len(pack["rotvecs"])),
                           settings.regressor.max_offset)
    clearance = drape_clearance(body, shape, pack_frames(pack, db, body, shape, measured))
    thickness = float(clearance.max() + settings.margin)
    kdsm = build_kdsm(body, shape, KDSMSettings(spacing=settings.spacing, thickness=thickness, reach=thickness,
                                                smoothing=settings.smoothing), crop_points=db.rest)
    kdsm.info.update({"clearance_max_m": float(clearance.max()), "clearance_frames": int(len(measured))})
    return kdsm


def example_frames(db, body, shape) -> GarmentFrames:
    """The database's beta0 drapes (anchors' and pose-model examples') as GarmentFrames (frame index -1)."""
    from ..engine.kernels import unpose
    from ..engine.pose_models import canonical_poses

    poses = canonical_poses(db.example_poses)
    heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
    skin_i = np.ascontiguousarray(db.skin_indices, dtype=np.int32)
    skin_w = np.ascontiguousarray(db.skin_weights, dtype=np.float64)
    transforms = np.empty((len(poses), body.n_bones, 3, 4))
    drapes = np.asarray(db.example_drapes, dtype=np.float64)
    unposed = np.empty_like(drapes)
    for m, pose in enumerate(poses):
        forward_kinematics(pose, np.zeros(3), heads, body.parents, transforms[m])
        unpose(drapes[m], skin_i, skin_w, transforms[m], unposed[m])
    return GarmentFrames(np.asarray(db.rest, dtype=np.float64), np.asarray(db.faces), skin_i, skin_w, transforms,
                         drapes, unposed, np.full(len(poses), -1, dtype=np.int64))


@dataclass
class KdsmTargets:
    """Training data of both models for the same F frames: pose, clip, posed drape, bone transforms, KDSM target d
    and rest-frame garment (the `regressor`'s target). Examples (the database's beta0 drapes) have clip "examples"."""

    poses: np.ndarray  # (F, B, 3) canonical rotation vectors
    groups: np.ndarray  # (F,) str clip names
    frames: np.ndarray  # (F,) pack frame index (-1: a database drape)
    transforms: np.ndarray  # (F, B, 3, 4) beta0 bone transforms, root translation zero
    drapes: np.ndarray  # (F, V, 3) posed ground truth
    displacements: np.ndarray  # (F, V, 3) d of the hybrid inverse embedding
    status: np.ndarray  # (F, V) int8 (kdsm.inverse status)
    unposed: np.ndarray  # (F, V, 3) the rest-frame garment (the drape unposed with the garment's weights)

    def subset(self, rows) -> "KdsmTargets":
        return KdsmTargets(**{k: v[rows] for k, v in self.__dict__.items()})


def kdsm_targets(kdsm: KDSM, db, body, shape, pack, count: int, max_offset: float | None = 0.5,
                 examples: bool = True, progress: bool = False, guess: str = "surface") -> KdsmTargets:
    """Inverse-embed `count` pack frames spread over its clips (left out: frames the `regressor` leaves out, whose
    garment strays more than max_offset from its skinned place) and, with `examples`, the database's beta0 drapes."""
    from ..engine.pose_models import canonical_poses

    frames = kept_frames(pack, spread_frames(pack, count), max_offset)
    pack_data(pack, db)  # refuses test clips and another garment
    parts = [(pack_frames(pack, db, body, shape, frames),
              np.array([str(n) for n in pack["clips"]])[pack["clip"][frames]],
              canonical_poses(pack["rotvecs"][frames]))]
    if examples:
        parts.append((example_frames(db, body, shape), np.array(["examples"] * len(db.example_poses)),
                      canonical_poses(db.example_poses)))
    out = []
    for data, groups, poses in parts:
        d, status = training_targets(kdsm, body, shape, data, TargetSettings(guess=guess), progress=progress)
        out.append(KdsmTargets(poses, groups, data.frames, data.transforms, data.drapes, d, status, data.unposed))
    return KdsmTargets(**{k: np.concatenate([getattr(t, k) for t in out]) for k in out[0].__dict__})


def save_targets(path, targets: KdsmTargets, key: dict) -> None:
    np.savez_compressed(path, key=json.dumps(key, sort_keys=True), **targets.__dict__)


def load_targets(path, key: dict) -> KdsmTargets | None:
    """Targets saved by save_targets for the same key (None when absent or made otherwise)."""
    if not Path(path).is_file():
        return None
    with np.load(path) as data:
        if str(data["key"]) != json.dumps(key, sort_keys=True):
            return None
        return KdsmTargets(**{k: data[k] for k in KdsmTargets.__dataclass_fields__})


def training_rows(targets: KdsmTargets, rows, copies: int) -> np.ndarray:
    """Indices of `rows` (pack frames) plus `copies` copies of the database's drapes (group "examples")."""
    examples = np.flatnonzero(targets.groups == "examples")
    return np.concatenate([np.asarray(rows, dtype=np.int64)] + [examples] * copies)


def fit_on_rows(targets: KdsmTargets, values, rows, dofs, settings: RegressorSettings):
    """The regressor (engine.database.Regressor, offline.regressor.fit) of per-frame values (F, V, 3) of `targets`
    - d, the rest-frame garment or the body-surface offsets - trained on `rows` (and the database's drapes
    settings.examples times): every model of the comparison learns through this one."""
    train = training_rows(targets, rows, settings.examples)
    return fit(TrainingData(targets.poses[train], values[train], targets.groups[train]), dofs, settings)[0]


def fit_displacements(targets: KdsmTargets, rows, dofs, settings: RegressorSettings):
    """The `kdsm` pose model's regressor: d(theta) on `rows` of targets (fit_on_rows)."""
    return fit_on_rows(targets, targets.displacements, rows, dofs, settings)


def fit_offsets(targets: KdsmTargets, rows, dofs, settings: RegressorSettings):
    """The same regressor trained on the rest-frame garment of the same rows (what the `regressor` learns)."""
    return fit_on_rows(targets, targets.unposed, rows, dofs, settings)


class SurfacePoser:
    """The body-surface parameterisation (kdsm.surface) of the database garment on the beta0 body: each vertex bound
    at rest to its closest body point among its own regions (as Method 2 of the inverse embedding)."""

    def __init__(self, db, body, shape):
        from ..kdsm.inverse import region_groups
        from ..kdsm.surface import anchor_garment

        self.body, self.shape, self.faces = body, shape, body.body_faces
        face_groups, point_groups = region_groups(body, db.skin_indices, db.skin_weights)
        self.anchors = anchor_garment(np.asarray(db.rest, dtype=np.float64), shape.vertices, self.faces,
                                      face_groups, point_groups)
        self._targets = None  # (targets, origin, frames, offsets) of the last targets seen

    def frames(self, transforms):
        """Surface points (F, V, 3) and frames (F, V, 3, 3) of the anchors at bone transforms (F, B, 3, 4)."""
        from ..kdsm.surface import surface_frames

        parts = [surface_frames(self.anchors, self.body.posed_vertices(self.shape, np.ascontiguousarray(t)),
                                self.faces) for t in transforms]
        return np.stack([p[0] for p in parts]), np.stack([p[1] for p in parts])

    def of_targets(self, targets: KdsmTargets):
        """(origin, frames, offsets (F, V, 3) of the drapes) at every frame of `targets`: computed once for the
        comparison and the test set, which both train on the same targets."""
        from ..kdsm.surface import to_surface

        if self._targets is None or self._targets[0] is not targets:
            origin, frames = self.frames(targets.transforms)
            self._targets = (targets, origin, frames, to_surface(targets.drapes, origin, frames))
        return self._targets[1:]


def posed_kdsm(kdsm: KDSM, rest, skin_indices, skin_weights, transforms, displacements):
    """(F, V, 3) world positions of displacements (F, V, 3) through the KDSM at poses `transforms` (F, B, 3, 4), and
    the count of vertex-frames skinned outside the shell."""
    poser = KdsmPoser(kdsm, rest, skin_indices, skin_weights)
    out = np.empty(displacements.shape)
    outside = 0
    for n in range(len(displacements)):
        out[n] = poser.pose(transforms[n], displacements[n])
        outside += poser.fallback_count
    return out, outside


def posed_skinned(rest_frame, skin_indices, skin_weights, transforms):
    """(F, V, 3) rest-frame garments (F, V, 3) skinned with the garment's weights at `transforms` (F, B, 3, 4)."""
    skin_i = np.ascontiguousarray(skin_indices, dtype=np.int32)
    skin_w = np.ascontiguousarray(skin_weights, dtype=np.float64)
    out = np.empty(rest_frame.shape)
    for n in range(len(rest_frame)):
        linear_blend_skinning(np.ascontiguousarray(rest_frame[n], dtype=np.float64), skin_i, skin_w,
                              np.ascontiguousarray(transforms[n], dtype=np.float64), out[n])
    return out


def _errors(posed, drapes) -> np.ndarray:
    """(F,) mean vertex distance per frame (m)."""
    return np.linalg.norm(posed - drapes, axis=2).mean(axis=1)


def held_out_folds(groups, folds: int, split: str = "clips", seed: int = 0) -> list[np.ndarray]:
    """Row indices (of groups (F,) clip names) of each fold's held-out set: whole clips (offline.regressor.clip_folds,
    our default: a test pose's clip is never seen) or, with split="frames", frames dealt at random (the paper's
    setting: neighbouring frames of the same clip sit in training)."""
    if split == "frames":
        order = np.random.default_rng(seed).permutation(len(groups))
        return [np.sort(order[i::folds]) for i in range(folds)]
    return [np.flatnonzero(np.isin(groups, held)) for held in clip_folds(np.unique(groups), folds)]


def compare(kdsm: KDSM, db, targets: KdsmTargets, dofs, settings: RegressorSettings, folds: int = 3,
            surface: SurfacePoser | None = None, split: str = "clips") -> dict:
    """The paper's comparison on held-out data: per fold (whole clips, or random frames: held_out_folds) the models
    are trained on the other folds' frames (plus the database's drapes, settings.examples times) with the same network
    and scored on the held-out frames as posed world positions (mean vertex distance, cm). Also: each target
    through its own map (the KDSM's inverse embedding error; the skinned offsets are exact), each target projected on
    its model's PCA, no pose dependence (the rest garment skinned; the fixed embedding, d = 0). With `surface`, the
    paper's own baseline as well: the same regressor on offsets from the skinned body surface (kdsm.surface)."""
    from ..kdsm.surface import from_surface

    rest = np.asarray(db.rest, dtype=np.float64)
    skin_i, skin_w = db.skin_indices, db.skin_weights
    pack_rows = np.flatnonzero(targets.groups != "examples")
    names = ("kdsm", "offsets", "kdsm_targets", "kdsm_pca", "offsets_pca", "rest_skinned", "fixed_embedding")
    if surface is not None:
        names += ("surface", "surface_targets", "surface_pca")
        origin, frames, surface_x = surface.of_targets(targets)
    errors = {n: [] for n in names}
    outside = {"kdsm": 0, "kdsm_targets": 0}
    fold_rows, seconds = [], {"fit_kdsm": 0.0, "fit_offsets": 0.0, "fit_surface": 0.0}
    for held in held_out_folds(targets.groups[pack_rows], folds, split):
        test = pack_rows[held]
        train = np.delete(pack_rows, held)
        t = targets.subset(test)
        started = time.perf_counter()
        reg_d = fit_displacements(targets, train, dofs, settings)
        seconds["fit_kdsm"] += time.perf_counter() - started
        started = time.perf_counter()
        reg_x = fit_offsets(targets, train, dofs, settings)
        seconds["fit_offsets"] += time.perf_counter() - started
        d = predict(reg_d, t.poses)
        posed, out = posed_kdsm(kdsm, rest, skin_i, skin_w, t.transforms, d)
        errors["kdsm"].append(_errors(posed, t.drapes))
        outside["kdsm"] += out
        errors["offsets"].append(_errors(posed_skinned(predict(reg_x, t.poses), skin_i, skin_w, t.transforms),
                                         t.drapes))
        posed, out = posed_kdsm(kdsm, rest, skin_i, skin_w, t.transforms, t.displacements)
        errors["kdsm_targets"].append(_errors(posed, t.drapes))
        outside["kdsm_targets"] += out
        posed, _ = posed_kdsm(kdsm, rest, skin_i, skin_w, t.transforms, restored(reg_d, t.displacements))
        errors["kdsm_pca"].append(_errors(posed, t.drapes))
        errors["offsets_pca"].append(_errors(posed_skinned(restored(reg_x, t.unposed), skin_i, skin_w,
                                                           t.transforms), t.drapes))
        errors["rest_skinned"].append(_errors(posed_skinned(np.broadcast_to(rest, t.unposed.shape), skin_i, skin_w,
                                                            t.transforms), t.drapes))
        posed, _ = posed_kdsm(kdsm, rest, skin_i, skin_w, t.transforms, np.zeros_like(t.displacements))
        errors["fixed_embedding"].append(_errors(posed, t.drapes))
        if surface is not None:
            started = time.perf_counter()
            reg_s = fit_on_rows(targets, surface_x, train, dofs, settings)
            seconds["fit_surface"] += time.perf_counter() - started
            for name, offsets in (("surface", predict(reg_s, t.poses)), ("surface_targets", surface_x[test]),
                                  ("surface_pca", restored(reg_s, surface_x[test]))):
                errors[name].append(_errors(from_surface(offsets, origin[test], frames[test]), t.drapes))
        fold_rows.append({"clips": sorted(set(targets.groups[test])), "frames": int(len(test)),
                          **{f"{n}_cm": float(errors[n][-1].mean() * 100) for n in names
                             if n in ("kdsm", "offsets", "surface")}})
    total = sum(len(e) for e in errors["kdsm"])
    report = {n: float(np.concatenate(errors[n]).mean() * 100) for n in names}
    per_frame = {n: np.concatenate(errors[n]) for n in ("kdsm", "offsets", "surface") if n in names}
    better = {"kdsm_better_frames": float((per_frame["kdsm"] < per_frame["offsets"]).mean())}
    if surface is not None:
        better["kdsm_better_than_surface_frames"] = float((per_frame["kdsm"] < per_frame["surface"]).mean())
    return {"error_cm": report, "frames": int(total), "vertices": int(len(rest)), "folds": fold_rows,
            "outside_shell_fraction": {k: v / (total * len(rest)) for k, v in outside.items()}, **better,
            "fit_seconds": seconds, "settings": asdict(settings), "dofs": int(len(dofs)),
            "training_rows_per_fold": "other folds' pack frames + examples x database drapes"}


def test_set_errors(kdsm: KDSM, db, body, shape, targets: KdsmTargets, dofs, settings: RegressorSettings, poses,
                    drapes, surface: SurfacePoser | None = None) -> dict:
    """Both models (with `surface`, the body-surface offsets too) trained on every pack frame of `targets` (plus the
    drapes) and scored on held-out poses (P, B, 3) draped at beta0 (P, V, 3) (evaluate.beta0): mean vertex distance
    (cm), all and per pose."""
    from ..engine.pose_models import canonical_poses
    from ..kdsm.surface import from_surface

    rows = np.flatnonzero(targets.groups != "examples")
    poses = canonical_poses(poses)
    heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
    transforms = np.empty((len(poses), body.n_bones, 3, 4))
    for n, pose in enumerate(poses):
        forward_kinematics(pose, np.zeros(3), heads, body.parents, transforms[n])
    rest = np.asarray(db.rest, dtype=np.float64)
    drapes = np.asarray(drapes, dtype=np.float64)
    reg_d = fit_displacements(targets, rows, dofs, settings)
    reg_x = fit_offsets(targets, rows, dofs, settings)
    posed_d, outside = posed_kdsm(kdsm, rest, db.skin_indices, db.skin_weights, transforms, predict(reg_d, poses))
    posed_x = posed_skinned(predict(reg_x, poses), db.skin_indices, db.skin_weights, transforms)
    rest_skinned = posed_skinned(np.broadcast_to(rest, drapes.shape), db.skin_indices, db.skin_weights, transforms)
    fixed, _ = posed_kdsm(kdsm, rest, db.skin_indices, db.skin_weights, transforms, np.zeros_like(drapes))
    rows_out = {"kdsm": _errors(posed_d, drapes), "offsets": _errors(posed_x, drapes),
                "rest_skinned": _errors(rest_skinned, drapes), "fixed_embedding": _errors(fixed, drapes)}
    models = (reg_d, reg_x)
    if surface is not None:
        reg_s = fit_on_rows(targets, surface.of_targets(targets)[2], rows, dofs, settings)
        origin, frames = surface.frames(transforms)
        rows_out["surface"] = _errors(from_surface(predict(reg_s, poses), origin, frames), drapes)
        models += (reg_s,)
    return {"poses": int(len(poses)), "error_cm": {k: float(v.mean() * 100) for k, v in rows_out.items()},
            "per_pose_cm": {k: (v * 100).round(3).tolist() for k, v in rows_out.items()},
            "outside_shell_fraction": outside / drapes.shape[0] / drapes.shape[1], "models": models}


def frame_cost(db_path, body, poses, repeats: int = 5) -> dict:
    """ms per frame of the engine with each learned pose model alone (no shape model), one thread: median over
    `repeats` interleaved passes of `poses` (P, B, 3)."""
    from ..engine import Engine, EngineConfig
    from ..engine.database import read_database

    db = read_database(db_path)
    engines = {name: Engine(db, body, EngineConfig(pose_model=name, shape_model=False))
               for name in ("kdsm", "regressor", "lbs") if name != "regressor" or db.regressor is not None}
    times = {name: [] for name in engines}
    zero = np.zeros(3)
    for engine in engines.values():
        engine.synthesize(poses[0], zero)  # compiled, warm
    for _ in range(repeats):
        for name, engine in engines.items():
            started = time.perf_counter()
            for pose in poses:
                engine.synthesize(pose, zero)
            times[name].append((time.perf_counter() - started) / len(poses) * 1e3)
    return {name: float(np.median(t)) for name, t in times.items()}


def store_kdsm_model(source, path, model) -> Path:
    """A copy of the database `source` with the KDSM group (engine.pose_models.KdsmModel) written into it at `path`
    (atomically: offline.regressor.store_in_database)."""
    from .regressor import store_in_database
    from ..engine.database import write_model

    return store_in_database(path, lambda h5: write_model(h5, "kdsm_model", model), source=source)


def targets_key(db_path, pack_path, settings: KdsmModelSettings, examples: bool = True,
                max_offset: float | None = 0.5) -> dict:
    return {"database": str(db_path), "pack": str(pack_path), "frames": settings.frames, "spacing": settings.spacing,
            "margin": settings.margin, "examples": examples, "max_offset": max_offset,
            **({"smoothing": settings.smoothing} if settings.smoothing else {}),
            **({"guess": settings.guess} if settings.guess != "surface" else {})}
