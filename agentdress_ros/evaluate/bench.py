"""Benchmarks printing JSON. Timings are medians and 99th percentiles of repeated runs on one core."""
from __future__ import annotations

import json
import time

import numpy as np
from threadpoolctl import threadpool_limits


def _timings_ms(function, repeats: int, warmup: int = 3) -> dict:
    for _ in range(warmup):
        function()
    samples = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        function()
        samples[i] = time.perf_counter() - start
    return {"p50": float(np.median(samples) * 1e3), "p99": float(np.percentile(samples, 99) * 1e3)}


def bench_body(garment_names=("tshirt",), garment_vertices=None, repeats=200, seed=0) -> dict:
    """Shape change (body + garment refit) and posing (FK + LBS of body and garments) times in ms."""
    from ..body import AnnyBody
    from ..garment import make_garment
    from ..garment.dressing import Dressing

    with threadpool_limits(limits=1):
        start = time.perf_counter()
        body = AnnyBody()
        load_s = time.perf_counter() - start
        garments = [make_garment(name, body, garment_vertices) for name in garment_names]
        dressing = Dressing(body, garments)
        rng = np.random.default_rng(seed)
        shapes = rng.uniform(0.0, 1.0, size=(16, 6))
        poses = rng.normal(scale=0.4, size=(16, body.n_bones, 3))
        counter = iter(range(10**9))
        shape_ms = _timings_ms(lambda: dressing.set_shape(shapes[next(counter) % 16]), max(20, repeats // 5))
        pose_ms = _timings_ms(lambda: dressing.pose(poses[next(counter) % 16], np.zeros(3)), repeats)
    return {
        "benchmark": "body",
        "threads": 1,
        "body_load_s": round(load_s, 3),
        "shape_change_ms": shape_ms,
        "pose_body_and_garments_ms": pose_ms,
        "body_vertices": int(len(dressing.body_rest)),
        "garments": {g.name: int(g.n_vertices) for g in garments},
        "goals": {"shape_change_ms_p50": 20.0, "pose_ms_p50": 2.0},
    }


def print_json(result: dict, out=None) -> None:
    """Print a JSON report; with `out`, write the same text to that file too."""
    text = json.dumps(result, indent=2)
    if out:
        from pathlib import Path

        Path(out).write_text(text + "\n")
    print(text)
