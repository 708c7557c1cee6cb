"""`agentdress bench pose-models`: the engine's cost per frame with each pose model, on a real database.

    agentdress bench pose-models --database out/tshirt_kdsm.h5 --pose-models examples regressor kdsm
    agentdress bench pose-models --pose-models examples regressor,fold=false regressor,fold=false,projection=8

One core (BLAS limited to one thread), at a training shape of the database (the shape models interpolate between them all), along a held-out CMU clip (its poses and root motion,
the way the node receives them). For each pose model: the synthesis (Engine.synthesize) and the pose model alone
(pose_model.evaluate), each the best of `passes` per-pass medians. The passes are interleaved (pass r of every pose
model before pass r + 1 of any), so load from other processes falls on every row alike; the ratios to the first
pose model are the numbers to compare across machines. An entry may carry engine knobs after the pose model's name,
comma-separated `field=value` (EngineConfig), so that a configuration such as the node default is timed as a whole.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_CLIP = Path(__file__).resolve().parents[2].parent / "shared" / "mocap" / "cmu" / "02_08.bvh"


def _median_ms(function, frames: int) -> float:
    samples = np.empty(frames)
    for i in range(frames):
        start = time.perf_counter()
        function(i)
        samples[i] = time.perf_counter() - start
    return float(np.median(samples) * 1e3)


def entry_config(entry: str) -> dict:
    """EngineConfig fields of a pose-model entry: "name" or "name,field=value,..." (values as JSON where they
    parse)."""
    from ..offline.shape_residual import engine_config

    name, *knobs = entry.split(",")
    return {"pose_model": name, **engine_config(knobs)}


def bench_pose_models(database, pose_models=("examples", "regressor"), clip=DEFAULT_CLIP, frames: int = 300,
                      passes: int = 5, shape_index: int = 3) -> dict:
    from threadpoolctl import threadpool_limits

    from ..body import AnnyBody
    from ..engine import Engine, EngineConfig
    from ..engine.database import read_database
    from ..motion.retarget import load_cmu_motion

    body = AnnyBody()
    db = read_database(database)
    shape = body.shape(db.beta0)
    motion = load_cmu_motion(str(clip), shape.heads, shape.tails)
    poses, roots = motion.rotvecs[:frames], motion.root_translation[:frames]
    beta = np.asarray(db.training_betas[min(shape_index, len(db.training_betas) - 1)], dtype=np.float64)
    with threadpool_limits(limits=1):
        engines = {name: Engine(db, body, EngineConfig(**entry_config(name))) for name in pose_models}
        for engine in engines.values():
            engine.set_shape(beta)
            engine.synthesize(poses[0], roots[0], frame=0)  # JIT and buffers before timing
        synthesis = {name: [] for name in engines}
        alone = {name: [] for name in engines}
        for _ in range(passes):
            for name, engine in engines.items():
                engine.reset()
                synthesis[name].append(_median_ms(lambda i: engine.synthesize(poses[i], roots[i], frame=i), len(poses)))
                model = engine.pose_model
                alone[name].append(_median_ms(lambda i: model.evaluate(poses[i], roots[i], i), len(poses)))
    first = pose_models[0]
    rows = {name: {"synthesis_ms": round(min(synthesis[name]), 4), "pose_model_ms": round(min(alone[name]), 4),
                   f"synthesis_vs_{first}": round(min(synthesis[name]) / min(synthesis[first]), 2)}
            for name in engines}
    return {"benchmark": "pose-models", "database": str(database), "clip": Path(clip).stem, "frames": int(len(poses)),
            "passes": passes, "threads": 1, "garment_vertices": int(db.n_vertices), "shape": beta.round(4).tolist(),
            "pose_models": rows, "goal_ms": {"regressor": 0.3, "kdsm": 0.3}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress bench pose-models", description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--pose-models", nargs="+", default=["examples", "regressor"],
                        help="pose models to time (the first is the reference of the ratios), each optionally with "
                             "engine knobs: regressor,fold=false,projection=8")
    parser.add_argument("--clip", default=str(DEFAULT_CLIP), help="a held-out CMU clip (.bvh)")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--passes", type=int, default=5)
    args = parser.parse_args(argv)
    with contextlib.redirect_stdout(sys.stderr):  # warp's and numba's chatter: stdout is the JSON alone
        report = bench_pose_models(args.database, tuple(args.pose_models), args.clip, args.frames, args.passes)
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
