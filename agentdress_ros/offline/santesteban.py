"""Training of the garment model of Santesteban et al. 2019 (engine.santesteban), offline, with scikit-learn.

    agentdress lab santesteban --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz

Data: the build's drapes (`<database>.drapes.npz`: every anchor pose on the 17 training shapes) and the dense beta0
sequence pack. Every drape is unposed to the rest frame of its own shape (their Eq. 5, with that shape's skeleton):
U(beta, theta).
- Fit regressor R_G(beta) (their Sec. 4.1): the fit displacement of each training shape, the mean over the anchor
  poses of U(beta, theta_s) - T (the build has no drape in the rest pose itself: the pose-averaged garment stands
  for it), an MLP of 20 tanh units from the 6 phenotypes to its PCA coefficients, as in the paper (more strongly
  regularised: see SantestebanSettings).
- Wrinkle regressor R_L(beta, theta) (their Sec. 4.2, the static variant): U - T - R_G(beta) of the anchors on all
  17 shapes (repeated `anchor_copies` times: a few hundred beside thousands of frames) and of the pack's frames at
  beta0, an MLP from the pose's sensitivity dofs and the phenotypes to the PCA coefficients (the `regressor`'s
  machinery, offline.regressor.fit).
Deterministic given the settings' seed; written into the database atomically (offline.regressor.store_in_database).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..engine.database import read_database, write_model
from ..engine.santesteban import SantestebanArrays
from .regressor import RegressorSettings, TrainingData, fit, pack_data, pose_dofs, predict, store_in_database

N_PHENOTYPES = 6


@dataclass(frozen=True)
class SantestebanSettings:
    fit: RegressorSettings = field(default_factory=lambda: RegressorSettings(
        components=16, hidden=(20,), alpha=1.0, max_iter=2000, examples=0))
    # alpha: the 17 training shapes vary one phenotype at a time, and a weakly regularised R_G extrapolates badly to
    # shapes that vary several (README "Santesteban et al.'s system": 1.0 measured best of {1e-4, 0.1, 1, 10} on
    # the held-out shapes; leave-one-shape-out on the training shapes prefers 1e-4, which cannot see this)
    wrinkles: RegressorSettings = field(default_factory=lambda: RegressorSettings(examples=0))
    anchor_copies: int = 5
    pack_frames: int = 0  # pack frames used (spread over the clips); 0: all


def inputs(poses: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """(F, D + 6) regressor inputs: canonical poses (F, B, 3) flattened, then the phenotypes (F, 6)."""
    return np.concatenate([poses.reshape(len(poses), -1), np.asarray(betas, dtype=np.float64)], axis=1)


def phenotype_dofs(db) -> np.ndarray:
    """(6,) the indices of the phenotypes in an input vector of `inputs`."""
    n_pose = 3 * len(db.parents)
    return np.arange(n_pose, n_pose + N_PHENOTYPES, dtype=np.int32)


def input_dofs(db, features: str) -> np.ndarray:
    """(I,) what an MLP of pose and shape reads from an input vector of `inputs`: the pose dofs of `features`
    (offline.regressor.pose_dofs), then the 6 phenotypes."""
    return np.concatenate([pose_dofs(db, features), phenotype_dofs(db)]).astype(np.int32)


def unposed_anchor_drapes(db, body, drapes_path) -> np.ndarray:
    """(A, S, V, 3) each anchor's drape on each training shape (from the build's drape pack), unposed to that
    shape's rest frame."""
    from ..body.kinematics import forward_kinematics
    from ..engine.kernels import unpose
    from ..engine.pose_models import canonical_poses
    poses = canonical_poses(db.anchor_poses)
    weights = np.asarray(db.skin_weights, dtype=np.float64)
    parents = np.asarray(db.parents, dtype=np.int64)
    transforms = np.empty((len(parents), 3, 4))
    out = np.empty((len(poses), len(db.training_betas), db.n_vertices, 3))
    drapes = _packed_drapes(drapes_path)
    missing = [f"anchor_{a:04d}_{k:02d}" for a in range(len(poses)) for k in range(len(db.training_betas))
               if f"anchor_{a:04d}_{k:02d}" not in drapes]
    if missing:
        raise ValueError(f"{drapes_path}: {len(missing)} of the build's anchor drapes are missing ({missing[0]}, ...)")
    for k, beta in enumerate(db.training_betas):
        heads = np.ascontiguousarray(body.shape(beta).heads, dtype=np.float64)
        for a, pose in enumerate(poses):
            forward_kinematics(pose, np.zeros(3), heads, parents, transforms)
            unpose(drapes[f"anchor_{a:04d}_{k:02d}"], db.skin_indices, weights, transforms, out[a, k])
    return out


