"""`agentdress eval`: the speed-accuracy trade of the runtime engine, measured against newton ground truth.

For every configuration (a row of the trade table) and in one run: the mean and 95th-percentile vertex error (cm)
against the held-out drapes (evaluate.testset), the share of garment vertices inside the body (by winding number,
split into the body's self-overlap and truly through the skin), the milliseconds
per frame on a held-out motion (one thread, the best of the per-pass medians, passes interleaved across the rows),
and the temporal jitter on that motion (mean vertex acceleration, mm per frame^2). Each mean error comes with a
95 % bootstrap interval over the test cases (the (pose, shape) pairs resampled, the same resamples for every row);
rows whose intervals overlap are indistinguishable on this test set. Writes report.json, trade.md and PNG plots
(Pareto front, error vs anchors as in the paper's Fig. 9, error vs distance of the shape from beta0) and a
stability report of extreme inputs through the full pipeline. Rows that lose to the skinned baseline are listed,
not hidden.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

BASELINE = "skinned template fitted to beta (no database)"
BOOTSTRAP_DRAWS = 4000


@dataclass
class Row:
    """One configuration of the trade table: `config` is an EngineConfig's fields, or None for the baseline."""

    name: str
    group: str
    config: dict | None = None
    results: dict = field(default_factory=dict)


#: Candidate body vertices at rest of the body-projection rows (EngineConfig.projection; each vertex also searches
#: its projection_examples nearest at every example pose, thinned by projection_spacing): the node default's.
PROJECTION = 8


def trade_rows(n_anchors: int, n_components: int, regressor: bool = False, santesteban: bool = False,
               kdsm: bool = False, recurrent: bool = False, shape_residual: dict | None = None) -> list[Row]:
    """The rows of the trade table (the anchors' K and the examples pose model's K in {1, 3, 5, 8}, components in
    {2, 5, 10}, penetration and decay off/on, the Sec. 4.6 ablation, float32/64) plus the Fig. 9 anchor sweep: N
    anchors restrict both the shape models and the pose model's examples to those anchors (their beta0 drapes),
    the pose model's K staying 5 (capped at N). With `regressor` (the database has one), the learned pose model
    alone and in synthesis, with and without its anchor residuals folded into the shape deltas. With `santesteban`
    (the database has garment_model/santesteban), Santesteban et al.'s own system (engine.santesteban). With `kdsm`
    (pose_model/kdsm), the `kdsm` pose model alone and in synthesis; with `recurrent` (pose_model/recurrent), the
    `recurrent` pose model alone and in synthesis. With `shape_residual` (shape_residual_config: the configuration
    the database's shape_model/residual was trained against, the residual on), that synthesis."""
    # sweeps around the node's default (the examples pose model, the most accurate measured)
    base = {"pose_model": "examples"}
    rows = [
        Row(BASELINE, "baseline"),
        Row("lbs pose model alone (beta0 garment, no shape model)", "pose model", {"shape_model": False}),
        Row("examples pose model alone (beta0 drapes, no shape model)", "pose model",
            {"shape_model": False, **base}),
        Row("synthesis (node default: examples pose model, K=5 anchors and K=5 examples per region, all anchors "
            "and examples, 5 components, float32)", "default", dict(base)),
        Row("synthesis with the lbs pose model (library default)", "pose model", {}),
    ]
    rows += [Row(f"synthesis, anchors' K={k}", "neighbors", {**base, "neighbors": k}) for k in (1, 3, 8)]
    rows += [Row(f"synthesis, pose model's K={k}", "pose neighbors", {**base, "pose_neighbors": k})
             for k in (1, 3, 8)]
    for count in sorted({c for c in (1, 2, 4, 8, 16, 32) if c < n_anchors} | {n_anchors}):
        rows.append(Row(f"synthesis, {count} anchor{'s' if count > 1 else ''} (shape models and pose-model "
                        "examples)", "anchors",
                        {**base, "anchors": count}))
    for c in (2, 10):
        if c < n_components or (c > 5 and n_components > 5):
            rows.append(Row(f"synthesis, {min(c, n_components)} PCA components", "components",
                            {**base, "components": min(c, n_components)}))
    rows += [
        Row("synthesis, penetration handling off", "refinement", {**base, "penetration": False}),
        Row(f"synthesis, body projection ({PROJECTION} candidates)", "refinement", {**base, "projection": PROJECTION}),
        Row("synthesis, decay off", "refinement", {**base, "decay": False}),
        Row("synthesis, penetration and decay off", "refinement", {**base, "penetration": False, "decay": False}),
        Row("ablation Sec. 4.6: no first-order term (blend of the anchors' re-posed f(beta, theta_s))", "ablation",
            {"taylor": "zeroth"}),
        Row("synthesis, plain Taylor (Eq. 2, deltas not re-posed)", "ablation", {**base, "taylor": "plain"}),
        Row("synthesis, float64", "precision", {**base, "dtype": "float64"}),
    ]
    if regressor:
        rows += [
            Row("regressor pose model alone (beta0 garment, no shape model)", "regressor",
                {"pose_model": "regressor", "shape_model": False}),
            Row("synthesis with the regressor pose model (anchor residuals folded into the shape deltas)",
                "regressor", {"pose_model": "regressor"}),
            Row("synthesis with the regressor pose model, no fold", "regressor",
                {"pose_model": "regressor", "fold": False}),
            Row(f"synthesis with the regressor pose model, no fold, body projection ({PROJECTION} candidates)",
                "regressor", {"pose_model": "regressor", "fold": False, "projection": PROJECTION}),
        ]
    if recurrent:
        rows += [
            Row("recurrent pose model alone (beta0 garment, no shape model)", "recurrent",
                {"pose_model": "recurrent", "shape_model": False}),
            Row("synthesis with the recurrent pose model", "recurrent", {"pose_model": "recurrent"}),
        ]
    if kdsm:
        rows += [
            Row("kdsm pose model alone (beta0 garment, no shape model)", "kdsm",
                {"pose_model": "kdsm", "shape_model": False}),
            Row("synthesis with the kdsm pose model", "kdsm", {"pose_model": "kdsm"}),
            Row(f"synthesis with the kdsm pose model, body projection ({PROJECTION} candidates)", "kdsm",
                {"pose_model": "kdsm", "projection": PROJECTION}),
        ]
    if shape_residual is not None:
        trained = ", ".join(f"{k}={v}" for k, v in sorted(shape_residual.items()) if k != "shape_residual")
        rows.append(Row(f"synthesis with the shape residual ({trained or 'the library defaults'}, the configuration "
                        "it was trained against)", "shape residual", dict(shape_residual)))
    if santesteban:
        rows.append(Row("Santesteban et al. 2019 system (fit and wrinkle regressors, own skinning, push-out "
                        "post-process; no AgentDress synthesis)", "santesteban", {"model": "santesteban"}))
    return rows


