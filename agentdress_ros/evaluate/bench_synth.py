"""Benchmark of the runtime synthesis against plain LBS of the same garment, in the same run, on one core.

`agentdress bench synth --vertices V --anchors N --neighbors K` prints bench_synth(...) as JSON. The database is
synthetic (engine.synthetic) but of the real sizes; the motion is a smooth random walk through human joint ranges,
so neighbour selection and decay behave as on mocap. Frames alternate synthesis and LBS, so machine noise hits both.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from threadpoolctl import threadpool_limits


def _motion(rng, frames: int, bone_names, step: float = 0.03) -> np.ndarray:
    """(frames, B, 3) smooth random walk inside the synthetic joint limits (reflected at the limits)."""
    from ..engine.synthetic import joint_limits

    limits = joint_limits(bone_names)[:, None]
    pose = rng.uniform(-0.5, 0.5, size=(len(bone_names), 3)) * limits
    velocity = np.zeros_like(pose)
    out = np.empty((frames, len(bone_names), 3))
    for f in range(frames):
        velocity = 0.9 * velocity + step * rng.normal(size=pose.shape) * limits
        pose = pose + velocity
        over = np.abs(pose) > limits
        pose = np.where(over, np.sign(pose) * limits, pose)
        velocity = np.where(over, -velocity, velocity)
        out[f] = pose
    return out


def _stats(samples) -> dict:
    samples = np.asarray(samples) * 1e3
    return {"p50": round(float(np.median(samples)), 4), "p99": round(float(np.percentile(samples, 99)), 4)}


def bench_synth(vertices: int = 12000, anchors: int = 150, neighbors: int = 5, frames: int = 600, seed: int = 0,
                components: int = 5, pose_model: str = "lbs", penetration: bool = True, decay: bool = True,
                shape_changes: int = 5, compare_float64: bool = True, cold_start: bool = False) -> dict:
    """Per-frame times (ms, p50/p99) of the full synthesis and of plain LBS (FK + skinning) of the same garment.

    Also: shape-change time, the float32-vs-float64 output difference over the motion, and (cold_start=True:
    writes the database to a temporary HDF5 file) the cold start of a fresh process (import + JIT + load + first
    frame). Returns a JSON-able dict.
    """
    from ..body import AnnyBody
    from ..body.kinematics import forward_kinematics, linear_blend_skinning
    from ..engine.config import EngineConfig
    from ..engine.engine import Engine
    from ..engine.synthetic import make_synthetic_database

    with threadpool_limits(limits=1):
        body = AnnyBody()
        start = time.perf_counter()
        db = make_synthetic_database(vertices, anchors, components, seed=seed, body=body)
        database_s = time.perf_counter() - start
        config = EngineConfig(pose_model=pose_model, neighbors=neighbors, penetration=penetration, decay=decay)
        start = time.perf_counter()
        engine = Engine(db, body, config)
        engine_s = time.perf_counter() - start
        rng = np.random.default_rng(seed)
        motion = _motion(rng, frames, db.bone_names)
        root = np.zeros(3)

        # plain LBS of the same garment: forward kinematics into a reused buffer, then the body's LBS kernel
        rest = np.ascontiguousarray(db.rest, dtype=np.float32)
        skin_i = np.ascontiguousarray(db.skin_indices, dtype=np.int32)
        skin_w = np.ascontiguousarray(db.skin_weights, dtype=np.float32)
        heads = np.ascontiguousarray(engine.reference.heads)
        transforms64 = np.empty((body.n_bones, 3, 4))
        transforms32 = np.empty((body.n_bones, 3, 4), dtype=np.float32)
        lbs_out = np.empty_like(rest)

        def plain_lbs(pose):
            forward_kinematics(pose, root, heads, engine.parents, transforms64)
            transforms32[:] = transforms64
            linear_blend_skinning(rest, skin_i, skin_w, transforms32, lbs_out)

        for pose in motion[:20]:  # warm up (JIT is cached, but caches and branch predictors are not)
            engine.synthesize(pose, root)
            plain_lbs(pose)
        engine.reset()
        synth_t, lbs_t, kernel_t = [], [], []
        clock = time.perf_counter
        for pose in motion:
            t0 = clock()
            engine.synthesize(pose, root)
            t1 = clock()
            plain_lbs(pose)
            t2 = clock()
            linear_blend_skinning(rest, skin_i, skin_w, transforms32, lbs_out)
            t3 = clock()
            synth_t.append(t1 - t0)
            lbs_t.append(t2 - t1)
            kernel_t.append(t3 - t2)
        synth, lbs = _stats(synth_t), _stats(lbs_t)

        shape_rng = np.random.default_rng(seed + 1)
        shape_t = []
        for _ in range(shape_changes):
            beta = db.beta0 + shape_rng.uniform(-0.3, 0.3, size=len(db.beta0))
            shape_t.append(engine.set_shape(beta).seconds)

        precision = None
        if compare_float64:
            engines = [Engine(db, body, EngineConfig(pose_model=pose_model, neighbors=neighbors,
                                                     penetration=penetration, decay=decay, dtype=d))
                       for d in ("float32", "float64")]
            worst, mean = 0.0, []
            for pose in motion[: min(100, frames)]:
                a, b = (e.synthesize(pose, root).astype(np.float64) for e in engines)
                diff = np.linalg.norm(a - b, axis=1)
                worst = max(worst, float(diff.max()))
                mean.append(float(diff.mean()))
            precision = {"float32_vs_float64_max_mm": round(worst * 1e3, 6),
                         "float32_vs_float64_mean_mm": round(float(np.mean(mean)) * 1e3, 6)}

        cold = None
        if cold_start:
            cold = _cold_start(db, config)

    return {
        "benchmark": "synth",
        "threads": 1,
        "vertices": int(db.n_vertices),
        "anchors": int(db.n_anchors),
        "neighbors": int(engine.neighbors),
        "components": int(db.n_components),
        "pose_model": pose_model,
        "penetration": penetration,
        "decay": decay,
        "frames": int(frames),
        "synth_ms": synth,
        "lbs_ms": lbs,
        "lbs_kernel_only_ms": _stats(kernel_t),
        "ratio_p50": round(synth["p50"] / lbs["p50"], 3),
        "shape_change_ms": _stats(shape_t),
        "database_build_s": round(database_s, 3),
        "engine_init_s": round(engine_s, 3),
        "precision": precision,
        "cold_start": cold,
        "goals": {"synth_ms_p50": 3.0, "ratio_p50": 4.0, "shape_change_ms_p50_at_5k_vertices_150_anchors": 100.0},
    }


def _cold_start(db, config) -> dict:
    """Seconds of a fresh interpreter: import, AnnyBody, read the database, build the engine, first frame."""
    from ..engine.database import write_database

    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "synthetic.h5")
        write_database(path, db)
        script = (
            "import time, json; t0 = time.perf_counter()\n"
            "from agentdress_ros.engine.engine import load_engine\n"
            "from agentdress_ros.engine.config import EngineConfig\n"
            "import numpy as np\n"
            "t1 = time.perf_counter()\n"
            f"engine = load_engine({path!r}, EngineConfig(**{_config_kwargs(config)!r}))\n"
            "t2 = time.perf_counter()\n"
            "engine.synthesize(np.zeros((engine.n_bones, 3)))\n"
            "t3 = time.perf_counter()\n"
            "print(json.dumps({'import_s': t1 - t0, 'load_s': t2 - t1, 'first_frame_s': t3 - t2, 'total_s': t3 - t0}))\n"
        )
        result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                                env={**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})
        size = os.path.getsize(path)
    out = {k: round(v, 3) for k, v in json.loads(result.stdout.strip().splitlines()[-1]).items()}
    out["database_mb"] = round(size / 2**20, 1)
    return out


def _config_kwargs(config) -> dict:
    return {k: getattr(config, k) for k in ("pose_model", "neighbors", "penetration", "decay")}


if __name__ == "__main__":
    print(json.dumps(bench_synth(*map(int, sys.argv[1:4])), indent=2))
