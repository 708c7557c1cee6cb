"""Ground truth v3: several valid newton drapes of each held-out case, so accuracy can be scored against physics' own
spread instead of against one drape.

A static drape is one equilibrium among several (a fold goes left or right, a hem settles a little higher), and
which one the solver reaches depends on the path it took. v3 fixes the paths before any model work: every case is
draped from rest with the animated collider along each of `RAMPS` (30-, 45- and 60-frame ramps from the rest pose
into the target pose). A drape that does not converge within the first frame budget is draped again with
`EXTENDED_MAX_FRAMES` (key suffix "x"); a case with a drape that converges in neither is reported and excluded.

Cases: the 40 poses of held-out set v2 (4 from each of the 10 test clips of ../shared/mocap/README.md), pose p at
v2's shape p mod 3 (two inside the training range, one just outside), so every shape is covered from rest.

`python -m agentdress_ros.evaluate.groundtruth_v3 --database data/tshirt_default.h5 --pack PACK` drapes what the
pack lacks (resumable: one file per drape in the cache, the pack rewritten every few drapes) and prints the
convergence table. `v3_drapes(db, pack)` reads them back as (C, R, V, 3).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

RAMPS = (30, 45, 60)
FIRST_MAX_FRAMES = 360  # the DrapeSettings default
EXTENDED_MAX_FRAMES = 900


@dataclass(frozen=True)
class V3Case:
    index: int  # the v2 pose index
    pose_label: str  # "02_01@120"
    shape_index: int  # index into the v2 shapes
    shape_label: str  # "inside" / "outside"


def v3_plan(db, body):
    """(cases, poses (C, B, 3), betas (C, 6), plan key) of the v3 set for database `db`."""
    from .testset import _check_held_out, held_out_poses, held_out_shapes, held_out_v2

    config = held_out_v2()
    _check_held_out(db, config.clips)
    poses, labels, _, _ = held_out_poses(body, config)
    shapes, shape_labels = held_out_shapes(db, config)
    picks = np.arange(len(poses)) % len(shapes)
    cases = [V3Case(p, labels[p], int(k), shape_labels[k]) for p, k in enumerate(picks)]
    betas = shapes[picks]
    key = json.dumps({"set": "v3", "garment": db.garment, "vertices": db.n_vertices, "ramps": list(RAMPS),
                      "max_frames": [FIRST_MAX_FRAMES, EXTENDED_MAX_FRAMES], "poses": labels,
                      "betas": np.round(betas, 9).tolist(), "clips": [Path(c).stem for c in config.clips]},
                     sort_keys=True)
    return cases, poses, betas, key


def drape_key(ramp: int, case: int, extended: bool = False) -> str:
    return f"v3r{ramp}{'x' if extended else ''}_{case:04d}_00"


def _jobs(db, poses, betas, extended: bool, only=None) -> list:
    from ..offline.jobs import DrapeJob

    max_frames = EXTENDED_MAX_FRAMES if extended else FIRST_MAX_FRAMES
    jobs = []
    for c, (pose, beta) in enumerate(zip(poses, betas)):  # case by case, so complete cases accumulate first
        for ramp in RAMPS:
            if only is None or (ramp, c) in only:
                kind = f"v3r{ramp}{'x' if extended else ''}"
                jobs.append(DrapeJob(kind, c, 0, pose, beta, db.garment, db.n_vertices,
                                     {"ramp_frames": ramp, "max_frames": max_frames}))
    return jobs


def environment() -> dict:
    """What the drapes were made with: solver versions and the commit of the code (recorded in the pack)."""
    from importlib.metadata import version

    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {"newton": version("newton"), "warp": version("warp-lang"), "commit": commit, "seed": 0}


def make_v3_drapes(database, pack, cache, workers: int = 0, progress: bool = True, cases: int | None = None) -> dict:
    """Drape every v3 case along every ramp (the first `cases` cases when given), extend the drapes that did not
    converge, and pack them all into `pack`. Returns the convergence summary (`summary`)."""
    from ..body import AnnyBody
    from ..offline.builder import run_jobs
    from ..offline.jobs import DrapeStore, read_drape_pack
    from ..engine import read_database

    db = read_database(database)
    all_cases, poses, betas, key = v3_plan(db, AnnyBody())
    n = len(all_cases) if cases is None else min(cases, len(all_cases))
    store = DrapeStore(Path(cache))
    pack = Path(pack)
    recorded = environment()
    if pack.is_file():
        stored = read_drape_pack(pack)["environment"] or {}
        recorded = {**recorded, "commit": stored.get("commit", recorded["commit"])}  # the commit that started it
        store.unpack(pack, key, {k: v for k, v in recorded.items()})
    pack.parent.mkdir(parents=True, exist_ok=True)

    def save():
        store.pack(pack, key, recorded)

    run_jobs(_jobs(db, poses[:n], betas[:n], extended=False), store, workers=workers, progress=progress, pack=save,
             pack_every=5)
    unconverged = {(r, c) for r in RAMPS for c in range(n) if not store.stats(drape_key(r, c))["converged"]}
    run_jobs(_jobs(db, poses[:n], betas[:n], extended=True, only=unconverged), store, workers=workers,
             progress=progress, pack=save, pack_every=5)
    save()
    return summary(read_drape_pack(pack), all_cases[:n])


def _final(drapes: dict, ramp: int, case: int):
    """(vertices, stats, extended) of one case's drape along one ramp: the extended drape when there is one."""
    for extended in (True, False):
        entry = drapes.get(drape_key(ramp, case, extended))
        if entry is not None:
            return entry[0], entry[1], extended
    return None


