"""The `kdsm` pose model trained (offline.kdsm_model) and compared with its alternatives (paper Sec. 6).

    python -m agentdress_ros.evaluate.kdsm_comparison --database data/tshirt_default.h5 \
        --pack data/tshirt_sequences.npz --frames 2000 --targets out/tshirt_kdsm_targets.npz --out out/tshirt_kdsm.h5 [--compare]

The KDSM is built at beta0 (2.5 cm lattice, a shell as thick as the farthest drape of the pack from the posed body
plus a margin); `frames` pack frames spread over the training clips (and, as for the `regressor`, the database's
beta0 drapes) are inverse-embedded (offline.kdsm_training.training_targets, about 0.2 s a frame) into plastic
displacements d; the Seed 2 regressor's machinery (offline.regressor.fit: PCA of d, an MLP from the same pose dofs to
the PCA coefficients, the same settings) learns d(theta). The KDSM and the learned model are written into a copy of the
database (`--out`, group pose_model/kdsm, engine.pose_models.KdsmModel); the engine's `kdsm` pose model
(engine.pose_models.KdsmPoseModel) predicts d, re-embeds rest + d and skins the parent tets (world positions).

`--compare` runs the paper's comparison on the same frames, the same clip folds and the same network: (a) d learned
in the KDSM against (b) the garment's rest-frame offsets learned from its own skinning (what the `regressor` learns)
and (c) offsets from the skinned body surface (the paper's baseline, Jin et al.; kdsm.surface), all scored as posed
world positions against the held-out clips' drapes (and, when given, `--beta0-pack`: the evaluation's held-out poses
draped at beta0, evaluate.beta0).
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from ..offline.kdsm_model import (KdsmModelSettings, SurfacePoser, compare, database_kdsm, fit_displacements,
                                  frame_cost, kdsm_targets, load_targets, save_targets, store_kdsm_model,
                                  targets_key, test_set_errors)
from ..offline.regressor import add_network_arguments, model_inputs, network_settings


def main(argv=None) -> int:
    import argparse

    from ..body import AnnyBody
    from ..engine.database import read_database
    from ..engine.pose_models import KdsmModel
    from ..kdsm.mesh import load_kdsm, save_kdsm
    from ..offline.sequences import load_sequence_pack

    parser = argparse.ArgumentParser(prog="python -m agentdress_ros.evaluate.kdsm_comparison", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True)
    parser.add_argument("--pack", required=True)
    parser.add_argument("--out", required=True, help="database copy to write with the pose_model/kdsm group")
    defaults = KdsmModelSettings()
    parser.add_argument("--frames", type=int, default=defaults.frames)
    parser.add_argument("--spacing", type=float, default=defaults.spacing)
    parser.add_argument("--margin", type=float, default=defaults.margin)
    parser.add_argument("--smoothing", type=int, default=defaults.smoothing,
                        help="Jacobi iterations of skin-weight diffusion in the air away from the body")
    parser.add_argument("--guess", choices=("surface", "unposed"), default=defaults.guess, help="the hybrid "
                        "inverse embedding's guess among candidate parents: Method 2's offset from the body surface "
                        "(the paper's) or the drape unposed with the garment's own skinning")
    parser.add_argument("--targets", default=None, help=".npz cache of the inverse-embedded frames (and the KDSM "
                        "beside it, <name>_mesh.npz): reused when made from the same data and settings")
    parser.add_argument("--folds", type=int, default=3, help="folds of the comparison")
    parser.add_argument("--split", choices=("clips", "frames"), default="clips", help="hold out whole clips (a "
                        "test pose's clip never seen) or frames at random (the paper's setting)")
    parser.add_argument("--compare", action="store_true", help="the comparison with rest-frame offsets (held-out "
                        "clips of the pack; with --beta0-pack also the evaluation's held-out poses at beta0)")
    parser.add_argument("--beta0-pack", default=None, help="packed drapes of the held-out poses at beta0 "
                        "(docs/eval/ground_truth_beta0.npz; a copy is used, the file is left alone)")
    parser.add_argument("--beta0-test-set", choices=("v1", "v2"), default="v1",
                        help="the held-out set whose poses --beta0-pack holds (v2: docs/eval/v2/<garment>/"
                        "ground_truth_beta0.npz, 40 poses)")
    parser.add_argument("--report", default=None, help="write the report (JSON) here too")
    add_network_arguments(parser, defaults.regressor, parts=True)  # --parts: every model of the comparison so
    args = parser.parse_args(argv)
    settings = replace(defaults, frames=args.frames, spacing=args.spacing, margin=args.margin,
                       smoothing=args.smoothing, guess=args.guess, regressor=network_settings(args))
    reg_settings = settings.regressor

    started = time.perf_counter()
    db = read_database(args.database)
    body = AnnyBody()
    shape = body.shape(db.beta0)
    pack = load_sequence_pack(args.pack)
    key = targets_key(args.database, args.pack, settings, max_offset=reg_settings.max_offset)
    mesh_path = None if args.targets is None else Path(args.targets).with_name(Path(args.targets).stem + "_mesh.npz")
    targets = None if args.targets is None else load_targets(args.targets, key)
    if targets is not None and mesh_path.is_file():
        kdsm = load_kdsm(mesh_path)
    else:
        kdsm = database_kdsm(db, body, shape, pack, settings)
        targets = kdsm_targets(kdsm, db, body, shape, pack, settings.frames, settings.regressor.max_offset,
                               progress=True, guess=settings.guess)
        if args.targets is not None:
            save_kdsm(mesh_path, kdsm)
            save_targets(args.targets, targets, key)
    target_seconds = time.perf_counter() - started
    dofs = model_inputs(db, reg_settings)
    report = {"kdsm": kdsm.info, "frames": int((targets.groups != "examples").sum()),
              "clips": int(len(np.unique(targets.groups[targets.groups != "examples"]))),
              "example_drapes": int((targets.groups == "examples").sum()), "targets_seconds": target_seconds}
    rows = np.flatnonzero(targets.groups != "examples")
    started = time.perf_counter()
    regressor = fit_displacements(targets, rows, dofs, reg_settings)
    report["fit_seconds"] = time.perf_counter() - started
    info = {"settings": json.loads(json.dumps(asdict(settings))), "pack": str(args.pack),
            "frames": report["frames"], "clips": report["clips"], "example_drapes": report["example_drapes"]}
    regressor = replace(regressor, info={**regressor.info, **info})
    model = KdsmModel(kdsm=kdsm, rest=np.asarray(db.rest, dtype=np.float32), regressor=regressor, info=info)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    store_kdsm_model(args.database, args.out, model)
    report["out"] = str(args.out)
    report["bytes"] = {"database": Path(args.database).stat().st_size, "out": Path(args.out).stat().st_size}
    if args.compare:
        surface = SurfacePoser(db, body, shape)
        report["clip_folds" if args.split == "clips" else "frame_folds"] = compare(
            kdsm, db, targets, dofs, reg_settings, args.folds, surface, args.split)
        if args.beta0_pack:
            report["test_set_beta0"] = beta0_comparison(kdsm, db, body, shape, targets, dofs, reg_settings,
                                                        args.beta0_pack, args.beta0_test_set, surface)
        from .testset import HeldOutConfig, default_clip_paths, held_out_poses

        _, _, sequence, _ = held_out_poses(body, HeldOutConfig(clips=default_clip_paths()[:1]))
        report["ms_per_frame"] = frame_cost(args.out, body, sequence)
        report["ms_per_frame_poses"] = int(len(sequence))
    text = json.dumps(report, indent=1)
    if args.report:
        Path(args.report).write_text(text + "\n")
    print(text)
    return 0


def beta0_comparison(kdsm, db, body, shape, targets, dofs, settings, pack, test_set: str = "v1",
                     surface: SurfacePoser | None = None) -> dict:
    """test_set_errors on the evaluation's held-out poses at beta0 (evaluate.beta0, from a copy of the packed
    drapes: nothing is draped when the pack holds them all) of held-out set `test_set` ("v1" or "v2")."""
    import shutil
    import tempfile

    from ..garment import make_garment
    from .beta0 import held_out_beta0
    from .testset import HeldOutConfig, default_clip_paths, held_out_v2

    garment = make_garment(db.garment, body, db.n_vertices)
    config = held_out_v2() if test_set == "v2" else HeldOutConfig(clips=default_clip_paths())
    with tempfile.TemporaryDirectory() as folder:
        copy = Path(folder) / "ground_truth_beta0.npz"
        shutil.copyfile(pack, copy)
        drapes, poses, labels = held_out_beta0(db, body, garment, config, Path(folder) / "cache", workers=0,
                                               progress=False, pack=copy)
    out = test_set_errors(kdsm, db, body, shape, targets, dofs, settings, poses, drapes, surface)
    out.pop("models")
    out["labels"] = labels
    return out


if __name__ == "__main__":
    raise SystemExit(main())