#: Pose models measured alone against drapes at beta0 (evaluate.beta0), with the rows' configurations.
BETA0_ROWS = (("lbs pose model alone", {"shape_model": False}),
              ("examples pose model alone", {"shape_model": False, "pose_model": "examples"}),
              ("regressor pose model alone", {"shape_model": False, "pose_model": "regressor"}),
              ("synthesis, examples pose model (node default)", {"pose_model": "examples"}),
              ("synthesis, regressor pose model (fold)", {"pose_model": "regressor"}),
              ("kdsm pose model alone", {"shape_model": False, "pose_model": "kdsm"}),
              ("synthesis, kdsm pose model", {"pose_model": "kdsm"}))


def shape_residual_config(db) -> dict | None:
    """The EngineConfig fields of synthesis with the database's shape residual, in the configuration it was trained
    against (None without one)."""
    if db.shape_residual is None:
        return None
    return {**db.shape_residual.info.get("engine", {}), "shape_residual": True}


def beta0_report(db, body, poses, drapes) -> list[dict]:
    """Each pose model alone (and synthesis with it) at beta0 against the beta0 drapes of the held-out poses: mean and
    p95 error (cm), with a 95 % bootstrap interval over the poses (the same resamples for every row)."""
    from ..engine import Engine, EngineConfig

    rows, cases = [], []
    beta0_rows = list(BETA0_ROWS)
    if db.shape_residual is not None:  # at beta0 it should add next to nothing: its drapes are at other shapes
        beta0_rows.append(("synthesis with the shape residual", shape_residual_config(db)))
    for name, config in beta0_rows:
        if (config.get("pose_model") == "regressor" and db.regressor is None
                or config.get("pose_model") == "kdsm" and db.kdsm_model is None):
            continue
        engine = Engine(db, body, EngineConfig(**config))
        errors = np.linalg.norm(synthesize_poses(engine, np.asarray(db.beta0), poses) - np.asarray(drapes), axis=2)
        cases.append([float(e.mean() * 100.0) for e in errors])
        errors = errors.ravel()
        rows.append({"name": name, "config": config, "error_mean_cm": float(errors.mean() * 100.0),
                     "error_p95_cm": float(np.percentile(errors, 95) * 100.0)})
    intervals, _ = bootstrap_intervals(cases)
    for row, interval in zip(rows, intervals):
        row["error_mean_ci_cm"] = interval.tolist()
    return rows


def _model(row: Row, db, body, garment):
    """An object with set_shape(beta) and synthesize(rotvecs, root) -> (V, 3) for the row."""
    if row.config is None:
        from ..models.garment_models import SkinnedGarmentModel

        return SkinnedGarmentModel(garment, body)
    if row.config.get("model") == "santesteban":
        from ..engine.santesteban import SantestebanModel

        return SantestebanModel(db, body)
    from ..engine import Engine, EngineConfig

    return Engine(db, body, EngineConfig(**row.config))


def _reset(model):
    if hasattr(model, "reset"):
        model.reset()


class InsideTest:
    """Which garment vertices lie inside the posed body, by generalised winding number (garment.inside, the test
    the drapes and build reports use), split into those trapped where the skinned body overlaps itself and those
    truly through the skin. The body's winding field and self-overlap are built once per (pose, shape)."""

    def __init__(self, body, beta, pose):
        from ..body import visible_body
        from ..garment.inside import BodyInside

        shape = body.shape(beta)
        transforms, _ = body.pose(shape, pose)
        ids, faces = visible_body(body)
        self.test = BodyInside(body.posed_vertices(shape, transforms)[ids], faces)

    def shares(self, vertices) -> tuple[float, float, float]:
        """(inside, in self-overlap, truly inside): shares of the vertices (V, 3)."""
        report = self.test.report(vertices)
        n = max(len(report["inside"]), 1)
        return report["inside_count"] / n, report["overlap_count"] / n, report["truly_inside_count"] / n

    def fraction(self, vertices) -> float:
        """Share of the vertices (V, 3) inside the body."""
        return float(np.mean(self.test.inside(vertices))) if len(vertices) else 0.0


#: Garment parts the errors are reported by (vertex_parts): the skinning regions merged left with right, and the
#: torso's vertices within EDGE_BAND of an open edge split off by height.
EDGE_BAND = 0.04


def vertex_parts(db) -> tuple[list, np.ndarray]:
    """(part names, (V,) index of each vertex's part): its dominant skinning region with left and right merged
    (sleeves, legs), the torso's vertices within EDGE_BAND (geodesic) of an open edge below the garment's middle
    height as "hem", above it as "top edge" (neckline, waistband)."""
    from ..garment.coverage import boundary_distance

    merged = []
    for name in db.region_names:
        part = name.replace("left_", "").replace("right_", "")
        merged.append({"upper_arm": "sleeves", "forearm": "sleeves", "leg": "legs"}.get(part, part))
    names = list(dict.fromkeys(merged)) + ["hem", "top edge"]
    labels = np.array([names.index(merged[r]) for r in np.argmax(db.regions, axis=1)])
    rest = np.asarray(db.rest, dtype=np.float64)
    near_edge = (boundary_distance(rest, db.faces) <= EDGE_BAND) & (labels == names.index("torso"))
    middle = 0.5 * (rest[:, 2].min() + rest[:, 2].max())
    labels[near_edge & (rest[:, 2] < middle)] = names.index("hem")
    labels[near_edge & (rest[:, 2] >= middle)] = names.index("top edge")
    used = [i for i in range(len(names)) if (labels == i).any()]
    return [names[i] for i in used], np.searchsorted(used, labels)


