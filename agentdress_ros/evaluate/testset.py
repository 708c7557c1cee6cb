"""The held-out test set of `agentdress eval`: poses from CMU clips the database never saw x body shapes inside and
just outside its training range, with newton ground-truth drapes cached on disk (resumable like a build).

`make_held_out_set(db, body, garment, HeldOutConfig, cache) -> HeldOutSet`. The drapes run through the build's job
machinery (`offline.jobs`, `offline.builder.run_jobs`): one file per drape under `<cache>/drapes`, written atomically;
kill it and rerun, and only the missing drapes are simulated. For each pose the first shape is draped from the
skinned garment and the others warm-start from that drape, as in the build.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..sim.settings import WARM_DRAPE

# CMU clips kept out of the default database's pose set (walk, brisk walk, dance with arms high, basketball shot,
# run): real motion the database has never seen.
HELD_OUT_CLIPS = ("02_01", "07_12", "05_12", "06_14", "09_01")


def default_clip_paths(root: Path | None = None) -> list[Path]:
    """The held-out clips under ../shared/mocap/cmu (beside the repository), in HELD_OUT_CLIPS order."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[3] / "shared" / "mocap" / "cmu"
    return [root / f"{name}.bvh" for name in HELD_OUT_CLIPS]


def default_cache(database, test_set: str = "v1") -> Path:
    """The folder of a held-out set's drapes for a database file when none is given: one per set, since a set's
    cache refuses another set's poses."""
    return Path("out/eval-cache-v2" if test_set == "v2" else "out/eval-cache") / Path(database).stem


def held_out_v2(root: Path | None = None) -> "HeldOutConfig":
    """The ground truth v2 test set: 4 poses from each of the 10 test clips of ../shared/mocap/README.md x 3 shapes
    (2 inside the training range, 1 just outside), draped with the animated collider (the body carried from rest
    into each pose), and dynamic sequences of 300 frames (30 fps) along two test clips, 02_08 (swordplay) and 05_12
    (dance, arms high), at beta0 and at the first inside shape."""
    from ..offline.sequences import TEST_CLIPS

    root = Path(root) if root is not None else default_clip_paths()[0].parent
    return HeldOutConfig(clips=[root / f"{name}.bvh" for name in TEST_CLIPS], poses_per_clip=4,
                         drape={"ramp_frames": 30}, dynamic_clips=[root / "02_08.bvh", root / "05_12.bvh"])


@dataclass
class HeldOutConfig:
    clips: list = field(default_factory=list)  # .bvh paths; the poses and the timing/jitter sequence come from them
    poses_per_clip: int = 2
    shapes_inside: int = 2  # random shapes inside the database's training range
    shapes_outside: int = 1  # shapes with one trained phenotype `outside_margin` beyond the range
    outside_margin: float = 0.05
    sequence_frames: int = 120  # frames (at 30 fps) of the first clip for timing and temporal jitter
    drape: dict = field(default_factory=dict)  # DrapeSettings overrides
    warm_drape: dict = field(default_factory=lambda: dict(WARM_DRAPE))
    seed: int = 0
    dynamic_clips: list = field(default_factory=list)  # .bvh paths simulated as whole sequences (sim.sequence)
    dynamic_frames: int = 300  # frames (30 fps) of each dynamic sequence
    dynamic_shapes: int = 2  # beta0, then the first shapes of the static set


@dataclass
class HeldOutSet:
    poses: np.ndarray  # (P, B, 3) canonical (root rotation removed) held-out poses
    pose_labels: list  # "02_01@120" = clip and frame
    betas: np.ndarray  # (S, 6)
    shape_labels: list  # "inside" / "outside"
    drapes: np.ndarray  # (P, S, V, 3) newton ground truth
    sequence: np.ndarray  # (T, B, 3) held-out motion (root rotation kept) for timing and jitter
    sequence_root: np.ndarray  # (T, 3)
    drape_stats: list  # per drape: frames, converged, seconds, inside_count, ...
    dynamic: list = field(default_factory=list)  # per dynamic sequence: {"label", "beta", "positions" (T, V, 3),
    # "rotvecs" (T, B, 3), "root_translation" (T, 3)}: newton ground truth along a held-out clip, root motion kept


