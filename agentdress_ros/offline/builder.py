"""`agentdress build`: pose set -> sensitivities -> anchors -> drapes -> shape and pose models -> HDF5 database.

Everything before the drapes is cheap and deterministic; it is computed once and kept in `<out>.work/` as
`plan.npz` (arrays, read without pickle) and `plan.json` (its key and report), so a rerun (after a kill) reuses it and
only drapes what is missing. The key holds everything a drape depends on: the build parameters and the drape
environment (the versions of anny, newton and warp, and a hash of the garment template with its generator
settings); a rerun under another key is refused and says what changed, so stale drapes are never reused. Drapes run
in parallel processes through Dask (a LocalCluster by default, or an existing scheduler), each written atomically as
soon as it arrives. The database file is written last, atomically: a partial build never leaves a partial file.
"""
from __future__ import annotations

import hashlib
import json
import logging
import platform
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody
from ..body.assets import PHENOTYPE_NAMES
from ..body.training_shapes import shape_range, shape_scale, training_shapes
from ..engine.database import Database, write_database
from ..garment import REGION_NAMES, make_garment
from ..garment.binding import SurfaceBinding
from ..garment.templates import EASE, SURFACE
from ..sim.settings import WARM_DRAPE
from .anchors import canonical_poses, coverage, farthest_poses, uniform_anchors, weighted_kmeans_anchors
from .jobs import DrapeJob, DrapeStore, key_changes, posed_scene, read_drape_pack, run_drape_job
from .sensitivity import joint_weights, region_dof_influence, vertex_sensitivity
from .shape_model import fit_shape_model


@dataclass
class BuildConfig:
    garment: str = "tshirt"
    garment_vertices: int = 3000
    anchors: int = 32
    shapes: int = 17
    components: int = 5
    examples: int = 64  # pose-model examples at beta0: the anchors' beta0 drapes plus poses where they are sparse
    sequence_frames: int = 60  # the simulated evaluation sequence at beta0 (Sec. 4.4)
    holdout_anchors: int = 4  # anchors draped on one extra, held-out shape to measure the shape model
    pose_every: int = 4  # one pose every few frames of each clip (the paper: 4)
    clips: list = field(default_factory=list)  # CMU .bvh files; empty: the procedural library only
    # Knee and elbow flips of the capture repaired (motion.cleanup); False: the clips as recorded, as the databases
    # built before the repair were (their drape packs' keys do not name it).
    repair_flips: bool = True
    procedural: list = field(default_factory=lambda: ["idle", "walk", "reach", "sweep", "wipe", "wave", "squat"])
    procedural_seconds: float = 4.0
    sequence_motion: str = "walk"
    sequence_fps: float = 30.0
    drape: dict = field(default_factory=dict)  # DrapeSettings overrides
    # ... and on top of those for drapes warm-started from another drape. Such a start is already near equilibrium,
    # so more drag settles it in 33 frames instead of 82 (2k-vertex T-shirt, shape variant) and moves the result
    # 1.1 mm on average, less than the 2.8 mm by which the two warm starts' equilibria differ.
    warm_drape: dict = field(default_factory=lambda: dict(WARM_DRAPE))
    seed: int = 0

    def plan_key(self) -> str:
        """The parameters the plan and the drapes depend on (workers, scheduler and the fit's components do not)."""
        return _plan_key(asdict(self))


FIT_ONLY = ("components",)  # changes only the models fitted to the drapes: a rerun refits, re-draping nothing


def _plan_key(fields: dict) -> str:
    """The build parameters' part of the key (also what a drape pack's `__plan_key__` holds)."""
    kept = {k: v for k, v in fields.items() if k not in FIT_ONLY}
    if not kept.get("repair_flips", False):  # builds on the raw clips keep the key they had before the repair
        kept.pop("repair_flips", None)
    return json.dumps(kept, sort_keys=True)


# A build or held-out set given a pack rewrites it after every this many drapes (a few seconds for 586 drapes),
# besides at the end.
PACK_EVERY = 10
#: Distributions whose versions change a drape: the body model (shapes, rig, skin weights) and the simulator.
DRAPE_PACKAGES = {"anny": "anny", "newton": "newton", "warp": "warp-lang"}