def synthesize_poses(model, beta, poses) -> np.ndarray:
    """The model's garment (P, V, 3) for each of the independent static poses (P, B, 3) at shape beta: reset
    before each pose, so no decay history passes between them."""
    model.set_shape(beta)
    frames = []
    for pose in poses:
        _reset(model)
        # a copy: a model may return the same buffer every frame
        frames.append(np.array(model.synthesize(pose, np.zeros(3)), dtype=np.float64))
    return np.asarray(frames)


def accuracy(model, test, inside_tests, parts=None, faces=None) -> dict:
    """Errors of a model on every (pose, shape) of the test set: cm mean / p95, inside fraction, per shape, and
    the mean of each case (shape-major: case k * poses + p), which the bootstrap resamples; with parts
    (vertex_parts), the mean by part and the mean of each vertex over the cases ("vertex_error_cm", for the error
    pictures: dropped from the report). With faces (F, 3), the share of face centres inside the body too: where
    skin shows through flat triangles although their vertices are outside."""
    errors, inside, inside_faces, per_shape = [], [], [], []
    for k, beta in enumerate(test.betas):
        shape_errors = []
        for p, out in enumerate(synthesize_poses(model, beta, test.poses)):
            error = np.linalg.norm(out - test.drapes[p, k], axis=1)
            errors.append(error)
            shape_errors.append(error.mean())
            inside.append(inside_tests[p][k].shares(out))
            if faces is not None:
                inside_faces.append(inside_tests[p][k].fraction(out[faces].mean(axis=1)))
        per_shape.append(float(np.mean(shape_errors) * 100.0))
    cases = [float(e.mean() * 100.0) for e in errors]
    per_vertex = np.mean(errors, axis=0) * 100.0
    errors = np.concatenate(errors)
    inside = np.mean(inside, axis=0)
    out = {"error_mean_cm": float(errors.mean() * 100.0), "error_p95_cm": float(np.percentile(errors, 95) * 100.0),
           "inside_fraction": float(inside[0]), "inside_overlap_fraction": float(inside[1]),
           "inside_true_fraction": float(inside[2]), "error_per_shape_cm": per_shape, "error_per_case_cm": cases}
    if faces is not None:
        out["inside_faces_fraction"] = float(np.mean(inside_faces))
    if parts is not None:
        names, labels = parts
        out["error_by_part_cm"] = {n: float(per_vertex[labels == i].mean()) for i, n in enumerate(names)}
        out["vertex_error_cm"] = per_vertex
    return out


def bootstrap_intervals(case_errors, draws: int = BOOTSTRAP_DRAWS, seed: int = 0, reference: int | None = None):
    """95 % percentile-bootstrap intervals of the mean error of each row, resampling the test cases.

    case_errors (rows, cases): each row's mean error per (pose, shape) case (every case has the same vertices, so
    their mean is the row's mean error). The same resampled case sets serve every row. Returns (intervals
    (rows, 2), differences (rows, 2)): the latter is the interval of each row's mean minus the `reference` row's
    on the same resamples (a paired comparison; None: no differences)."""
    case_errors = np.asarray(case_errors, dtype=np.float64)
    n_cases = case_errors.shape[1]
    picks = np.random.default_rng(seed).integers(0, n_cases, size=(draws, n_cases))
    means = case_errors[:, picks].mean(axis=2)  # (rows, draws)
    intervals = np.percentile(means, [2.5, 97.5], axis=1).T
    if reference is None:
        return intervals, None
    return intervals, np.percentile(means - means[reference], [2.5, 97.5], axis=1).T


def overlaps(a, b) -> bool:
    """Whether two intervals [low, high] overlap."""
    return bool(a[0] <= b[1] and b[0] <= a[1])


def speed_and_jitter(models, test, beta, repeats: int = 3) -> list[dict]:
    """ms per frame (best of `repeats` per-pass medians over the held-out motion) and the mean vertex acceleration
    (mm / frame^2) of the output along it (first pass), at shape beta, for each model. The passes are interleaved
    (pass r of every model before pass r + 1 of any), so that load from other processes falls on every row alike."""
    for model in models:
        model.set_shape(beta)
    medians = np.empty((repeats, len(models)))
    jitter = []
    for r in range(repeats):
        for m, model in enumerate(models):
            _reset(model)
            times, frames = [], []
            for pose, root in zip(test.sequence, test.sequence_root):
                start = time.perf_counter()
                out = model.synthesize(pose, root)
                times.append(time.perf_counter() - start)
                if r == 0:
                    frames.append(np.array(out, dtype=np.float64))
            medians[r, m] = np.median(times)
            if r == 0:
                frames = np.stack(frames)
                acceleration = np.linalg.norm(frames[2:] - 2 * frames[1:-1] + frames[:-2], axis=2)
                jitter.append(float(acceleration.mean() * 1e3) if len(frames) > 2 else 0.0)
    return [{"ms_per_frame": float(medians[:, m].min() * 1e3), "jitter_mm": jitter[m]} for m in range(len(models))]


def _jitter_mm(frames: np.ndarray) -> float:
    """Mean vertex acceleration (mm / frame^2) of frames (T, V, 3)."""
    if len(frames) < 3:
        return 0.0
    return float(np.linalg.norm(frames[2:] - 2 * frames[1:-1] + frames[:-2], axis=2).mean() * 1e3)


