"""`agentdress lab floor`: how far apart two equally valid newton drapes of the same held-out case lie.

A static drape is one equilibrium among several (a fold goes left or right, a sleeve settles a little higher), and
which one the simulation reaches depends on the path it took. The held-out set's drapes took one path (for v2, a
30-frame ramp from rest); this command drapes a subset of the same cases along another valid path (by default a
60-frame ramp) and compares the two vertex for vertex. Their distance is the ground truth's own spread: a model that
reproduced one of them exactly would still score about that against the other, so it marks the error below which
no deterministic model can be told apart on this test set.

With `--path database` the other path is the one the database's shape variants take: every shape of each chosen
pose is warm-started from the pose's held-out drape at beta0 (`evaluate.beta0`, simulated when its pack is missing)
with the build's own warm settings, where the held-out set drapes the first shape from rest and warm-starts the
others from it. Their distance is the spread a model trained on the database's kind of drape meets at other shapes.

The reference drapes come from the test set's pack or cache (nothing is simulated for them); the other path's
drapes are packed into `<out>/floor_drapes.npz` (`floor_database_drapes.npz`), so a rerun simulates nothing.
Resumable like a build.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["ground_truth_spread", "main"]


#: The other paths a held-out case can be draped along (see the module docstring), with their default overrides.
DEFAULT_ALTERNATIVE = {"ramp": {"ramp_frames": 60}, "database": {}}
PATHS = tuple(DEFAULT_ALTERNATIVE)


def ground_truth_spread(db_path, cache, pack, out, alternative: dict, every: int = 2, workers: int = 0,
                        progress: bool = True, clips=None, quick: bool = False, path: str = "ramp",
                        beta0_pack=None) -> dict:
    """Compare v2 held-out drapes, every `every`-th pose, with the same cases draped along another path (the test
    set as `agentdress eval --test-set v2` makes it, with `clips` and `quick` as there). path "ramp": the first shape
    draped from rest under the `alternative` DrapeSettings overrides; "database": every shape warm-started from the
    pose's drape at beta0 (read from `beta0_pack` when present) with the database build's warm settings plus
    `alternative`. Returns per-case and overall distances (cm) and writes floor.json (floor_database.json)."""
    if path not in PATHS:
        raise ValueError(f"path must be one of {', '.join(PATHS)}, got {path!r}")
    from ..body import AnnyBody, visible_body
    from ..offline.builder import run_jobs
    from ..offline.jobs import DrapeJob, DrapeStore
    from ..engine import read_database
    from ..garment import make_garment
    from ..garment.inside import BodyInside
    from .beta0 import held_out_beta0
    from .evaluate import held_out_config
    from .testset import held_out_poses, held_out_shapes, static_jobs, test_set_key

    db = read_database(db_path)
    body = AnnyBody()
    config = held_out_config("v2", clips, quick)
    poses, labels, _, _ = held_out_poses(body, config)
    betas, _ = held_out_shapes(db, config)
    reference = DrapeStore(Path(cache) / "drapes")
    if pack is not None and Path(pack).is_file():
        reference.unpack(pack, test_set_key(db, config, betas))
    picked = set(range(len(poses))[::every])
    chosen = [job for job in static_jobs(db, config, poses, betas)
              if job.index in picked and (path == "database" or job.shape_index == 0)]
    missing = [job.key for job in chosen if not reference.has(job.key)]
    if missing or not chosen:
        raise FileNotFoundError(f"{cache}: the held-out drapes {missing} are missing; run `agentdress eval "
                                f"--test-set v2` on {db_path} first (or give its --ground-truth pack)")
    suffix = "" if path == "ramp" else f"_{path}"
    store = DrapeStore(Path(cache) / f"floor{suffix}")
    if path == "ramp":
        settings = {**config.drape, **alternative}
        jobs = [DrapeJob("floor", job.index, 0, job.pose, job.beta, db.garment, db.n_vertices, settings)
                for job in chosen]
    else:
        settings = {**db.provenance["config"]["drape"], **db.provenance["config"]["warm_drape"], **alternative}
        beta0 = np.asarray(db.beta0, dtype=np.float64)
        garment = make_garment(db.garment, body, db.n_vertices)
        sources, _, _ = held_out_beta0(db, body, garment, config, cache, workers=workers, progress=progress,
                                       pack=beta0_pack)
        for p in sorted(picked):  # the sources travel with the store, so a warm job finds them
            if not store.has(f"beta0_{p:04d}_00"):
                store.save({"key": f"beta0_{p:04d}_00", "vertices": sources[p], "stats": {}})
        jobs = [DrapeJob("floor", job.index, job.shape_index, job.pose, job.beta, db.garment, db.n_vertices, settings,
                         warm_key=f"beta0_{job.index:04d}_00", warm_pose=job.pose, warm_beta=beta0)
                for job in chosen]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    floor_pack = out / f"floor{suffix}_drapes.npz"
    key = json.dumps({"test_set": test_set_key(db, config, betas), "alternative": settings, "every": every,
                      **({"path": path} if path != "ramp" else {})}, sort_keys=True)
    if floor_pack.is_file():
        store.unpack(floor_pack, key)
    run_jobs(jobs, store, workers=workers, progress=progress, pack=lambda: store.pack(floor_pack, key))
    store.pack(floor_pack, key)

    ids, faces = visible_body(body)
    cases = []
    for job, ref in zip(jobs, chosen):
        a, b = reference.load(ref.key).astype(np.float64), store.load(job.key).astype(np.float64)
        distance = np.linalg.norm(a - b, axis=1)
        shape = body.shape(job.beta)
        posed = body.posed_vertices(shape, body.pose(shape, job.pose)[0])[ids]
        test = BodyInside(posed, faces)
        inside = [float(np.mean(test.inside(v))) for v in (a, b)]
        stats = [reference.stats(ref.key), store.stats(job.key)]
        cases.append({"pose": labels[job.index], "shape": int(job.shape_index),
                      "mean_cm": 100.0 * float(distance.mean()),
                      "p95_cm": 100.0 * float(np.percentile(distance, 95)),
                      "max_cm": 100.0 * float(distance.max()), "inside_fraction": inside,
                      "converged": [bool(s.get("converged")) for s in stats],
                      "frames": [int(s.get("frames", 0)) for s in stats]})
    means = np.array([c["mean_cm"] for c in cases])
    picks = np.random.default_rng(0).integers(0, len(means), size=(4000, len(means)))
    report = {
        "database": str(db_path), "path": path, "reference": {k: config.drape[k] for k in sorted(config.drape)},
        "alternative": settings, "cases": cases,
        "mean_cm": float(means.mean()),
        "mean_cm_per_shape": [float(np.mean([c["mean_cm"] for c in cases if c["shape"] == k]))
                              for k in sorted({c["shape"] for c in cases})],
        "mean_ci_cm": np.percentile(means[picks].mean(axis=1), [2.5, 97.5]).tolist(),
        "p95_cm": float(np.mean([c["p95_cm"] for c in cases])),
        "both_converged": int(sum(all(c["converged"]) for c in cases)),
        "mean_cm_both_converged": float(np.mean([c["mean_cm"] for c in cases if all(c["converged"])] or [np.nan])),
    }
    (out / f"floor{suffix}.json").write_text(json.dumps(report, indent=2))
    return report


def main(argv=None) -> int:
    import argparse

    from .testset import default_cache

    parser = argparse.ArgumentParser(prog="agentdress lab floor", description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--cache", default=None, help="the v2 held-out set's cache (default: "
                        "out/eval-cache-v2/<database file name without .h5>)")
    parser.add_argument("--ground-truth", default=None, help="the v2 held-out set's pack (default: "
                        "<out>/ground_truth_drapes.npz)")
    parser.add_argument("--out", default="docs/eval/v2/tshirt", help="folder for floor.json and floor_drapes.npz "
                        "(floor_database.* with --path database)")
    parser.add_argument("--alternative", default=None, help="JSON DrapeSettings overrides of the second path "
                        "(default: {\"ramp_frames\": 60} for --path ramp, none for --path database)")
    parser.add_argument("--every", type=int, default=2, help="take every this many-th held-out pose")
    parser.add_argument("--path", choices=PATHS, default="ramp", help="ramp: the first shape draped from rest with "
                        "--alternative; database: every shape warm-started from the pose's drape at beta0 the way "
                        "the database's shape variants are")
    parser.add_argument("--beta0-pack", default=None, help="with --path database: the held-out poses' drapes at beta0 "
                        "(default: <out>/ground_truth_beta0.npz; simulated and written there when missing)")
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    cache = args.cache or default_cache(args.database, "v2")
    pack = args.ground_truth or Path(args.out) / "ground_truth_drapes.npz"
    alternative = json.loads(args.alternative) if args.alternative else DEFAULT_ALTERNATIVE[args.path]
    report = ground_truth_spread(args.database, cache, pack, args.out, alternative, args.every, args.workers,
                                 progress=not args.quiet, path=args.path,
                                 beta0_pack=args.beta0_pack or Path(args.out) / "ground_truth_beta0.npz")
    print(json.dumps({k: v for k, v in report.items() if k != "cases"}, indent=2))
    return 0