def held_out_shapes(db, config: HeldOutConfig) -> tuple[np.ndarray, list]:
    """(S, 6) shapes and their labels: uniform inside the training range, then just outside it (one trained
    phenotype past its low or high end by `outside_margin`, cycling through the phenotypes whose range leaves room
    inside Anny's [0, 1])."""
    from ..body.training_shapes import trained_phenotypes, uniform_shapes

    rng = np.random.default_rng(config.seed)
    low, high = np.asarray(db.beta_range, dtype=np.float64).T
    trained = trained_phenotypes(db.beta_range)

    def random_inside():
        return uniform_shapes(db.beta0, db.beta_range, 1, rng)[0]

    betas = [random_inside() for _ in range(config.shapes_inside)]
    labels = ["inside"] * len(betas)
    # only phenotypes whose training range leaves room in [0, 1] can be exceeded (gender spans all of it)
    room = [p for p in trained if high[p] + config.outside_margin <= 1.0 or low[p] - config.outside_margin >= 0.0]
    for i in range(config.shapes_outside if room else 0):
        beta = random_inside()
        p = room[i % len(room)]
        above = high[p] + config.outside_margin
        beta[p] = above if above <= 1.0 else low[p] - config.outside_margin
        betas.append(beta)
        labels.append("outside")
    return np.array(betas).reshape(-1, len(db.beta0)), labels


def _check_held_out(db, clips) -> None:
    built_from = {Path(c).stem for c in db.provenance.get("config", {}).get("clips", [])}
    overlap = sorted(built_from & {Path(c).stem for c in clips})
    if overlap:
        raise ValueError(f"clips {overlap} were used to build the database: a test set must be held out")


def held_out_poses(body, config: HeldOutConfig):
    """(poses (P, B, 3) canonical, labels, sequence (T, B, 3), sequence root (T, 3)) from the held-out clips."""
    from ..offline.anchors import canonical_poses
    from ..motion.retarget import load_cmu_motion

    reference = body.shape()
    poses, labels, sequence = [], [], None
    for clip in config.clips:
        motion = load_cmu_motion(clip, reference.heads, reference.tails)
        n = motion.num_frames
        frames = np.linspace(0.15 * n, 0.85 * n, config.poses_per_clip).round().astype(int)
        poses.append(canonical_poses(motion.rotvecs[frames]))
        labels += [f"{Path(clip).stem}@{f}" for f in frames]
        if sequence is None:  # 120 fps clips, taken at 30 fps as the build's pose set
            step = max(1, int(round(motion.fps / 30.0)))
            sequence = (motion.rotvecs[::step][: config.sequence_frames],
                        motion.root_translation[::step][: config.sequence_frames])
    if sequence is None:
        raise ValueError("the test set needs at least one held-out clip")
    return np.concatenate(poses), labels, sequence[0], sequence[1]


def test_set_key(db, config: HeldOutConfig, betas) -> str:
    """The plan key of a test set's drapes (its cache stamp and its pack's key)."""
    fields = asdict(config)
    if not config.dynamic_clips:  # a static set keeps the key it had before dynamic sequences existed
        fields = {k: v for k, v in fields.items() if not k.startswith("dynamic_")}
    return json.dumps({"garment": db.garment, "vertices": db.n_vertices, **fields,
                       "clips": [Path(c).stem for c in config.clips], "betas": np.round(betas, 9).tolist()},
                      sort_keys=True, default=str)


def static_jobs(db, config: HeldOutConfig, poses, betas) -> list:
    """The drape jobs of the static cases, "test_<pose>_<shape>": each pose's first shape draped from the skinned
    garment (or from rest, with a ramp), the others warm-started from it."""
    from ..offline.jobs import DrapeJob

    common = dict(garment=db.garment, garment_vertices=db.n_vertices, settings=config.drape)
    warm_settings = {**config.drape, **config.warm_drape}
    jobs = []
    for p, pose in enumerate(poses):
        for k, beta in enumerate(betas):
            warm = {} if k == 0 else dict(warm_key=f"test_{p:04d}_00", warm_pose=pose, warm_beta=betas[0],
                                          settings=warm_settings)
            jobs.append(DrapeJob("test", p, k, pose, beta, **{**common, **warm}))
    return jobs