def temporal_report(models, names, sequences) -> list[dict]:
    """Along each dynamic ground-truth sequence (HeldOutSet.dynamic): every model's mean error per frame (cm) and
    its jitter against the ground truth's own (mm / frame^2), decay history kept from frame to frame."""
    report = []
    for sequence in sequences:
        truth = np.asarray(sequence["positions"], dtype=np.float64)
        entry = {"sequence": sequence["label"], "frames": int(len(truth)), "truth_jitter_mm": _jitter_mm(truth),
                 "rows": []}
        for name, model in zip(names, models):
            model.set_shape(sequence["beta"])
            _reset(model)
            out = np.stack([np.array(model.synthesize(pose.astype(np.float64), root.astype(np.float64)),
                                     dtype=np.float64)
                            for pose, root in zip(sequence["rotvecs"], sequence["root_translation"])])
            error = np.linalg.norm(out - truth, axis=2).mean(axis=1) * 100.0
            entry["rows"].append({"name": name, "error_mean_cm": float(error.mean()),
                                  "error_max_frame_cm": float(error.max()), "jitter_mm": _jitter_mm(out)})
        report.append(entry)
    return report


def stability_report(db, body, garment) -> list[dict]:
    """The engine's extreme inputs through the full pipeline (default config): for each case the largest distance
    (cm) from the skinned template at the same pose and (effective) shape, non-finite outputs and rejected frames."""
    from ..engine import Engine, EngineConfig
    from ..models.garment_models import SkinnedGarmentModel

    rng = np.random.default_rng(1)
    n_bones = len(db.bone_names)
    low, high = np.asarray(db.beta_range, dtype=np.float64).T
    beta0 = np.asarray(db.beta0, dtype=np.float64)
    near_pi = np.zeros((n_bones, 3))
    near_pi[1:, 0] = np.pi - 1e-7
    wrapped = np.asarray(db.anchor_poses[0], dtype=np.float64).copy()
    norms = np.linalg.norm(wrapped, axis=1, keepdims=True)
    wrapped = np.where(norms > 0, wrapped * (1.0 + 2.0 * np.pi / np.maximum(norms, 1e-12)), wrapped)
    jump = np.asarray(db.anchor_poses[0], dtype=np.float64).copy()
    jump_to = jump.copy()
    jump_to[list(db.bone_names).index("LeftArm")] += np.array([np.pi, 0.0, 0.0])
    far = rng.uniform(-3.0, 3.0, size=(n_bones, 3))
    far[0] = 0.0
    subnormal = np.full((n_bones, 3), 1e-310)
    cases = [
        ("beta at the low end of the training range", low, [db.anchor_poses[0]], None),
        ("beta at the high end of the training range", high, [db.anchor_poses[0]], None),
        ("beta beyond the training range (all 0, clamped)", np.zeros_like(beta0), [db.anchor_poses[0]], None),
        ("beta beyond the training range (all 1, clamped)", np.ones_like(beta0), [db.anchor_poses[0]], None),
        ("every joint at pi - 1e-7", beta0, [near_pi], None),
        ("an anchor's pose wrapped by 2 pi", beta0, [wrapped], None),
        ("pose exactly at an anchor (D = 0)", beta0, [db.anchor_poses[0]], None),
        ("all anchors far away (random angles up to 3 rad)", beta0, [far], None),
        ("180-degree jump of the left arm in one frame", beta0, [jump, jump_to], None),
        ("subnormal joint angles (1e-310)", beta0, [subnormal], None),
        ("huge root translation (1e30 m, clamped to 1e4)", beta0, [db.anchor_poses[0]], np.full(3, 1e30)),
    ]
    engine = Engine(db, body, EngineConfig())
    skinned = SkinnedGarmentModel(garment, body)
    report = []
    for name, beta, poses, root in cases:
        shape_report = engine.set_shape(beta)
        skinned.set_shape(shape_report.effective)
        engine.reset()
        deviation, non_finite = 0.0, 0
        bad_before = engine.bad_frames
        for pose in poses:
            pose = np.asarray(pose, dtype=np.float64)
            root_in = np.zeros(3) if root is None else root
            out = np.array(engine.synthesize(pose, root_in), dtype=np.float64)
            non_finite += int(np.count_nonzero(~np.isfinite(out)))
            clamped_root = np.clip(root_in, -engine.config.max_root_translation, engine.config.max_root_translation)
            reference = np.asarray(skinned.synthesize(pose, clamped_root), dtype=np.float64)
            distance = np.linalg.norm(out - reference, axis=1).max() if np.isfinite(out).all() else np.inf
            deviation = max(deviation, float(distance * 100.0))
        report.append({"case": name, "max_deviation_from_skinned_cm": deviation, "non_finite": non_finite,
                       "rejected_frames": engine.bad_frames - bad_before, "clamped": list(shape_report.clamped_names)})
    return report


def held_out_config(test_set: str = "v1", clips=None, quick: bool = False, drape: dict | None = None,
                    overrides: dict | None = None):
    """The HeldOutConfig of a test set: v1 (static collider, `clips` or the 5 default held-out clips) or v2
    (evaluate.testset.held_out_v2); quick: one pose of the first clip, two shapes, short drapes (a smoke test);
    drape: DrapeSettings overrides; overrides: HeldOutConfig fields to replace."""
    from .testset import HeldOutConfig, default_clip_paths, held_out_v2

    clips = [Path(c) for c in (clips or default_clip_paths())]
    if quick:
        config = HeldOutConfig(clips=clips[:1], poses_per_clip=1, shapes_inside=1, shapes_outside=1,
                               sequence_frames=30, drape={"max_frames": 20, **(drape or {})})
        if test_set == "v2":  # the same, with a short ramp and a short dynamic sequence
            config.drape["ramp_frames"] = 8
            config.dynamic_clips, config.dynamic_frames, config.dynamic_shapes = clips[:1], 4, 1
    elif test_set == "v2":  # animated-collider drapes of all 10 test clips, and dynamic sequences
        config = held_out_v2()
        config.drape.update(drape or {})
    else:
        config = HeldOutConfig(clips=clips, drape=drape or {})
    for key, value in (overrides or {}).items():
        if key not in HeldOutConfig.__dataclass_fields__:
            raise ValueError(f"--test-config: {key!r} is not a test-set field "
                             f"({', '.join(HeldOutConfig.__dataclass_fields__)})")
        setattr(config, key, [Path(v) for v in value] if key in ("clips", "dynamic_clips") else value)
    return config