def _version(distribution: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(distribution)
    except PackageNotFoundError:
        return "not installed"


def template_hash(garment) -> str:
    """sha256 of a garment template (topology, binding, skin weights, regions, pinned vertices) and the settings
    its generator was run with (name, vertex count, ease, surface). Floats are rounded to 1e-9 so that the same
    template built on another machine hashes the same."""
    settings = {"name": garment.name, "vertices": int(garment.n_vertices), "surface": garment.surface,
                "ease": EASE.get(garment.name), "tights": SURFACE, "binding": type(garment.binding).__name__}
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    binding = sorted(vars(garment.binding).items())
    for name, value in [("faces", garment.faces), ("skin_indices", garment.skin_indices),
                        ("skin_weights", garment.skin_weights), ("regions", garment.regions),
                        ("pinned", garment.pinned)] + [(f"binding.{k}", v) for k, v in binding]:
        array = np.asarray(value)
        array = (np.round(array.astype(np.float64), 9) + 0.0) if array.dtype.kind == "f" else array.astype(np.int64)
        digest.update(f"{name}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def drape_environment(garment) -> dict:
    """What changes a drape besides the build parameters: package versions and the garment template's hash."""
    environment = {name: _version(dist) for name, dist in DRAPE_PACKAGES.items()}
    environment["garment_template"] = template_hash(garment)
    return environment


def build_key(config: BuildConfig, environment: dict) -> dict:
    """The full key of a build's plan and drapes (JSON-compatible)."""
    return json.loads(json.dumps({"parameters": json.loads(config.plan_key()), "environment": environment},
                                 sort_keys=True))


def _motion_poses(config: BuildConfig, body: AnnyBody, shape) -> np.ndarray:
    """Pose set (P, B, 3) from the CMU clips and the procedural motions, every `pose_every` frames, root removed."""
    from ..motion.procedural import make_motion
    from ..motion.retarget import load_cmu_motion

    poses = []
    for clip in config.clips:
        motion = load_cmu_motion(clip, shape.heads, shape.tails, repair_flips=config.repair_flips)
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


def make_plan(config: BuildConfig, body: AnnyBody, garment=None) -> dict:
    """All deterministic inputs of the drapes and models (no simulation): arrays, the garment and a report."""
    rng = np.random.default_rng(config.seed)
    garment = garment if garment is not None else make_garment(config.garment, body, config.garment_vertices)
    beta0 = np.asarray(REFERENCE_SHAPE, dtype=np.float64)
    shapes = training_shapes(config.shapes, beta0)
    scale = shape_scale()
    reference = body.shape(beta0)
    pose_set = _motion_poses(config, body, reference)
    sensitivity = vertex_sensitivity(body, garment, shapes)
    dof_weights = joint_weights(sensitivity)
    anchors, anchor_ids = weighted_kmeans_anchors(pose_set, dof_weights, config.anchors, config.seed)
    # The pose model's examples reuse the anchors' beta0 drapes and add the poses the anchors cover worst.
    extra = farthest_poses(pose_set, anchors, dof_weights, max(0, config.examples - len(anchors)))
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
        "examples": pose_set[extra],  # (M, B, 3) example poses beyond the anchors
        "sequence": _sequence_poses(config, reference),
        "holdout_beta": holdout,
        "report": report,
    }


def _jobs(config: BuildConfig, plan: dict) -> list:
    """Every drape of the build. Anchors at beta0 start from skinning; the other shapes of an anchor (and its
    held-out shape) start from its beta0 drape, and each sequence frame from the previous one (`warm_key`)."""
    common = dict(garment=config.garment, garment_vertices=config.garment_vertices, settings=config.drape)
    warm_settings = {**config.drape, **config.warm_drape}
    beta0 = plan["beta0"]
    jobs = []

    def from_anchor(s):
        return dict(warm_key=f"anchor_{s:04d}_00", warm_pose=plan["anchors"][s], warm_beta=beta0,
                    settings=warm_settings)

    for s, pose in enumerate(plan["anchors"]):
        for k, beta in enumerate(plan["shapes"]):
            warm = from_anchor(s) if k > 0 else {}
            jobs.append(DrapeJob("anchor", s, k, pose, beta, **{**common, **warm}))
    for s in range(min(config.holdout_anchors, len(plan["anchors"]))):
        jobs.append(DrapeJob("holdout", s, 0, plan["anchors"][s], plan["holdout_beta"], **{**common, **from_anchor(s)}))
    for m, pose in enumerate(plan["examples"]):
        jobs.append(DrapeJob("example", m, 0, pose, beta0, **common))
    for t, pose in enumerate(plan["sequence"]):
        warm = {} if t == 0 else dict(warm_key=f"sequence_{t - 1:04d}_00", warm_pose=plan["sequence"][t - 1],
                                      warm_beta=beta0, settings=warm_settings)
        jobs.append(DrapeJob("sequence", t, 0, pose, beta0, **{**common, **warm}))
    return jobs


PLAN_ARRAYS = ("beta0", "shapes", "scale", "sensitivity", "dof_weights", "region_dof", "anchors", "examples",
               "sequence", "holdout_beta")


def _load_or_make_plan(config: BuildConfig, body: AnnyBody, work: Path) -> tuple:
    """(plan, key) of this build: the plan is computed once and stored as plan.npz + plan.json, then reloaded.

    A work folder whose plan has another key is refused, naming what changed (parameters, package versions, the
    garment template), as is one holding drapes without a readable plan (an older pickled plan.pkl, which is never
    loaded: unpickling runs code): its drapes cannot be told apart from stale ones.
    """
    garment = make_garment(config.garment, body, config.garment_vertices)
    key = build_key(config, drape_environment(garment))
    meta, arrays = work / "plan.json", work / "plan.npz"
    drapes = sorted((work / "drapes").glob("*.npz"))
    if meta.is_file():
        try:
            stored = json.loads(meta.read_text())
            with np.load(arrays, allow_pickle=False) as data:
                plan = {name: data[name] for name in PLAN_ARRAYS}
            stored_key, report = stored["key"], stored["report"]
            if not isinstance(stored_key, dict):
                raise TypeError(f"its key is {type(stored_key).__name__}, not an object")
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{work}: unreadable plan ({error}); delete the folder or use another --out") from None
        if stored_key != key:
            what = ("belongs to a build with other parameters" if stored_key.get("parameters") != key["parameters"]
                    else "was made under another drape key")
            changes = "\n    ".join(key_changes(stored_key, key))
            raise ValueError(
                f"{work}: this work folder {what}; its {len(drapes)} finished drapes are not reused. Use another "
                f"--out or delete the folder.\n  changed (stored -> requested):\n    {changes}")
        return {**plan, "garment": garment, "report": report}, key
    if (work / "plan.pkl").exists():
        raise ValueError(f"{work}: holds a pickled plan (plan.pkl) of an older agentdress, which is not loaded "
                         f"(unpickling can run code), and {len(drapes)} drapes under an unknown key. Delete the folder "
                         "or use another --out; drapes packed with --pack-drapes can seed the new build.")
    if drapes:
        raise ValueError(f"{work}: {len(drapes)} drapes without a plan (plan.json): their key is unknown, so they "
                         "are not reused. Delete the folder or use another --out.")
    plan = make_plan(config, body, garment)
    work.mkdir(parents=True, exist_ok=True)
    partial = work / "plan.partial.npz"
    np.savez(partial, **{name: np.asarray(plan[name]) for name in PLAN_ARRAYS})
    partial.replace(arrays)
    partial = work / "plan.json.partial"
    partial.write_text(json.dumps({"key": key, "report": plan["report"]}, indent=1, sort_keys=True))
    partial.replace(meta)  # written last: its presence marks a complete plan
    return plan, key


def run_jobs(jobs, store: DrapeStore, workers: int = 2, scheduler: str | None = None, progress: bool = True,
             pack=None, pack_every: int = PACK_EVERY):
    """Drape every job not yet in the store, in parallel through Dask; results are saved as they complete.

    A job that warm-starts from another drape is sent out once that drape is in the store.
    pack: callable() that packs the store, called after every `pack_every` saved drapes, so that work in a
    tracked pack survives the loss of the work folder (a new checkout, a killed machine).
    """
    from tqdm import tqdm

    pending = [job for job in jobs if not store.has(job.key)]
    known = {job.key for job in jobs}
    for job in pending:
        if job.warm_key and job.warm_key not in known and not store.has(job.warm_key):
            raise ValueError(f"job {job.key} starts from drape {job.warm_key}, which no job makes")
    waiting: dict = {}  # warm_key -> jobs that start from it
    ready = []
    for job in pending:
        if job.warm_key and not store.has(job.warm_key):
            waiting.setdefault(job.warm_key, []).append(job)
        else:
            ready.append(job)

    def inputs(job):
        return store.load(job.warm_key) if job.warm_key else None

    saved = 0

    def finished(result):
        nonlocal saved
        store.save(result)
        bar.update()
        saved += 1
        if pack is not None and saved % pack_every == 0:
            pack()
        return waiting.pop(result["key"], [])

    bar = tqdm(total=len(jobs), initial=len(jobs) - len(pending), desc="drapes", unit="drape", disable=not progress)
    if pending and workers == 0 and scheduler is None:
        while ready:  # in this process: no cluster start-up (tests, debugging)
            job = ready.pop(0)
            ready.extend(finished(run_drape_job(job, inputs(job))))
    elif pending:
        from dask.distributed import Client, LocalCluster, as_completed

        cluster = None if scheduler else LocalCluster(n_workers=max(1, workers), threads_per_worker=1,
                                                      processes=True, dashboard_address=":0",
                                                      silence_logs=logging.WARNING)
        with Client(scheduler or cluster) as client:
            def submit(job):
                return client.submit(run_drape_job, job, inputs(job), key=f"drape-{job.key}-{id(store)}", pure=False)

            queue = as_completed([submit(job) for job in ready])
            for future in queue:
                for job in finished(future.result()):
                    queue.add(submit(job))
        if cluster is not None:
            cluster.close()
    bar.close()
    if waiting:  # only when a warm-start source failed to appear, which finished() rules out
        raise RuntimeError(f"drapes never started: {sorted(waiting)}")


def fit_database(config: BuildConfig, plan: dict, store: DrapeStore, body: AnnyBody, command: str,
                 partial: bool = False, environment: dict | None = None) -> tuple:
    """Shape models, pose-model data and provenance from the finished drapes: (Database, report).

    partial: use only the anchors whose drapes are all finished (and the examples and the leading sequence frames
    that are), for a usable database from a build that is still running; a complete build is the same either way.
    environment: the drape environment of the build's key (drape_environment), recorded in the provenance.
    """
    garment = plan["garment"]
    n_anchors, n_shapes = len(plan["anchors"]), len(plan["shapes"])
    complete = [s for s in range(n_anchors) if all(store.has(f"anchor_{s:04d}_{k:02d}") for k in range(n_shapes))]
    if not partial and len(complete) < n_anchors:
        missing = sorted(set(range(n_anchors)) - set(complete))
        raise RuntimeError(f"anchors {missing} lack drapes; finish the build (or ask for a partial database)")
    if not complete:
        raise RuntimeError("no anchor has all its drapes yet: nothing to fit")
    means, components, ridges, ratios = [], [], [], []
    train_errors, holdout_errors, loo_errors = [], [], []

    residual = isinstance(garment.binding, SurfaceBinding)  # .mhclo clothes have no surface binding to store

    def skinned(beta, pose):  # the garment fitted to beta, skinned to pose: what the residual basis subtracts
        return posed_scene(body, garment, beta, pose)[1] if residual else np.zeros((garment.n_vertices, 3))

    for s in complete:
        pose = plan["anchors"][s]
        drapes = np.stack([store.load(f"anchor_{s:04d}_{k:02d}") for k in range(n_shapes)])
        base = np.stack([skinned(beta, pose) for beta in plan["shapes"]])
        model = fit_shape_model(drapes - base, plan["shapes"], plan["beta0"], plan["scale"], config.components)
        means.append(model.mean)
        components.append(model.components)
        ridges.append(model.ridge)
        ratios.append(model.explained_variance_ratio)
        train_errors.append(np.linalg.norm(model.predict(plan["shapes"]) + base - drapes, axis=2).mean())
        # held out in turn: each shape but beta0, predicted by the model fitted to the other 16 (no extra drapes)
        for k in range(1, n_shapes):
            keep = np.arange(n_shapes) != k
            loo = fit_shape_model((drapes - base)[keep], plan["shapes"][keep], plan["beta0"], plan["scale"],
                                  config.components)
            predicted = loo.predict(plan["shapes"][k])[0] + base[k]
            loo_errors.append(np.linalg.norm(predicted - drapes[k], axis=1).mean())
        if store.has(f"holdout_{s:04d}_00"):
            truth = store.load(f"holdout_{s:04d}_00")
            predicted = model.predict(plan["holdout_beta"])[0] + skinned(plan["holdout_beta"], pose)
            holdout_errors.append(np.linalg.norm(predicted - truth, axis=1).mean())
    # pose-model examples: every anchor's beta0 drape and the extra example poses, as far as they are draped
    example_keys = [(pose, f"anchor_{s:04d}_00") for s, pose in enumerate(plan["anchors"])]
    example_keys += [(pose, f"example_{m:04d}_00") for m, pose in enumerate(plan["examples"])]
    example_keys = [(pose, key) for pose, key in example_keys if store.has(key)]
    example = np.stack([store.load(key) for _, key in example_keys])
    sequence = []
    for t in range(len(plan["sequence"])):
        if not store.has(f"sequence_{t:04d}_00"):
            break  # only a complete prefix is a sequence
        sequence.append(store.load(f"sequence_{t:04d}_00"))
    drape_stats = [store.stats(p.stem) for p in sorted(store.folder.glob("*.npz"))]
    report = dict(plan["report"])
    report.update(
        partial=len(complete) < n_anchors or len(example_keys) < n_anchors + len(plan["examples"])
        or len(sequence) < len(plan["sequence"]),
        anchors_planned=n_anchors,
        anchors_fitted=len(complete),
        shape_model_train_error_mm=float(np.mean(train_errors) * 1e3),
        shape_model_holdout_error_mm=float(np.mean(holdout_errors) * 1e3) if holdout_errors else None,
        shape_model_leave_one_out_error_mm=float(np.mean(loo_errors) * 1e3) if loo_errors else None,
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
        anchor_poses=plan["anchors"][complete],
        training_betas=plan["shapes"],
        pca_mean=np.stack(means),
        pca_components=np.stack(components),
        ridge=np.stack(ridges),
        explained_variance_ratio=np.stack(ratios),
        example_poses=np.stack([pose for pose, _ in example_keys]),
        example_drapes=example,
        sequence_poses=plan["sequence"][: len(sequence)] if sequence else None,
        sequence_root_translation=np.zeros((len(sequence), 3)) if sequence else None,
        sequence_drapes=np.stack(sequence) if sequence else None,
        sequence_fps=config.sequence_fps,
        **(dict(shape_basis="skinned_residual", binding_triangles=garment.binding.triangles,
                binding_barycentric=garment.binding.barycentric, binding_offset=garment.binding.offset,
                binding_surface=garment.surface) if residual else {}),
        body_model="anny-0.6.2/cmu_mb (hm08)",
        build_command=command,
        provenance={
            "config": asdict(config),
            "drape_environment": environment,
            "report": report,
            "python": sys.version.split()[0],
            "machine": platform.machine(),
            "built_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    )
    return db, report


def build_database(config: BuildConfig, out, workers: int = 2, scheduler: str | None = None,
                   progress: bool = True, command: str | None = None, partial: bool = False,
                   seed_drapes=None, pack_drapes=None) -> dict:
    """Run (or resume) a build; writes `out` and returns the report.

    partial: drape nothing, write a database from the drapes finished so far (fit_database(partial=True)).
    seed_drapes: a pack (DrapeStore.pack) of this build's finished drapes to start from, e.g. from another machine.
    pack_drapes: pack every finished drape into this file, every PACK_EVERY drapes and at the end, so the build can
        continue elsewhere (with `partial`: the drapes finished so far, while another run of the same build goes on).
    """
    out = Path(out)
    work = out.with_name(out.name + ".work")
    work.mkdir(parents=True, exist_ok=True)
    body = AnnyBody()
    plan, key = _load_or_make_plan(config, body, work)
    store = DrapeStore(work / "drapes")
    # a build that packs into the file it was seeded from starts that file the first time
    first_pack = bool(pack_drapes and seed_drapes and Path(seed_drapes) == Path(pack_drapes)
                      and not Path(seed_drapes).exists())
    if seed_drapes and not first_pack:
        try:
            store.unpack(seed_drapes, config.plan_key(), key["environment"])
        except ValueError as error:
            raw = replace(config, repair_flips=False).plan_key()
            if config.repair_flips and read_drape_pack(seed_drapes)["plan_key"] == raw:  # made on the raw clips
                raise ValueError(f"{error}\n  (its drapes were made on the clips as recorded: add --raw-clips, "
                                 "as the shipped databases need)") from None
            raise

    def pack():
        store.pack(pack_drapes, config.plan_key(), key["environment"])

    if not partial:
        run_jobs(_jobs(config, plan), store, workers, scheduler, progress, pack=pack if pack_drapes else None)
    if pack_drapes:  # before fitting: the finished drapes travel even when too few anchors are complete to fit
        pack()
    command = command or "agentdress " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    db, report = fit_database(config, plan, store, body, command, partial=partial, environment=key["environment"])
    write_database(out, db)
    return report