def make_held_out_set(db, body, garment, config: HeldOutConfig, cache, workers: int = 2, progress: bool = True,
                      pack=None) -> HeldOutSet:
    """Poses, shapes and ground-truth drapes of the test set (drapes from `cache` when present, else simulated).

    pack: a file of packed drapes (DrapeStore.pack) of this test set: read first when it exists, rewritten as the
    drapes finish and after, so the ground truth can travel with the report instead of being simulated again.
    """
    from ..offline.builder import run_jobs
    from ..offline.jobs import DrapeStore

    if not config.clips:
        raise ValueError("no held-out clips given")
    missing = [str(c) for c in config.clips if not Path(c).is_file()]
    if missing:
        raise FileNotFoundError(f"held-out clips not found: {missing}")
    _check_held_out(db, config.clips)
    if garment.faces.shape != db.faces.shape or not np.array_equal(garment.faces, db.faces):
        raise ValueError(f"garment {db.garment!r} at {db.n_vertices} vertices does not reproduce the database's "
                         "topology; the ground truth would not match it vertex for vertex")
    poses, labels, sequence, sequence_root = held_out_poses(body, config)
    betas, shape_labels = held_out_shapes(db, config)

    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    key = test_set_key(db, config, betas)
    stamp = cache / "testset.json"
    if stamp.is_file() and stamp.read_text() != key:
        raise ValueError(f"{cache}: this cache holds another test set; use another --cache or delete it.\n"
                         f"  stored:    {stamp.read_text()}\n  requested: {key}")
    stamp.write_text(key)

    jobs = static_jobs(db, config, poses, betas)
    store = DrapeStore(cache / "drapes")
    if pack is not None and Path(pack).is_file():
        store.unpack(pack, key)
    if pack is not None:
        Path(pack).parent.mkdir(parents=True, exist_ok=True)
    run_jobs(jobs, store, workers=workers, progress=progress,
             pack=None if pack is None else lambda: store.pack(pack, key))
    if pack is not None:
        store.pack(pack, key)
    drapes = np.stack([np.stack([store.load(f"test_{p:04d}_{k:02d}") for k in range(len(betas))])
                       for p in range(len(poses))])
    stats = [store.stats(job.key) for job in jobs]
    dynamic = held_out_sequences(db, body, garment, config, betas, cache / "dynamic", progress=progress)
    return HeldOutSet(poses, labels, betas, shape_labels, drapes, sequence, sequence_root, stats, dynamic)


def held_out_sequences(db, body, garment, config: HeldOutConfig, betas, folder, progress: bool = True) -> list:
    """Dynamic ground truth along config.dynamic_clips (simulated once into `folder`, resumable by chunks) at beta0
    and the first static shapes; see HeldOutSet.dynamic."""
    from ..motion.retarget import load_cmu_motion
    from ..motion.skeleton import Motion
    from ..sim.sequence import SequenceSettings, load_sequence, resample, simulate_sequence
    from ..sim.settings import DrapeSettings

    drape = DrapeSettings(**{k: v for k, v in config.drape.items() if k != "ramp_frames"})
    # the sequence reaches its first pose the way the static drapes reach theirs: the same ramp, and settles there
    # within their frame budget (v1 and v2: the sequence defaults, 30 and 120; the quick set: 8 and 30)
    default = SequenceSettings()
    settings = SequenceSettings(drape=drape, ramp_frames=config.drape.get("ramp_frames", default.ramp_frames),
                                settle_frames=min(default.settle_frames, drape.max_frames))
    shapes = [np.asarray(db.beta0, dtype=np.float64)] + [b for b in betas[: max(0, config.dynamic_shapes - 1)]]
    sequences = []
    for clip in config.dynamic_clips:
        for k, beta in enumerate(shapes):
            shape = body.shape(beta)
            motion = load_cmu_motion(clip, shape.heads, shape.tails)
            rotvecs, roots = resample(motion, settings.fps)
            motion = Motion(rotvecs[: config.dynamic_frames], roots[: config.dynamic_frames], settings.fps,
                            name=Path(clip).stem)
            path = Path(folder) / f"{Path(clip).stem}_{k:02d}"
            simulate_sequence(motion, garment, beta, path, settings, body=body, progress=progress)
            data = load_sequence(path)
            sequences.append({"label": f"{Path(clip).stem} {'beta0' if k == 0 else f'shape {k}'}",
                              "beta": beta, "positions": data["positions"], "rotvecs": data["rotvecs"],
                              "root_translation": data["root_translation"]})
    return sequences
