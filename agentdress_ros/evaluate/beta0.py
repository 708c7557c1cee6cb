"""Ground truth at the reference shape beta0 for the held-out poses: what a pose model f(beta0, theta) alone is
measured against (the held-out set's own shapes are all away from beta0).

    drapes = held_out_beta0(db, body, garment, HeldOutConfig(clips=...), cache, pack="docs/eval/ground_truth_beta0.npz")

One newton drape per held-out pose at beta0, draped from the skinned garment like the first shape of the held-out
set (`evaluate.testset`), one file per drape under `<cache>/beta0` (resumable); `pack` is read first when present
and rewritten after, so an evaluation reruns without draping.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def held_out_beta0(db, body, garment, config, cache, workers: int = 2, progress: bool = True, pack=None):
    """(P, V, 3) newton drapes at beta0 of the held-out poses of `config` (testset.HeldOutConfig)."""
    from ..offline.builder import run_jobs
    from ..offline.jobs import DrapeJob, DrapeStore
    from .testset import _check_held_out, held_out_poses

    _check_held_out(db, config.clips)
    poses, labels, _, _ = held_out_poses(body, config)
    beta0 = np.asarray(db.beta0, dtype=np.float64)
    key = json.dumps({"garment": db.garment, "vertices": db.n_vertices, "poses": labels, "drape": config.drape,
                      "beta0": np.round(beta0, 9).tolist()}, sort_keys=True, default=str)
    store = DrapeStore(Path(cache) / "beta0")
    stamp = store.folder / "key.json"
    if stamp.is_file() and stamp.read_text() != key:
        raise ValueError(f"{store.folder}: these drapes belong to another set of poses; delete the folder")
    stamp.write_text(key)
    if pack is not None and Path(pack).is_file():
        store.unpack(pack, key)
    jobs = [DrapeJob("beta0", p, 0, pose, beta0, db.garment, db.n_vertices, dict(config.drape))
            for p, pose in enumerate(poses)]
    run_jobs(jobs, store, workers=workers, progress=progress)
    if pack is not None:
        Path(pack).parent.mkdir(parents=True, exist_ok=True)
        store.pack(pack, key)
    return np.stack([store.load(job.key) for job in jobs]), poses, labels


def main(argv=None) -> int:
    import argparse

    from ..body import AnnyBody
    from ..engine import read_database
    from ..garment import make_garment
    from .testset import HeldOutConfig, default_cache, default_clip_paths, held_out_v2

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--pack", required=True)
    parser.add_argument("--cache", default=None)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--test-set", choices=("v1", "v2"), default="v1", help="whose held-out poses to drape")
    args = parser.parse_args(argv)
    db = read_database(args.database)
    body = AnnyBody()
    garment = make_garment(db.garment, body, db.n_vertices)
    cache = args.cache or default_cache(args.database, args.test_set)
    config = held_out_v2() if args.test_set == "v2" else HeldOutConfig(clips=default_clip_paths())
    drapes, _, labels = held_out_beta0(db, body, garment, config, cache, workers=args.workers, pack=args.pack)
    print(json.dumps({"pack": args.pack, "drapes": len(drapes), "poses": labels}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