def _packed_drapes(path) -> dict:
    """{job key: (V, 3) float64} of a build's drape pack (DrapeStore.pack's file), the anchors' only."""
    from .jobs import read_drape_pack

    return {key: vertices for key, (vertices, _) in read_drape_pack(path)["drapes"].items()
            if key.startswith("anchor_")}


def train(db, body, drapes_path, pack: dict, settings: SantestebanSettings, progress: bool = True):
    """(SantestebanArrays, report dict) trained from the build's drapes and the sequence pack."""
    from tqdm import tqdm

    from ..engine.pose_models import canonical_poses
    from ..offline.kdsm_training import spread_frames

    bar = tqdm(total=3, desc="santesteban", unit="step", disable=not progress)
    unposed = unposed_anchor_drapes(db, body, drapes_path)  # (A, S, V, 3)
    rest = np.asarray(db.rest, dtype=np.float64)
    betas = np.asarray(db.training_betas, dtype=np.float64)
    n_anchors, n_shapes = unposed.shape[:2]
    bar.update()
    shape_inputs = phenotype_dofs(db)
    fit_target = unposed.mean(axis=0) - rest  # (S, V, 3)
    fit_inputs = inputs(np.zeros((n_shapes, len(db.parents), 3)), betas)
    fit_regressor, _ = fit(TrainingData(fit_inputs, fit_target, np.array(["shapes"] * n_shapes)), shape_inputs,
                           settings.fit)
    fit_predicted = predict(fit_regressor, fit_inputs)  # what R_L is added to at run time
    bar.update()
    anchor_poses = canonical_poses(db.anchor_poses)
    anchor_x = inputs(np.repeat(anchor_poses, n_shapes, axis=0), np.tile(betas, (n_anchors, 1)))
    anchor_y = (unposed - rest - fit_predicted[None]).reshape(n_anchors * n_shapes, -1, 3)
    frames = pack_data(pack, db, settings.wrinkles.max_offset)
    if settings.pack_frames:
        keep = spread_frames({"rotvecs": frames.poses}, settings.pack_frames)
        frames = frames.rows(keep)
    beta0_fit = predict(fit_regressor, inputs(np.zeros((1, len(db.parents), 3)), np.asarray(db.beta0)[None]))[0]
    pack_x = inputs(frames.poses, np.repeat(np.asarray(db.beta0, dtype=np.float64)[None], len(frames.poses), 0))
    pack_y = frames.positions - rest - beta0_fit
    x = np.concatenate([pack_x] + [anchor_x] * settings.anchor_copies)
    y = np.concatenate([pack_y] + [anchor_y] * settings.anchor_copies)
    wrinkles, _ = fit(TrainingData(x, y, np.array(["all"] * len(x))), input_dofs(db, settings.wrinkles.features),
                      settings.wrinkles)
    bar.update()
    bar.close()
    anchor_error = np.linalg.norm(predict(wrinkles, anchor_x) + fit_predicted[np.tile(np.arange(n_shapes), n_anchors)]
                                  - (unposed - rest).reshape(n_anchors * n_shapes, -1, 3), axis=2).mean()
    report = {"anchors": int(n_anchors), "shapes": int(n_shapes), "pack_frames": int(len(frames.poses)),
              "pack_clips": int(len(np.unique(frames.groups))),
              "fit_training_error_m": float(np.linalg.norm(fit_predicted - fit_target, axis=2).mean()),
              "anchor_training_error_m": float(anchor_error),
              "settings": json.loads(json.dumps(asdict(settings)))}
    return SantestebanArrays(fit=fit_regressor, wrinkles=wrinkles, info=report), report


def main(argv=None) -> int:
    from ..body import AnnyBody
    from .sequences import load_sequence_pack

    parser = argparse.ArgumentParser(prog="agentdress lab santesteban", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True)
    parser.add_argument("--pack", required=True, help="the garment's beta0 sequence pack (data/<garment>_sequences.npz)")
    parser.add_argument("--drapes", default=None, help="the build's drapes (default: <database stem>.drapes.npz)")
    parser.add_argument("--pack-frames", type=int, default=0, help="pack frames used, spread over the clips (0: all)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    path = Path(args.database)
    drapes = Path(args.drapes) if args.drapes else path.with_name(path.stem + ".drapes.npz")
    defaults = SantestebanSettings()
    settings = replace(defaults, pack_frames=args.pack_frames, fit=replace(defaults.fit, seed=args.seed),
                       wrinkles=replace(defaults.wrinkles, seed=args.seed))
    db = read_database(path)
    arrays, report = train(db, AnnyBody(), drapes, load_sequence_pack(args.pack), settings)
    store_in_database(path, lambda h5: write_model(h5, "santesteban", arrays))
    print(json.dumps({"database": str(path), "drapes": str(drapes), **report}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