def summary(pack: dict, cases: list) -> dict:
    """Per case and ramp: frames, converged, extended; the cases kept (every drape present and converged), those
    with a drape still missing (or not converged and not yet extended), and those excluded because a drape
    converged neither at first nor extended."""
    rows, kept, missing = [], [], []
    for case in cases:
        row = {"case": case.index, "pose": case.pose_label, "shape": case.shape_label, "drapes": {}}
        complete = True
        for ramp in RAMPS:
            final = _final(pack["drapes"], ramp, case.index)
            if final is None:
                complete = False
                if case.index not in missing:
                    missing.append(case.index)
                continue
            _, stats, extended = final
            row["drapes"][ramp] = {"frames": stats["frames"], "converged": bool(stats["converged"]),
                                   "extended": extended, "seconds": round(stats["seconds"], 1)}
            complete &= bool(stats["converged"])
            if not stats["converged"] and not extended and case.index not in missing:
                missing.append(case.index)  # its extended drape is still to come
        rows.append(row)
        if complete:
            kept.append(case.index)
    seconds = [d["seconds"] for r in rows for d in r["drapes"].values()]
    not_converged = [c.index for c in cases if c.index not in kept and c.index not in missing]
    return {"cases": rows, "kept": kept, "missing": missing, "not_converged": not_converged, "drapes": len(seconds), "cpu_hours": round(sum(seconds) / 3600, 2),
            "environment": pack["environment"]}


def v3_drapes(pack, expected_key: str | None = None) -> tuple[np.ndarray, list, dict]:
    """(drapes (C, R, V, 3) of the kept cases, their case indices, summary) from a v3 pack; with expected_key (the
    plan key of `v3_plan`), a pack of another garment, vertex count or case list is refused, naming what differs."""
    from ..offline.jobs import key_changes, read_drape_pack

    data = read_drape_pack(pack)
    if expected_key is not None and data["plan_key"] != expected_key:
        changes = key_changes(json.loads(data["plan_key"]), json.loads(expected_key))
        raise ValueError(f"{pack}: these v3 drapes belong to another plan (pack -> wanted): {'; '.join(changes)}")
    plan = json.loads(data["plan_key"])
    cases = [V3Case(i, label, 0, "") for i, label in enumerate(plan["poses"])]
    report = summary(data, cases)
    if not report["kept"]:
        raise ValueError(f"{pack}: no case has all {len(RAMPS)} drapes converged yet")
    drapes = np.stack([np.stack([_final(data["drapes"], r, c)[0] for r in RAMPS]) for c in report["kept"]])
    return drapes, report["kept"], report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress lab groundtruth-v3", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True, help="garment database (.h5) whose garment is draped")
    parser.add_argument("--pack", required=True, help="drape pack to read and (re)write (.npz)")
    parser.add_argument("--cache", default=None, help="one file per finished drape (default: out/v3/<garment>)")
    parser.add_argument("--cases", type=int, default=None, help="only the first N cases (a pilot)")
    parser.add_argument("--workers", type=int, default=0, help="drape processes (0: in this process)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    cache = args.cache or Path("out/v3") / Path(args.database).stem
    report = make_v3_drapes(args.database, args.pack, cache, workers=args.workers, progress=not args.quiet,
                            cases=args.cases)
    json.dump({k: v for k, v in report.items() if k != "cases"}, sys.stdout, indent=2)
    print()
    for row in report["cases"]:
        cells = [f"{r}: {d['frames']}{'' if d['converged'] else ' NOT converged'}{' (extended)' if d['extended'] else ''}"
                 for r, d in row["drapes"].items()]
        print(f"{row['case']:3d} {row['pose']:>10} {row['shape']:>8}  " + "; ".join(cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