def evaluate(db_path, out_dir, cache, clips=None, quick: bool = False, workers: int = 2, progress: bool = True,
             drape: dict | None = None, pack=None, test_set: str = "v1", beta0_pack=None,
             test_config: dict | None = None, beta0: bool | None = None) -> dict:
    """Build (or reuse) the held-out set, measure every row, write report.json, trade.md and the plots.

    pack: file of the held-out ground-truth drapes, read when present and rewritten (see make_held_out_set).
    beta0_pack: file of the held-out poses' drapes at beta0 (evaluate.beta0), for the pose models alone at beta0:
    read when present, else simulated and written when `beta0` says so (None: for a full v1 set, 10 drapes; a v2
    set has 40).
    test_config: HeldOutConfig fields to override in the chosen test set (e.g. {"poses_per_clip": 1,
    "dynamic_clips": []} for a smaller one)."""
    from ..body import AnnyBody
    from ..engine import read_database
    from ..garment import make_garment
    from .testset import make_held_out_set

    db = read_database(db_path)
    body = AnnyBody()
    garment = make_garment(db.garment, body, db.n_vertices)
    config = held_out_config(test_set, clips, quick, drape, test_config)
    simulate_beta0 = (test_set == "v1" and not quick) if beta0 is None else beta0
    start = time.perf_counter()
    test = make_held_out_set(db, body, garment, config, cache, workers=workers, progress=progress, pack=pack)
    ground_truth_seconds = time.perf_counter() - start
    inside_tests = [[InsideTest(body, beta, pose) for beta in test.betas] for pose in test.poses]
    # the same measure on the ground truth itself: what a perfect model would score
    cases = [(p, k) for p in range(len(test.poses)) for k in range(len(test.betas))]
    truth_inside = np.mean([inside_tests[p][k].shares(test.drapes[p, k]) for p, k in cases], axis=0)
    truth_faces = float(np.mean([inside_tests[p][k].fraction(test.drapes[p, k][db.faces].mean(axis=1))
                                 for p, k in cases]))

    rows = trade_rows(db.n_anchors, db.n_components, regressor=db.regressor is not None,
                      santesteban=db.santesteban is not None, kdsm=db.kdsm_model is not None,
                      recurrent=db.recurrent is not None,
                      shape_residual=shape_residual_config(db))
    repeats = 1 if quick else 3
    from tqdm import tqdm

    with threadpool_limits(limits=1):
        models = []
        parts = vertex_parts(db)
        for row in tqdm(rows, desc="configurations", disable=not progress):
            models.append(_model(row, db, body, garment))
            row.results = accuracy(models[-1], test, inside_tests, parts, db.faces)
        for row, timing in zip(rows, speed_and_jitter(models, test, test.betas[0], repeats=repeats)):
            row.results.update(timing)
        stability = stability_report(db, body, garment)
        temporal = temporal_report(models, [r.name for r in rows], test.dynamic)
        beta0, pose_share = [], []
        if beta0_pack is not None and (Path(beta0_pack).is_file() or simulate_beta0):
            from .beta0 import held_out_beta0

            drapes, poses, _ = held_out_beta0(db, body, garment, config, cache, workers=workers, progress=progress,
                                              pack=beta0_pack)
            beta0 = beta0_report(db, body, poses, drapes)
            if len(poses) == len(test.poses) and np.allclose(np.asarray(poses), np.asarray(test.poses)):
                synthesis = [i for i, r in enumerate(rows) if r.group in ("default", "regressor", "recurrent", "kdsm")
                             and r.config.get("shape_model", True)]
                pose_share = pose_model_share([rows[i] for i in synthesis], [models[i] for i in synthesis], test,
                                              np.asarray(db.beta0), np.asarray(drapes))

    baseline = rows[0].results
    default = next(i for i, r in enumerate(rows) if r.group == "default")
    intervals, differences = bootstrap_intervals([r.results["error_per_case_cm"] for r in rows], reference=default)
    for row, interval, difference in zip(rows, intervals, differences):
        row.results["error_mean_ci_cm"] = interval.tolist()
        row.results["error_vs_default_ci_cm"] = difference.tolist()
        # better or worse than the baseline only when the intervals do not overlap
        row.results["beats_baseline"] = bool(interval[1] < intervals[0][0])
        row.results["vs_baseline"] = ("baseline" if row is rows[0] else "better" if row.results["beats_baseline"]
                                      else "worse" if interval[0] > intervals[0][1] else "indistinguishable")
        row.results["error_vs_baseline"] = row.results["error_mean_cm"] / baseline["error_mean_cm"]
    best = int(np.argmin([r.results["error_mean_cm"] for r in rows]))
    vertex_errors = {rows[i].name: rows[i].results["vertex_error_cm"] for i in (0, best)}
    for row in rows:
        row.results.pop("vertex_error_cm")
    z = (test.betas - np.asarray(db.beta0)) / np.asarray(db.beta_scale)
    report = {
        "database": str(db_path),
        "database_anchors": db.n_anchors,
        "database_vertices": db.n_vertices,
        "database_components": db.n_components,
        "database_regressor": db.regressor is not None, "database_santesteban": db.santesteban is not None,
        "database_kdsm": db.kdsm_model is not None, "database_recurrent": db.recurrent is not None,
        "test_set": {"poses": test.pose_labels, "betas": test.betas.tolist(), "shape_labels": test.shape_labels,
                     "shape_distance_from_beta0": np.linalg.norm(z, axis=1).tolist(),
                     "sequence_frames": int(len(test.sequence)),
                     "drapes": len(test.drape_stats),
                     "drape_seconds_mean": float(np.mean([s.get("seconds", np.nan) for s in test.drape_stats])),
                     "drapes_converged": int(sum(bool(s.get("converged")) for s in test.drape_stats)),
                     "ground_truth_inside_max": int(max(s.get("inside_count", 0) for s in test.drape_stats)),
                     "ground_truth_inside_fraction": float(truth_inside[0]),
                     "ground_truth_inside_overlap_fraction": float(truth_inside[1]),
                     "ground_truth_inside_true_fraction": float(truth_inside[2]),
                     "ground_truth_inside_faces_fraction": truth_faces,
                     "ground_truth_seconds_this_run": ground_truth_seconds},
        "rows": [{"name": r.name, "group": r.group, "config": r.config, **r.results} for r in rows],
        "timing": {"frames": int(len(test.sequence)), "passes": repeats,
                   "statistic": "best of the per-pass medians of ms per frame, one thread, passes interleaved "
                                "across the rows, this run only"},
        "bootstrap": {"draws": BOOTSTRAP_DRAWS, "cases": len(test.poses) * len(test.betas), "level": 0.95,
                      "resampled": "(pose, shape) cases, with replacement"},
        "lowest_mean_error": rows[best].name,
        "indistinguishable_from_lowest": [r.name for r in rows
                                          if overlaps(r.results["error_mean_ci_cm"], intervals[best])],
        "loses_to_baseline": [r.name for r in rows[1:] if r.results["vs_baseline"] == "worse"],
        "indistinguishable_from_baseline": [r.name for r in rows[1:]
                                            if r.results["vs_baseline"] == "indistinguishable"],
        "stability": stability,
        "temporal": temporal,
        "beta0": beta0,
        "pose_model_share": pose_share,
    }
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    (out_dir / "trade.md").write_text(trade_markdown(report))
    write_plots(report, out_dir)
    write_error_picture(db, vertex_errors, out_dir / "vertex_error.png")
    return report


