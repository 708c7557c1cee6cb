"""Training of the shape residual (EngineConfig.shape_residual), offline, with scikit-learn.

    agentdress lab shape-residual --database data/trousers_default.h5 --shaped out/shaped/trousers_shaped.npz \
        --engine pose_model=regressor fold=false

Why: synthesis carries each anchor's shape model to a pose through the sensitivity-weighted blend of the nearest
anchors, and each shape model is fitted on 17 shapes that vary one phenotype at a time. At a shape that varies
several at once, in a pose between the anchors, it misses what neither captures; with a perfect pose model the
trousers' held-out error stays at the shape term's 1.46 cm (README "What the trousers' pose model costs").

Data: a shaped pack (`agentdress lab settle --start shaped`): the training clips' poses draped at random shapes, each
stored unposed with its own shape's bones. Target of each drape: the drape minus the engine's synthesis at the same
shape and pose (the configuration `--engine`, the one the residual will correct), both unposed with that shape's
bones - the frame in which the synthesis kernel adds the blended shape delta (Eq. 4), so adding the target to the
delta moves the output onto the drape. Model: the regressor's PCA + MLP (offline.regressor.fit), its inputs the pose's
sensitivity dofs followed by the 6 phenotypes (offline.santesteban.inputs, input_dofs). Validation holds out whole clips.
Deterministic given the seed; stored atomically as shape_model/residual, with the engine configuration in its info.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..engine.database import read_database, write_model
from .regressor import (RegressorSettings, TrainingData, add_network_arguments, cross_validate, fit, network_settings,
                        predict, store_in_database, vertex_error)
from .santesteban import input_dofs, inputs

#: The network's defaults: a few hundred drapes, so a small PCA and a strong penalty (README "A learned shape
#: residual, measured").
DEFAULTS = RegressorSettings(components=32, hidden=(256,), alpha=10.0, examples=0, ensemble=5)


def engine_config(pairs) -> dict:
    """EngineConfig fields from "key=value" strings (values as JSON where they parse, else text)."""
    config = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        try:
            config[key] = json.loads(value)
        except json.JSONDecodeError:
            config[key] = value
    return config


def residual_data(db, body, pack: dict, config: dict, progress: bool = True) -> TrainingData:
    """The shaped pack's drapes as training data: inputs (F, D + 6), the rest-frame residual (F, V, 3) of the
    engine's synthesis (EngineConfig fields `config`, without a shape residual) at each drape's shape and pose,
    groups the clip names."""
    from tqdm import tqdm

    from ..engine import Engine, EngineConfig
    from ..engine.pose_models import canonical_poses
    from .sequences import check_training_clips
    from .settled import shaped_offsets

    if "betas" not in pack:
        raise ValueError("the pack has no per-drape shapes: make it with `agentdress lab settle --start shaped`")
    names = [str(n) for n in pack["clips"]]
    check_training_clips(names)
    engine = Engine(db, body, EngineConfig(**{**config, "shape_residual": False}))
    poses = canonical_poses(pack["rotvecs"])
    betas = np.asarray(pack["betas"], dtype=np.float64)
    synthesis = []
    for beta, pose in tqdm(zip(betas, poses), total=len(poses), desc="synthesis at the shaped drapes", unit="drape",
                           disable=not progress):
        engine.set_shape(beta)
        engine.reset()
        synthesis.append(np.array(engine.synthesize(pose), dtype=np.float64))
    # stored the way the pack stores its drapes, so the difference is the rest-frame residual
    unposed = np.reshape(shaped_offsets(body, db, betas, poses, synthesis), (len(poses), -1, 3))
    residuals = np.asarray(pack["offsets"], dtype=np.float64) - unposed
    return TrainingData(inputs(poses, betas), residuals, np.array(names)[pack["clip"]])


def train(db, body, pack: dict, config: dict, settings: RegressorSettings = DEFAULTS, folds: int = 3,
          progress: bool = True):
    """(Regressor, report): cross-validated by clip, then trained on every drape of the shaped pack."""
    data = residual_data(db, body, pack, config, progress)
    dofs = input_dofs(db, settings.features)
    report = cross_validate(data, None, dofs, settings, folds)
    report["residual_before_m"] = vertex_error(np.zeros_like(data.positions), data.positions)
    residual, _ = fit(data, dofs, settings)
    info = {**residual.info, "engine": config, "drapes": int(len(data.poses)),
            "clips": sorted(set(data.groups.tolist())),
            "training_error_m": vertex_error(predict(residual, data.poses), data.positions), **report}
    return replace(residual, info=info), info


def main(argv=None) -> int:
    from ..body import AnnyBody
    from .sequences import load_sequence_pack

    parser = argparse.ArgumentParser(prog="agentdress lab shape-residual", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True, help="database file to write shape_model/residual into")
    parser.add_argument("--shaped", required=True, help="shaped pack (agentdress lab settle --start shaped)")
    parser.add_argument("--engine", nargs="*", default=[], help="EngineConfig fields key=value of the synthesis the "
                        "residual corrects (the node's configuration of this garment)")
    parser.add_argument("--folds", type=int, default=3, help="clip folds of the validation")
    parser.add_argument("--validate-only", action="store_true", help="print the validation, store nothing")
    add_network_arguments(parser, DEFAULTS)
    args = parser.parse_args(argv)
    settings = network_settings(args)
    db = read_database(args.database)
    residual, info = train(db, AnnyBody(), load_sequence_pack(args.shaped), engine_config(args.engine), settings,
                           args.folds)
    info = {**info, "shaped_pack": str(args.shaped)}  # the settings are in it (offline.regressor.fit)
    if not args.validate_only:
        before = Path(args.database).stat().st_size
        residual = replace(residual, info=info)
        store_in_database(args.database, lambda h5: write_model(h5, "shape_residual", residual))
        info = {**info, "bytes_before": before, "bytes_after": Path(args.database).stat().st_size}
    print(json.dumps({"database": str(args.database), **info}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
