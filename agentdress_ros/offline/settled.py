"""Static drapes settled from the dynamic training frames: more of the kind of cloth the held-out set holds.

    agentdress lab settle --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz --frames 500 \
        --out data/tshirt_settled.npz [--workers 2]

The held-out ground truth and the anchors are static drapes: the cloth hangs at rest on a body standing still. The
dense training frames are dynamic: the cloth swings and lags. A pose model trained on both sees 40 static drapes
beside 9,000 moving ones. This turns `frames` of the dynamic frames (spread evenly over the pack, so over its
training clips) into static drapes: the frame's garment, in the frame's pose at beta0, settles with the body held
still (about 100 frames, 10 s at 1,200 vertices; nothing is lifted out of the body first, the cloth starts where
the dynamic simulation left it). The result is a pack of the same format as the sequences' (offline.sequences), one
"frame" per drape with its source clip and frame and zero speeds, which `agentdress lab regressor --pack` reads beside
the sequences.

Each drape is one build job (offline.jobs, `warm_ramp_frames` 1: the start is the frame itself), run on the build's
Dask machinery and written atomically under `<out>.work/`, so a killed run loses at most the drapes in flight.

`--start rest` drapes the same poses the way the anchors and the held-out ground truth are draped instead: the
garment starts at rest on the body at rest and the body carries it into the frame's pose (the database's own drape
settings, `ramp_frames` 30), then it settles. It costs about twice as much (about 30 s a drape) and lands in the
held-out set's kind of equilibrium rather than next to a moving cloth. The drapes run in a spread order (a base-2
radical inverse over the frames), so the drapes finished at any moment cover the clips evenly and `--partial` packs
a usable subset of a run still going.

`--select novel` picks the frames by novelty instead of spreading them: greedy farthest-point sampling in the
database regressor's standardised pose inputs, away from the poses the `--skip` packs and the database's drapes
already cover (and their mirror images). More drapes of the same clips spread evenly land next to poses already
draped; these go where the training poses are sparsest, and every prefix of the order is itself such a pick.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

#: Settling from a dynamic frame is a warm start: near equilibrium, so the warm drapes' extra drag applies.
SETTLE_DRAPE = {"velocity_retention": 0.75, "warm_ramp_frames": 1}
#: Shaped drapes reach this far beyond the training range (the held-out set's outside shapes lie 0.05 beyond it).
SHAPED_MARGIN = 0.05


def settle_jobs(pack: dict, db, body, frames, drape: dict | None = None) -> tuple:
    """(jobs, starts): one DrapeJob per pack frame index in `frames`, warm-started from the frame's own garment
    (starts: {"dynamic_<frame>_00": posed garment (V, 3)}, the pack's rest-frame offsets skinned at beta0).
    drape: DrapeSettings overrides on top of SETTLE_DRAPE."""
    from ..offline.kdsm_training import pack_frames
    from .jobs import DrapeJob

    shape = body.shape(db.beta0)
    beta0 = np.asarray(db.beta0, dtype=np.float64)
    garments = pack_frames(pack, db, body, shape, frames)
    jobs, starts = [], {}
    for n, f in enumerate(np.asarray(frames, dtype=np.int64)):
        pose = np.asarray(pack["rotvecs"][f], dtype=np.float64)
        start_key = f"dynamic_{f:04d}_00"
        starts[start_key] = garments.drapes[n]
        jobs.append(DrapeJob("settled", int(f), 0, pose, beta0, db.garment, db.n_vertices,
                             {**SETTLE_DRAPE, **(drape or {})},
                             warm_key=start_key, warm_pose=pose, warm_beta=beta0))
    return jobs, starts


def rest_start_jobs(pack: dict, db, frames, drape: dict | None = None) -> list:
    """One DrapeJob per pack frame index in `frames`: the frame's pose at beta0, draped from rest with the
    database's drape settings (its build's `drape` overrides, the held-out set's kind of drape) plus `drape`."""
    from .jobs import DrapeJob

    settings = {**dict(db.provenance.get("config", {}).get("drape", {})), **(drape or {})}
    if not settings.get("ramp_frames"):
        raise ValueError("a drape from rest needs ramp_frames > 0 (the database was built with a static collider; "
                         "pass drape={'ramp_frames': 30})")
    beta0 = np.asarray(db.beta0, dtype=np.float64)
    return [DrapeJob("rest", int(f), 0, np.asarray(pack["rotvecs"][f], dtype=np.float64), beta0, db.garment,
                     db.n_vertices, settings) for f in np.asarray(frames, dtype=np.int64)]


def shaped_jobs(db, rest_jobs: list, seed: int = 0, margin: float = SHAPED_MARGIN, drape: dict | None = None) -> list:
    """One DrapeJob per drape from rest in `rest_jobs`: the same pose at a random body shape (body.training_shapes.
    uniform_shapes over the database's training range widened by `margin`, seeded), warm-started from that drape
    the way the held-out set's other shapes start from its first (the held-out set's warm settings, plus the
    DrapeSettings overrides `drape`)."""
    from ..body.training_shapes import uniform_shapes
    from ..sim.settings import WARM_DRAPE
    from .jobs import DrapeJob

    betas = uniform_shapes(db.beta0, db.beta_range, len(rest_jobs), np.random.default_rng(seed), margin)
    warm = {**dict(db.provenance.get("config", {}).get("drape", {})), **WARM_DRAPE, **(drape or {})}
    return [DrapeJob("shaped", job.index, 1, job.pose, beta, db.garment, db.n_vertices, warm, warm_key=job.key,
                     warm_pose=job.pose, warm_beta=job.beta) for job, beta in zip(rest_jobs, betas)]


def shaped_offsets(body, db, betas, poses, garments) -> list:
    """Rows (3V,) of each posed garment (V, 3) of `garments` unposed with the bones of its shape (betas (F, 6)) in
    its pose (poses (F, B, 3)), minus the garment fitted to that shape at rest (`Garment.rest_vertices`): what a
    shaped pack stores."""
    from ..garment import make_garment
    from .sequences import rest_frame_offsets

    garment = make_garment(db.garment, body, db.n_vertices)
    rows = []
    for beta, pose, posed in zip(betas, poses, garments):
        shape = body.shape(beta)
        rows += rest_frame_offsets(body, shape, db.skin_indices, db.skin_weights, garment.rest_vertices(body, shape),
                                   [posed], [pose], np.zeros((1, 3)))
    return rows


def spread_order(count: int) -> np.ndarray:
    """(count,) a permutation of range(count) whose every prefix is spread evenly over the range: the order of the
    base-2 radical inverse (0, 1/2, 1/4, 3/4, ...) of the positions."""
    bits = max(1, int(count - 1).bit_length())
    reversed_bits = [int(format(i, f"0{bits}b")[::-1], 2) for i in range(count)]
    return np.argsort(reversed_bits, kind="stable")


def settled_in(pack: dict, settled: dict, frames) -> np.ndarray:
    """(len(frames),) bool: which of the pack's frame indices a settled pack already holds (same clip and frame)."""
    held = {(str(settled["clips"][c]), int(f)) for c, f in zip(settled["clip"], settled["frame"])}
    return np.array([(str(pack["clips"][pack["clip"][f]]), int(pack["frame"][f])) in held for f in frames], dtype=bool)


def novel_frames(pack: dict, db, body, covered, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(`count` pack frame indices, their distances when picked): greedy farthest-point sampling in the database
    regressor's standardised pose inputs. Each pick is the pack frame farthest from every pose a drape already
    covers - the `covered` canonical poses (C, B, 3), the picks before it, and the mirror images of both (the
    regressor trains on those too) - so new drapes go where the training poses are sparsest."""
    from scipy.spatial import cKDTree

    from ..engine.pose_models import canonical_poses
    from .mirror import bone_twins, mirrored_canonical_poses
    from .regressor import standardized_inputs

    if db.regressor is None:
        raise ValueError("--select novel measures novelty in the database regressor's inputs, and this database "
                         "has no pose_model/regressor")
    twins = bone_twins(body.bone_names)

    def inputs(poses):  # (F, I) of the poses and (F, I) of their mirror images
        poses = canonical_poses(np.asarray(poses, dtype=np.float64))
        return (standardized_inputs(db.regressor, poses),
                standardized_inputs(db.regressor, mirrored_canonical_poses(poses, twins)))

    candidates, candidates_mirrored = inputs(pack["rotvecs"])
    nearest = cKDTree(np.concatenate(inputs(covered))).query(candidates)[0]
    picks, distances = [], []
    for _ in range(min(count, len(candidates))):
        f = int(np.argmax(nearest))
        if nearest[f] <= 0.0:  # every frame left is a pose already draped
            break
        picks.append(f)
        distances.append(float(nearest[f]))
        for point in (candidates[f], candidates_mirrored[f]):
            nearest = np.minimum(nearest, np.linalg.norm(candidates - point, axis=1))
    return np.array(picks, dtype=np.int64), np.array(distances)


def settle_pack(db_path, pack_path, out, count: int, workers: int = 2, progress: bool = True,
                components: int = 64, drape: dict | None = None, partial: bool = False, work=None,
                start: str = "dynamic", seed: int = 0, skip=None, select: str = "spread") -> dict:
    """Settle `count` frames of the pack (see the module docstring), resumably; write the pack `out`; a report.
    skip: settled packs (a path or several) whose frames are left out (`count` 2n - 1 over a pack of n spread frames
    settles the n - 1 frames halfway between them: more drapes without draping the first ones again).
    select: "spread" (frames evenly over the pack, in spread_order) or "novel" (novel_frames: the `count` frames
    farthest from the poses the skipped packs and the database's examples already cover, in the order picked).
    work: the folder of finished drapes (default `<out>.work`); partial: drape nothing, pack the drapes finished so
    far (while another run of the same command goes on); start: "dynamic" (from the frame's own cloth) or "rest"
    (carried from the rest pose, as the anchors are) or "shaped" (each finished drape from rest in `work` again at a
    random shape drawn with `seed`, warm-started from it)."""
    from ..body import AnnyBody
    from ..engine.database import read_database
    from ..offline.kdsm_training import spread_frames
    from .builder import run_jobs
    from .jobs import DrapeStore
    from .regressor import settled_paths
    from .sequences import check_training_clips, load_sequence_pack, rest_frame_offsets, write_pack

    db = read_database(db_path)
    body = AnnyBody()
    pack = load_sequence_pack(pack_path)
    check_training_clips([str(c) for c in pack["clips"]])
    skipped = [load_sequence_pack(path) for path in settled_paths(skip)]
    novelty = None
    if select == "novel":
        covered = np.concatenate([np.asarray(db.example_poses)] + [p["rotvecs"] for p in skipped])
        frames, novelty = novel_frames(pack, db, body, covered, count)
    elif select == "spread":
        frames = spread_frames(pack, count)
        for settled in skipped:
            frames = frames[~settled_in(pack, settled, frames)]
        frames = frames[spread_order(len(frames))]
    else:
        raise ValueError(f"select must be 'spread' or 'novel', got {select!r}")
    same_garment = str(pack["garment"]) == db.garment and int(pack["garment_vertices"]) == db.n_vertices
    if start == "dynamic" and not same_garment:
        raise ValueError(f"{pack_path}: its frames are the {pack['garment']} at {int(pack['garment_vertices'])} "
                         f"vertices, and settling from them needs that garment's database, not {db_path} "
                         f"({db.garment}, {db.n_vertices} vertices); --start rest drapes any garment at the pack's "
                         "poses")
    store = DrapeStore(Path(work if work is not None else str(out) + ".work") / "drapes")
    if start in ("rest", "shaped"):
        jobs, starts = rest_start_jobs(pack, db, frames, drape), {}
        if start == "shaped":  # the other shape of each pose whose drape from rest is finished (every pose
            # draws its shape, finished or not, so that a frame's shape never depends on how far the rest run got)
            jobs = [job for job in shaped_jobs(db, jobs, seed, drape=drape) if store.has(job.warm_key)]
    elif start == "dynamic":
        jobs, starts = settle_jobs(pack, db, body, frames, drape)
    else:
        raise ValueError(f"start must be 'dynamic', 'rest' or 'shaped', got {start!r}")
    for key, vertices in starts.items():
        if not store.has(key):
            store.save({"key": key, "vertices": vertices, "stats": {}})
    if partial:
        jobs = [job for job in jobs if store.has(job.key)]
    else:
        run_jobs(jobs, store, workers=workers, progress=progress)
    # the database's garment, which need not be the pack's with --start rest (the pack gives only the poses)
    rest = np.asarray(db.rest, dtype=np.float64)
    drapes, poses, shaped = [store.load(job.key) for job in jobs], [job.pose for job in jobs], {}
    if start == "shaped":  # each drape unposed with its own shape's bones, from the garment fitted to that shape
        shaped = {"betas": np.array([job.beta for job in jobs])}
        offsets = shaped_offsets(body, db, shaped["betas"], poses, drapes)
    else:
        offsets = rest_frame_offsets(body, body.shape(db.beta0), db.skin_indices, db.skin_weights, rest, drapes,
                                     poses, np.zeros((len(jobs), 3)))
    stats = [store.stats(job.key) for job in jobs]
    n = len(jobs)
    done = np.array([job.index for job in jobs], dtype=np.int64)  # the pack frames settled (all but with partial)
    fields = {"rotvecs": pack["rotvecs"][done], "root_translation": np.zeros((n, 3)),
              "root_velocity": np.zeros((n, 3)), "cloth_speed": np.zeros(n), "body_speed": np.zeros(n),
              "clip": pack["clip"][done], "frame": pack["frame"][done], **shaped}
    names = [str(c) for c in pack["clips"]]
    error, explained, k = write_pack(out, db.garment, db.n_vertices, np.asarray(db.beta0), rest,
                                     np.asarray(db.faces), offsets, fields, names, [True] * len(names),
                                     components)
    moved = [s["displacement_mean"] for s in stats]
    return {"pack": str(out), "bytes": Path(out).stat().st_size, "drapes": n, "source": str(pack_path), "start": start,
            "clips": int(len(np.unique(fields["clip"]))), "converged": int(sum(s["converged"] for s in stats)),
            "frames_median": float(np.median([s["frames"] for s in stats])),
            "seconds_median": float(np.median([s["seconds"] for s in stats])),
            "cpu_seconds": float(sum(s["seconds"] for s in stats)),
            f"moved_from_{start}_mean_m": float(np.mean(moved)),
            "inside_true_mean": float(np.mean([s["inside_true_count"] for s in stats])),
            "inside_overlap_mean": float(np.mean([s["inside_overlap_count"] for s in stats])),
            "components": k, "explained_variance": explained, "rest_frame_error_mean_m": float(error.mean()),
            "select": select, **({} if novelty is None else {"novelty_first_last": [float(novelty[0]),
                                                                                  float(novelty[-1])]})}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress lab settle", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--pack", default="data/tshirt_sequences.npz", help="sequence pack of the training clips")
    parser.add_argument("--frames", type=int, default=500, help="frames spread over the pack to settle")
    parser.add_argument("--out", required=True, help="the settled drapes' pack (.npz)")
    parser.add_argument("--workers", type=int, default=2, help="local worker processes (0: in this process)")
    parser.add_argument("--components", type=int, default=64, help="PCA components of the pack")
    parser.add_argument("--work", default=None, help="folder of the finished drapes (default: <out>.work)")
    parser.add_argument("--partial", action="store_true", help="drape nothing: pack the drapes finished so far "
                        "(with --work naming a running command's folder and another --out)")
    parser.add_argument("--start", choices=["dynamic", "rest", "shaped"], default="dynamic",
                        help="dynamic: settle from the frame's own cloth; rest: carry the garment from the rest pose "
                        "into the frame's pose, as the anchors and the held-out set are draped; shaped: each drape "
                        "from rest finished in --work again at a random body shape, warm-started from it")
    parser.add_argument("--seed", type=int, default=0, help="--start shaped: the seed of the random shapes")
    parser.add_argument("--drape", type=json.loads, default=None, help="JSON DrapeSettings overrides, e.g. "
                        "'{\"ramp_frames\": 30}' to drape from rest with a database built with the static collider")
    parser.add_argument("--skip", nargs="+", default=None, help="settled packs whose frames are left out: with "
                        "--frames 2n-1 over a pack of n frames, the n-1 frames halfway between them")
    parser.add_argument("--select", choices=["spread", "novel"], default="spread",
                        help="spread: frames evenly over the pack; novel: the frames farthest, in the database "
                        "regressor's pose inputs, from the poses --skip's packs and the database's drapes cover")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    report = settle_pack(args.database, args.pack, args.out, args.frames, args.workers, not args.quiet,
                         args.components, drape=args.drape, partial=args.partial, work=args.work,
                         start=args.start, seed=args.seed, skip=args.skip, select=args.select)
    json.dump(report, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