def write_error_picture(db, vertex_errors: dict, path: Path) -> Path:
    """Each row's mean error per vertex (cm) on the garment at rest, front and back (faces turned away culled), one
    colour scale for all: {row name: (V,)} -> PNG."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    rest = np.asarray(db.rest, dtype=np.float64)
    faces = np.asarray(db.faces)
    corners = rest[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    top = max(float(np.percentile(e, 99)) for e in vertex_errors.values())
    fig, axes = plt.subplots(len(vertex_errors), 2, figsize=(8, 4.2 * len(vertex_errors)), squeeze=False)
    for row_axes, (name, errors) in zip(axes, vertex_errors.items()):
        for ax, (view, sign) in zip(row_axes, (("front", -1.0), ("back", 1.0))):
            facing = sign * normals[:, 1] > 0  # the body faces -y: the front view looks along +y
            x = rest[:, 0] if sign < 0 else -rest[:, 0]
            shown = ax.tripcolor(Triangulation(x, rest[:, 2], faces[facing]), errors, shading="gouraud",
                                 cmap="magma", vmin=0.0, vmax=top)
            ax.set_title(textwrap.fill(f"{view}: {name}", 44) + f"\nmean {errors.mean():.2f} cm", fontsize=7)
            ax.set_aspect("equal")
            ax.axis("off")
    fig.colorbar(shown, ax=axes, shrink=0.6, label="mean vertex error over the held-out set (cm)")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _share(fraction) -> str:
    return "-" if fraction is None else f"{100 * fraction:.2f} %"


def _inside_cell(entry: dict, prefix: str = "") -> str:
    """'6.81 % (6.70 / 0.11)': the inside share and its split, from a row (or, with prefix, the test set)."""
    share = entry[f"{prefix}inside_fraction"]
    if f"{prefix}inside_overlap_fraction" not in entry:  # a report from before the split
        return f"{100 * share:.2f} %"
    return (f"{100 * share:.2f} % ({100 * entry[f'{prefix}inside_overlap_fraction']:.2f} / "
            f"{100 * entry[f'{prefix}inside_true_fraction']:.2f})")


def pose_model_share(rows, models, test, beta0, beta0_drapes) -> list[dict]:
    """How much of each synthesis row's error its pose model makes: the row's model against the held-out drapes at
    every shape, and the same with its own beta0 output replaced by the drape of the pose at beta0,
    drape(beta0) + synthesis(beta) - synthesis(beta0) (a perfect pose model, up to the beta0 drape's own path noise).
    What stays is the shape term's error. beta0_drapes (P, V, 3): the test poses' drapes at beta0, in test order."""
    out = []
    for row, model in zip(rows, models):
        at_beta0 = synthesize_poses(model, beta0, test.poses)
        synthesis, oracle = [], []
        for k, beta in enumerate(test.betas):
            frames = synthesize_poses(model, beta, test.poses)
            synthesis.append(np.linalg.norm(frames - test.drapes[:, k], axis=2).mean() * 100.0)
            oracle.append(np.linalg.norm(beta0_drapes + frames - at_beta0 - test.drapes[:, k], axis=2).mean() * 100.0)
        out.append({"name": row.name, "config": row.config, "error_mean_cm": float(np.mean(synthesis)),
                    "perfect_pose_model_error_mean_cm": float(np.mean(oracle)),
                    "error_per_shape_cm": [float(e) for e in synthesis],
                    "perfect_pose_model_error_per_shape_cm": [float(e) for e in oracle]})
    return out


def trade_markdown(report: dict) -> str:
    lines = ["| # | configuration | mean error (cm) | 95 % interval | minus node default (paired 95 % interval) | "
             "p95 error (cm) | vs baseline | inside body (self-overlap / truly) | face centres inside | ms / frame | "
             "jitter (mm/frame^2) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(report["rows"], start=1):
        (low, high), (d_low, d_high) = r["error_mean_ci_cm"], r["error_vs_default_ci_cm"]
        lines.append(f"| {i} | {r['name']} | {r['error_mean_cm']:.2f} | {low:.2f}-{high:.2f} | "
                     f"{d_low:+.2f} to {d_high:+.2f} | {r['error_p95_cm']:.2f} | {r['error_vs_baseline']:.2f}x | "
                     f"{_inside_cell(r)} | {_share(r.get('inside_faces_fraction'))} | {r['ms_per_frame']:.3f} | "
                     f"{r['jitter_mm']:.2f} |")
    parts = list(report["rows"][0].get("error_by_part_cm", {}))
    if parts:
        lines += ["", "Mean error by garment part (cm; the vertices' dominant skinning region, left and right merged; "
                  f"hem and top edge: the torso within {100 * EDGE_BAND:.0f} cm of an open edge below and above the "
                  "middle height; the per-vertex picture of the baseline and the lowest row: vertex_error.png):", "",
                  "| # | configuration | " + " | ".join(parts) + " |", "|---|---|" + "---|" * len(parts)]
        for i, r in enumerate(report["rows"], start=1):
            lines.append(f"| {i} | {r['name']} | " + " | ".join(f"{r['error_by_part_cm'][n]:.2f}" for n in parts)
                         + " |")
    lines += ["", "| extreme input (full pipeline) | max distance from skinned (cm) | non-finite | rejected frames |",
              "|---|---|---|---|"]
    for s in report["stability"]:
        lines.append(f"| {s['case']} | {s['max_deviation_from_skinned_cm']:.2f} | {s['non_finite']} | "
                     f"{s['rejected_frames']} |")
    for entry in report.get("temporal", []):
        lines += ["", f"Along the dynamic ground truth {entry['sequence']} ({entry['frames']} frames at 30 fps; the "
                  f"ground truth's own jitter {entry['truth_jitter_mm']:.2f} mm/frame^2):", "",
                  "| configuration | mean error per frame (cm) | worst frame (cm) | jitter (mm/frame^2) | "
                  "jitter / ground truth's |", "|---|---|---|---|---|"]
        for r in entry["rows"]:
            ratio = r["jitter_mm"] / max(entry["truth_jitter_mm"], 1e-12)
            lines.append(f"| {r['name']} | {r['error_mean_cm']:.2f} | {r['error_max_frame_cm']:.2f} | "
                         f"{r['jitter_mm']:.2f} | {ratio:.2f} |")
    if report.get("beta0"):
        lines += ["", "At beta0, against drapes of the same held-out poses at the reference shape (intervals: the "
                  "poses resampled):", "", "| configuration (at beta0) | mean error (cm) | 95 % interval | "
                  "p95 error (cm) |", "|---|---|---|---|"]
        for r in report["beta0"]:
            low, high = r["error_mean_ci_cm"]
            lines.append(f"| {r['name']} | {r['error_mean_cm']:.2f} | {low:.2f}-{high:.2f} | "
                         f"{r['error_p95_cm']:.2f} |")
    if report.get("pose_model_share"):
        lines += ["", "What the pose model costs: each synthesis row, and the same with its beta0 output replaced by "
                  "the held-out drape at beta0 (drape(beta0) + synthesis(beta) - synthesis(beta0): a perfect pose "
                  "model; what stays is the shape term's error), mean error (cm) over the shapes and by shape:", "",
                  "| configuration | synthesis | with a perfect pose model | by shape: synthesis / perfect |",
                  "|---|---|---|---|"]
        for r in report["pose_model_share"]:
            by_shape = ", ".join(f"{a:.2f} / {b:.2f}" for a, b in zip(r["error_per_shape_cm"],
                                                                     r["perfect_pose_model_error_per_shape_cm"]))
            lines.append(f"| {r['name']} | {r['error_mean_cm']:.2f} | {r['perfect_pose_model_error_mean_cm']:.2f} | "
                         f"{by_shape} |")
    truth = report["test_set"]
    lines += ["", f"Ground truth: {truth['drapes']} newton drapes of {len(truth['poses'])} held-out poses x "
              f"{len(truth['betas'])} shapes; {_inside_cell(truth, 'ground_truth_')} of their vertices inside the "
              "body by the same winding-number test (in the body's self-overlap / truly through the skin), and "
              f"{_share(truth.get('ground_truth_inside_faces_fraction'))} of their face centres."]
    timing, boot = report["timing"], report["bootstrap"]
    lines += ["", f"ms / frame: the best of {timing['passes']} per-pass medians over the {timing['frames']}-frame "
              "held-out motion, one thread, every row in the same run (the passes interleaved across the rows): "
              "compare rows by their ratio, not with another run's numbers."]
    lines += ["", f"Intervals: {boot['draws']} bootstrap resamples of the {boot['cases']} {boot['resampled']}, "
              "the same resamples for every row. Lowest mean error: " + report["lowest_mean_error"]
              + "; indistinguishable from it (intervals overlap): "
              + ", ".join(n for n in report["indistinguishable_from_lowest"] if n != report["lowest_mean_error"])
              + "."]
    for key, what in (("loses_to_baseline", "worse than the skinned baseline (intervals apart)"),
                      ("indistinguishable_from_baseline", "indistinguishable from the skinned baseline")):
        names = report[key]
        lines += ["", f"Configurations {what}: " + (", ".join(names) if names else "none") + "."]
    return "\n".join(lines) + "\n"


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _error_bars(rows) -> np.ndarray:
    """(2, n) distances from each row's mean error down and up to its interval's ends (matplotlib's yerr)."""
    return np.array([[r["error_mean_cm"] - r["error_mean_ci_cm"][0], r["error_mean_ci_cm"][1] - r["error_mean_cm"]]
                     for r in rows]).T


def write_plots(report: dict, out_dir: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["rows"]
    paths = []
    # Pareto front: error vs ms per frame
    fig, ax = plt.subplots(figsize=(7, 5))
    top = 2.0 * rows[0]["error_mean_cm"]  # rows far worse than the baseline are drawn at the top edge
    for i, r in enumerate(rows, start=1):  # points numbered as the rows of trade.md
        marker = "s" if r["group"] == "baseline" else ("*" if r["group"] == "default" else "o")
        error = min(r["error_mean_cm"], top)
        ax.scatter(r["ms_per_frame"], error, marker="^" if error < r["error_mean_cm"] else marker,
                   s=70 if marker != "o" else 25, label=r["name"][:40] if marker != "o" else None)
        if error == r["error_mean_cm"]:
            ax.errorbar(r["ms_per_frame"], error, yerr=_error_bars([r]), fmt="none", ecolor="0.6", lw=0.8, capsize=2)
        ax.annotate(str(i) if error == r["error_mean_cm"] else f"{i} ({r['error_mean_cm']:.0f} cm)",
                    (r["ms_per_frame"], error), fontsize=7, xytext=(3, -9 if error < r["error_mean_cm"] else 3),
                    textcoords="offset points")
    ax.set_ylim(0, top * 1.05)
    points = sorted((r["ms_per_frame"], r["error_mean_cm"]) for r in rows)
    front, best = [], np.inf
    for t, e in points:
        if e < best:
            front.append((t, e))
            best = e
    ax.plot(*zip(*front), "k--", lw=0.8, label="Pareto front")
    ax.set_xlabel("ms per frame (one core)")
    ax.set_ylabel("mean vertex error vs newton (cm)")
    ax.set_title("Speed vs accuracy on held-out CMU poses and shapes")
    ax.legend(fontsize=7)
    paths.append(_save(fig, out_dir / "pareto.png"))

    # error vs number of anchors (Fig. 9): shape models and pose-model examples both restricted to N anchors
    sweep = sorted((r["config"]["anchors"], r) for r in rows if r["group"] == "anchors")
    fig, ax = plt.subplots(figsize=(6, 4))
    counts = [n for n, _ in sweep]
    ax.errorbar(counts, [r["error_mean_cm"] for _, r in sweep], yerr=_error_bars([r for _, r in sweep]), fmt="o-",
                capsize=3, label="synthesis (examples pose model on the same anchors)")
    baseline = rows[0]
    ax.axhline(baseline["error_mean_cm"], color="gray", ls="--", label="skinned baseline (95 % interval shaded)")
    ax.axhspan(*baseline["error_mean_ci_cm"], color="gray", alpha=0.15)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("anchors used (error bars: 95 % bootstrap interval)")
    ax.set_ylabel("mean vertex error (cm)")
    ax.set_title("Error vs number of anchors (cf. AgentDress Fig. 9)")
    ax.legend()
    paths.append(_save(fig, out_dir / "anchors.png"))

    # error vs distance of the shape from beta0
    distance = report["test_set"]["shape_distance_from_beta0"]
    fig, ax = plt.subplots(figsize=(6, 4))
    for r in rows:
        if r["group"] in ("baseline", "default") or r["name"].startswith("lbs pose model alone"):
            ax.plot(distance, r["error_per_shape_cm"], "o", label=r["name"][:48])
    for d, label in zip(distance, report["test_set"]["shape_labels"]):
        ax.annotate(label, (d, 0), fontsize=7, xytext=(0, 3), textcoords="offset points")
    ax.set_xlabel("distance of the shape from beta0 (training steps, |z|)")
    ax.set_ylabel("mean vertex error (cm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    paths.append(_save(fig, out_dir / "shape_distance.png"))
    return paths


def main(argv=None) -> int:
    import argparse

    from .testset import default_cache

    parser = argparse.ArgumentParser(prog="agentdress eval", description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--out", default="docs/eval", help="folder for report.json, trade.md and the plots")
    parser.add_argument("--cache", default=None, help="ground-truth drapes of the held-out set (default: "
                        "out/eval-cache/<database file name without .h5>, out/eval-cache-v2/... for --test-set v2)")
    parser.add_argument("--clips", nargs="*", default=None, help="held-out CMU .bvh clips (default: "
                        "../shared/mocap/cmu/{02_01,07_12,05_12,06_14,09_01}.bvh)")
    parser.add_argument("--quick", action="store_true", help="one pose, two shapes, short drapes (a smoke test)")
    parser.add_argument("--workers", type=int, default=2, help="drape processes (0: in this process)")
    parser.add_argument("--drape", default="", help="JSON DrapeSettings overrides for the ground truth")
    parser.add_argument("--ground-truth", default=None, help="pack of the held-out drapes, read when present and "
                        "rewritten (default: <out>/ground_truth_drapes.npz; 'none' for no pack)")
    parser.add_argument("--test-set", choices=["v1", "v2", "v3"], default="v1", help="v1: 10 poses of 5 test clips "
                        "x 3 shapes, static collider; v2: 40 poses of all 10 test clips x 3 shapes, animated collider, "
                        "and dynamic sequences along 02_08 and 05_12 (see evaluate.testset.held_out_v2); v3: the v2 "
                        "poses, each at one of its shapes, draped along 3 ramps and scored against physics' own spread "
                        "(evaluate.score_v3; its drapes come from `agentdress lab groundtruth-v3`)")
    parser.add_argument("--test-config", default="", help="JSON object of test-set fields to override (evaluate."
                        "testset.HeldOutConfig), e.g. '{\"poses_per_clip\": 1, \"shapes_inside\": 1, \"dynamic_clips\": []}'")
    parser.add_argument("--beta0", action="store_true", help="drape the held-out poses at beta0 too when their pack "
                        "(<out>/ground_truth_beta0.npz) is missing, for the pose models alone at beta0 (a v1 set "
                        "always does: 10 drapes; v2: 40)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    pack = None if args.ground_truth == "none" else (args.ground_truth or Path(args.out) / "ground_truth_drapes.npz")
    if args.test_set == "v3":
        from .score_v3 import evaluate_v3, markdown

        report = evaluate_v3(args.database, pack, args.out, progress=not args.quiet)
        print(markdown(report))
        return 0
    cache = args.cache or default_cache(args.database, args.test_set)
    beta0_pack = None if pack is None else Path(pack).with_name("ground_truth_beta0.npz")
    report = evaluate(args.database, args.out, cache, clips=args.clips, quick=args.quick,
                      workers=args.workers, progress=not args.quiet,
                      drape=json.loads(args.drape) if args.drape else None, pack=pack, test_set=args.test_set,
                      beta0_pack=beta0_pack, test_config=json.loads(args.test_config) if args.test_config else None,
                      beta0=True if args.beta0 else None)
    summary = {r["name"]: {**{k: round(r[k], 4) for k in ("error_mean_cm", "error_p95_cm", "ms_per_frame")},
                           "error_mean_ci_cm": [round(x, 4) for x in r["error_mean_ci_cm"]]}
               for r in report["rows"]}
    print(json.dumps({"out": args.out, "rows": summary, "loses_to_baseline": report["loses_to_baseline"]}, indent=2))
    return 0
