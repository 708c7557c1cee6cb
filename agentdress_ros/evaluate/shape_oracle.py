"""How much of a synthesis row's error its pose model makes, measured without the ground truth's path noise.

The "perfect pose model" replaces the row's own garment at beta0 by the held-out pose's drape at beta0:
    oracle(beta) = drape(beta0) + synthesis(beta) - synthesis(beta0).
`evaluate.pose_model_share` scores it against the v2 drapes, which were draped from rest (first shape) or
warm-started from that shape's drape, independently of the beta0 drape the oracle starts from: the oracle then
pays the path noise between two independent drapes (about 1 cm, `agentdress lab floor`) on top of the shape term,
and the figure overstates the shape term. Here it is also scored against the drapes of the floor's database path,
which are warm-started from that very beta0 drape the way the database's shape variants are: what remains is the
shape term's own error.

Reads only committed packs (the v2 ground truth, its beta0 drapes, the floor's database-path drapes); simulates
nothing.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def shape_term(database, folder, engine: dict) -> dict:
    """Mean errors (cm) over the floor's database-path cases of one garment, for the EngineConfig `engine`:
    synthesis and oracle against the from-rest v2 drapes, and against the database-path drapes."""
    from ..body import AnnyBody
    from ..offline.jobs import read_drape_pack
    from ..engine import Engine, EngineConfig, read_database
    from .evaluate import synthesize_poses
    from .score_v3 import interval
    from .testset import held_out_poses, held_out_shapes, held_out_v2

    db = read_database(database)
    body = AnnyBody()
    config = held_out_v2()
    poses, _, _, _ = held_out_poses(body, config)
    betas, _ = held_out_shapes(db, config)
    folder = Path(folder)
    v2 = read_drape_pack(folder / "ground_truth_drapes.npz")["drapes"]
    beta0 = read_drape_pack(folder / "ground_truth_beta0.npz")["drapes"]
    database_path = read_drape_pack(folder / "floor_database_drapes.npz")["drapes"]
    engine_model = Engine(db, body, EngineConfig(**engine))
    rows = {"synthesis vs v2": [], "oracle vs v2": [], "synthesis vs database path": [],
            "oracle vs database path": []}
    kept = 0
    for key, (target, stats) in sorted(database_path.items()):
        if not key.startswith("floor_") or not stats.get("converged", False):
            continue
        p, k = int(key[6:10]), int(key[11:13])
        reference = v2[f"test_{p:04d}_{k:02d}"][0]
        at_beta0 = synthesize_poses(engine_model, np.asarray(db.beta0), poses[p][None])[0]
        synthesis = synthesize_poses(engine_model, betas[k], poses[p][None])[0]
        oracle = beta0[f"beta0_{p:04d}_00"][0] + synthesis - at_beta0
        for name, candidate, truth in (("synthesis vs v2", synthesis, reference), ("oracle vs v2", oracle, reference),
                                       ("synthesis vs database path", synthesis, target),
                                       ("oracle vs database path", oracle, target)):
            rows[name].append(float(np.linalg.norm(candidate - truth, axis=1).mean() * 100.0))
        kept += 1
    return {"database": str(database), "engine": engine, "cases": kept,
            "rows": {name: {"mean_cm": float(np.mean(v)), "ci_cm": interval(v)} for name, v in rows.items()}}


def main(argv=None) -> int:
    import argparse

    from ..ros.params import default_engine
    from .bench import print_json

    parser = argparse.ArgumentParser(prog="agentdress lab shape-oracle", description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--folder", default="docs/eval/v2/tshirt", help="the v2 evaluation folder holding "
                        "ground_truth_drapes.npz, ground_truth_beta0.npz and floor_database_drapes.npz")
    parser.add_argument("--out", default=None, help="write the report (JSON) here too")
    args = parser.parse_args(argv)
    from ..engine import read_database

    print_json(shape_term(args.database, args.folder, default_engine(read_database(args.database).garment)), args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
