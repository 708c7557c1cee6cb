"""`agentdress bench cold-start`: seconds from a fresh interpreter to the first synthesised frame on a real database.

Each repeat starts a new Python process (one BLAS thread, numba's cache warm after the first) that imports the
engine, loads the body and the database with the node's default engine knobs for the garment (ros.params
PARAMETERS["engine"]), and synthesises one frame. Reported (JSON): per repeat import_s, load_s (body + database +
engine), first_frame_s, total_s (inside the process), process_s (interpreter start to exit, measured outside) and
cpu_s (the process' user + system CPU seconds: what it costs whatever else shares the core); the median of each over
the repeats after the first (the first may compile numba kernels into the cache).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["bench_cold_start", "main"]

_SCRIPT = """\
import json, sys, time
t0 = time.perf_counter()
import numpy as np
from agentdress_ros.body import AnnyBody
from agentdress_ros.engine.config import EngineConfig
from agentdress_ros.engine.engine import load_engine
t1 = time.perf_counter()
engine = load_engine(sys.argv[1], EngineConfig(**json.loads(sys.argv[2])), AnnyBody())
t2 = time.perf_counter()
engine.synthesize(np.zeros((engine.n_bones, 3)))
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "load_s": t2 - t1, "first_frame_s": t3 - t2, "total_s": t3 - t0}))
"""


def node_engine_knobs(garment: str) -> dict:
    """The node's default EngineConfig overrides for one garment, as keyword arguments."""
    from ..ros.params import default_engine

    return default_engine(garment)


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def bench_cold_start(database: str, garment: str, repeats: int = 5) -> dict:
    if repeats < 2:
        raise ValueError(f"repeats must be at least 2 (the first run may fill numba's cache), got {repeats}")
    if not Path(database).is_file():
        raise FileNotFoundError(f"database {database!r} not found")
    knobs = node_engine_knobs(garment)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    runs = []
    for _ in range(repeats):
        start, cpu = time.perf_counter(), _children_cpu_s()
        out = subprocess.run([sys.executable, "-c", _SCRIPT, database, json.dumps(knobs)], capture_output=True,
                             text=True, check=True, env=env)
        run = json.loads(out.stdout.strip().splitlines()[-1])
        run["process_s"] = time.perf_counter() - start
        run["cpu_s"] = _children_cpu_s() - cpu
        runs.append({k: round(v, 3) for k, v in run.items()})
    warm = runs[1:]
    return {"benchmark": "cold-start", "database": database, "garment": garment, "engine": knobs,
            "database_mb": round(os.path.getsize(database) / 2**20, 2), "repeats": repeats, "runs": runs,
            "median": {k: round(statistics.median(r[k] for r in warm), 3) for k in warm[0]}, "goal_s": 5.0}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress bench cold-start", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--garment", default="tshirt", help="whose node default engine knobs to use")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    print(json.dumps(bench_cold_start(args.database, args.garment, args.repeats), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
