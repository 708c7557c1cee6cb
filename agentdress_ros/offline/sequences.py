"""Dynamic training sequences: every training clip simulated at beta0, per garment, resumable, on Dask, packed.

    agentdress lab sequences --garment tshirt --clips ../shared/mocap/cmu/*.bvh --out out/sequences [--workers 1]
    agentdress lab sequences --garment tshirt --clips ... --out out/sequences --pack data/tshirt_sequences.npz

With --pack, clips the pack already holds whole are not simulated again (unless their chunk folder is there), and
the new pack keeps them beside the clips simulated here: the work of several machines or days adds up in one file.
A clip simulated again (its chunk folder there) replaces its frames in the pack and keeps its place.
A clip packed part-way (`clip_complete` false) keeps its frames in the pack until a later run simulates it whole.

Each clip runs as one job (`sim.sequence.simulate_sequence`, checkpointed every second of motion) in
`<out>/<garment>/<clip>/`; a rerun continues every clip after its last complete chunk. Test clips of
../shared/mocap/README.md are refused by name: they hold the held-out ground truth.

The pack stores what a learned pose model trains on, compactly: every frame's garment unposed to the rest frame
with beta0's bones (Santesteban et al. 2019, Eq. 5: delta = W^-1(S) - T) as PCA coefficients (float16) plus the
basis (float16; packs made before it: float32) and the rest garment, beside the frame's pose, root translation and
root velocity.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

# ../shared/mocap/README.md: never part of a build's pose set or of any training data.
TEST_CLIPS = ("02_01", "02_08", "05_07", "05_12", "05_14", "06_04", "06_14", "07_12", "08_10", "09_01")


def check_training_clips(clips) -> list[Path]:
    """The clip paths, or ValueError naming any test clip among them."""
    paths = [Path(c) for c in clips]
    held_out = sorted(p.stem for p in paths if p.stem in TEST_CLIPS)
    if held_out:
        raise ValueError(f"test clips cannot be training data: {', '.join(held_out)}")
    return paths


@dataclass(frozen=True)
class SequenceJob:
    clip: str  # a CMU .bvh path
    garment: str
    garment_vertices: int
    beta: tuple
    folder: str
    settings: dict  # SequenceSettings fields, with its `drape` as a dict of DrapeSettings fields


def _settings(fields: dict):
    from ..sim.sequence import DrapeSettings, SequenceSettings

    fields = dict(fields)
    return SequenceSettings(**{**fields, "drape": DrapeSettings(**fields.get("drape", {}))})


def run_sequence_job(job: SequenceJob) -> dict:
    """Simulate (or finish) one clip; returns its statistics."""
    from ..motion.retarget import load_cmu_motion
    from ..sim.sequence import simulate_sequence
    from .jobs import _body_and_garment

    body, garment = _body_and_garment(job.garment, job.garment_vertices)
    shape = body.shape(np.asarray(job.beta))
    motion = load_cmu_motion(job.clip, shape.heads, shape.tails)
    stats = simulate_sequence(motion, garment, shape.beta, job.folder, _settings(job.settings), body=body,
                              progress=False)
    return {"clip": Path(job.clip).stem, **stats}


def run_sequences(jobs, workers: int = 1, scheduler: str | None = None, progress: bool = True) -> list[dict]:
    """Run sequence jobs in this process (workers=0), on local worker processes, or on a Dask cluster."""
    from tqdm import tqdm

    results = []
    bar = tqdm(total=len(jobs), desc="sequences", unit="clip", disable=not progress)
    if workers == 0 and scheduler is None:
        for job in jobs:
            results.append(run_sequence_job(job))
            bar.update()
    else:
        import logging

        from dask.distributed import Client, LocalCluster, as_completed

        cluster = None if scheduler else LocalCluster(n_workers=max(1, workers), threads_per_worker=1,
                                                      processes=True, dashboard_address=":0",
                                                      silence_logs=logging.WARNING)
        with Client(scheduler or cluster) as client:
            futures = [client.submit(run_sequence_job, job, key=f"sequence-{Path(job.folder).name}", pure=False)
                       for job in jobs]
            for future in as_completed(futures):
                results.append(future.result())
                bar.update()
        if cluster is not None:
            cluster.close()
    bar.close()
    return results


def pack_sequences(root, garment_name: str, garment_vertices: int, out, components: int = 200,
                   beta=None, inside_every: int = 10) -> dict:
    """Pack every sequence under `root/<garment>/` into one .npz (see the module docstring); returns a report with
    the pack's size, the PCA reconstruction error in the rest frame (mean and max vertex distance, metres), and the
    garment vertices inside the body on every `inside_every`-th frame (mean per frame: all, in the body's
    self-overlap, truly inside; garment.inside)."""
    from ..body import visible_body
    from ..body.model import REFERENCE_SHAPE
    from ..garment.inside import inside_report
    from ..sim.posing import posed_surfaces
    from ..sim.sequence import load_sequence
    from .jobs import _body_and_garment

    body, garment = _body_and_garment(garment_name, garment_vertices)
    shape = body.shape(REFERENCE_SHAPE if beta is None else beta)
    rest = garment.rest_vertices(body, shape)
    garment_root = Path(root) / garment_name
    folders = sorted(p for p in garment_root.iterdir() if any(p.glob("chunk_*.npz"))) if garment_root.is_dir() else []
    offsets, poses, roots, velocities, clip_ids, frame_ids, names, complete = [], [], [], [], [], [], [], []
    cloth_speed, body_speed = [], []
    out = Path(out)
    previous = load_sequence_pack(out) if out.is_file() else None  # clips packed before, simulated elsewhere or earlier
    by_name = {f.name: f for f in folders}
    # A clip simulated again keeps its place in the pack; clips new to it follow in name order.
    previous_index = {str(name): c for c, name in enumerate(previous["clips"])} if previous is not None else {}
    order = list(previous_index) + [name for name in sorted(by_name) if name not in previous_index]
    inside = []
    for name in order:
        names.append(name)
        c = len(names) - 1
        if name not in by_name:  # kept from the previous pack
            index = previous_index[name]
            rows = previous["clip"] == index
            complete.append(bool(previous["clip_complete"][index]) if "clip_complete" in previous else True)
            offsets.extend(previous["offsets"][rows].reshape(int(rows.sum()), -1).astype(np.float64))
            for target, field in ((poses, "rotvecs"), (roots, "root_translation"), (velocities, "root_velocity"),
                                  (cloth_speed, "cloth_speed"), (body_speed, "body_speed"), (frame_ids, "frame")):
                target.append(previous[field][rows])
            clip_ids.append(np.full(int(rows.sum()), c, dtype=np.int16))
            continue
        folder = by_name[name]
        data = load_sequence(folder)
        planned = json.loads((folder / "sequence.json").read_text())["chunks"]
        complete.append(len(list(folder.glob("chunk_*.npz"))) >= planned)
        for f in range(0, len(data["frames"]), max(1, inside_every)):
            bodies, _ = posed_surfaces(body, garment, shape, data["rotvecs"][f:f + 1].astype(np.float64),
                                       data["root_translation"][f:f + 1].astype(np.float64))
            counts = inside_report(data["positions"][f], bodies[0], visible_body(body)[1])
            inside.append([counts["inside_count"], counts["overlap_count"], counts["truly_inside_count"]])
        offsets.extend(rest_frame_offsets(body, shape, garment.skin_indices, garment.skin_weights, rest,
                                          data["positions"], data["rotvecs"], data["root_translation"]))
        poses.append(data["rotvecs"])
        roots.append(data["root_translation"])
        velocities.append(data["root_velocity"])
        cloth_speed.append(data["cloth_speed"])
        body_speed.append(data["body_speed"])
        clip_ids.append(np.full(len(data["frames"]), c, dtype=np.int16))
        frame_ids.append(data["frames"].astype(np.int32))
    fields = {"rotvecs": np.concatenate(poses), "root_translation": np.concatenate(roots),
              "root_velocity": np.concatenate(velocities), "cloth_speed": np.concatenate(cloth_speed),
              "body_speed": np.concatenate(body_speed), "clip": np.concatenate(clip_ids),
              "frame": np.concatenate(frame_ids)}
    error, explained, k = write_pack(out, garment_name, garment_vertices, shape.beta, rest, garment.faces, offsets,
                                     fields, names, complete, components)
    return {"pack": str(out), "bytes": out.stat().st_size, "clips": len(names),
            "clips_part_way": [n for n, done in zip(names, complete) if not done], "frames": len(offsets),
            "components": k, "explained_variance": explained, "rest_frame_error_mean_m": float(error.mean()),
            "rest_frame_error_max_m": float(error.max()),
            "inside_per_frame": dict(zip(("all", "in_self_overlap", "truly_inside"),
                                         np.mean(inside, axis=0).round(2).tolist())),
            "inside_frames_tested": len(inside),
            "max_cloth_speed": float(np.concatenate(cloth_speed).max()),
            "max_body_speed": float(np.concatenate(body_speed).max())}


def rest_frame_offsets(body, shape, skin_indices, skin_weights, rest, positions, rotvecs, roots) -> list:
    """F rows (3V,): each posed garment positions (F, V, 3) unposed with the bones of `shape` in pose rotvecs
    (F, B, 3) and root translation roots (F, 3), minus the rest garment (V, 3): what a pack stores (Eq. 5)."""
    from ..engine.kernels import unpose

    skin_weights = np.asarray(skin_weights, dtype=np.float64)
    unposed = np.empty_like(np.asarray(rest, dtype=np.float64))
    rows = []
    for garment, pose, root in zip(positions, rotvecs, roots):
        transforms, _ = body.pose(shape, np.asarray(pose, dtype=np.float64), np.asarray(root, dtype=np.float64))
        unpose(np.asarray(garment, dtype=np.float64), skin_indices, skin_weights, transforms, unposed)
        rows.append((unposed - rest).ravel())
    return rows


def write_pack(out, garment_name: str, garment_vertices: int, beta, rest, faces, offsets, fields: dict, names,
               complete, components: int) -> tuple:
    """Write a pack (the module docstring's format) atomically: offsets (F, 3V) rest-frame offsets as float16 PCA
    coefficients of `components` components (each scaled to its range) plus the float16 basis; `fields` the per-frame
    arrays (rotvecs (F, B, 3), root_translation, root_velocity (F, 3), cloth_speed, body_speed (F,), clip (F,)
    indices into `names`, frame (F,); optionally betas (F, 6), each frame's body shape, where they differ);
    complete (C,) whether each clip is whole. Returns (rest-frame error of the
    stored offsets (F, V) metres, explained variance, components kept)."""
    out = Path(out)
    matrix = np.asarray(offsets, dtype=np.float64)
    if any(len(fields[name]) != len(matrix) for name in fields):
        raise ValueError(f"{out}: {len(matrix)} frames of offsets but per-frame fields of "
                         f"{ {name: len(value) for name, value in fields.items()} } rows")
    mean = matrix.mean(axis=0)
    k = min(components, len(matrix) - 1, matrix.shape[1])
    _, singular, basis = np.linalg.svd(matrix - mean, full_matrices=False)
    basis = basis[:k]
    coefficients = (matrix - mean) @ basis.T
    scale = np.abs(coefficients).max(axis=0) + 1e-12  # float16 keeps ~3 digits of each coefficient's range
    coefficients16 = (coefficients / scale).astype(np.float16)
    # the basis in float16 too: its unit rows lose ~1e-5 m of a restored offset, and it is half the pack
    basis16 = basis.astype(np.float16)
    restored = (coefficients16.astype(np.float64) * scale) @ basis16.astype(np.float64) + mean
    error = np.linalg.norm((restored - matrix).reshape(len(matrix), -1, 3), axis=2)
    per_frame = {name: np.asarray(fields[name], dtype=np.float32) for name in
                 ("rotvecs", "root_translation", "root_velocity", "cloth_speed", "body_speed")}
    partial = out.with_name(out.name + ".partial")
    with open(partial, "wb") as handle:
        np.savez_compressed(
            handle, garment=np.array(garment_name), garment_vertices=np.array(garment_vertices),
            beta=np.asarray(beta), rest=np.asarray(rest, dtype=np.float32), faces=np.asarray(faces, dtype=np.int32),
            mean=mean.astype(np.float32), basis=basis16, scale=scale.astype(np.float32),
            coefficients=coefficients16, clip=np.asarray(fields["clip"], dtype=np.int16),
            frame=np.asarray(fields["frame"], dtype=np.int32), clips=np.array(names),
            clip_complete=np.array(complete, dtype=bool), **per_frame,
            **({"betas": np.asarray(fields["betas"], dtype=np.float64)} if "betas" in fields else {}))
    out.parent.mkdir(parents=True, exist_ok=True)
    partial.replace(out)
    return error, float((singular[:k] ** 2).sum() / (singular ** 2).sum()), k


def clips_to_simulate(clips, pack, folder) -> list:
    """The clips a run still has to simulate: all but those `pack` holds whole, unless their chunk folder is in
    `folder` (a run under way). A clip packed part-way is simulated again, whole."""
    if not Path(pack).is_file():
        return list(clips)
    with np.load(pack) as data:
        whole = data["clip_complete"] if "clip_complete" in data.files else np.ones(len(data["clips"]), bool)
        done = {str(name) for name, complete in zip(data["clips"], whole) if complete}
    return [c for c in clips if Path(c).stem not in done or (Path(folder) / Path(c).stem).is_dir()]


def load_sequence_pack(path) -> dict:
    """A pack's arrays with the rest-frame offsets restored: offsets (F, V, 3) float32 and the per-frame fields."""
    with np.load(path) as data:
        arrays = {name: data[name] for name in data.files}
    coefficients = arrays["coefficients"].astype(np.float32) * arrays["scale"]
    offsets = coefficients @ arrays["basis"] + arrays["mean"]
    arrays["offsets"] = offsets.reshape(len(offsets), -1, 3)
    return arrays


def main(argv=None) -> int:
    from ..body.model import REFERENCE_SHAPE
    from ..sim.sequence import SequenceSettings

    parser = argparse.ArgumentParser(prog="agentdress lab sequences", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--vertices", type=int, default=1200)
    parser.add_argument("--clips", nargs="*", default=[], help="training CMU .bvh clips (test clips are refused)")
    parser.add_argument("--out", default="out/sequences", help="folder of the resumable sequence chunks")
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (0: in this process)")
    parser.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    parser.add_argument("--settings", default="", help="JSON object of SequenceSettings overrides")
    parser.add_argument("--pack", default=None, help="pack the finished sequences into this .npz")
    parser.add_argument("--components", type=int, default=200, help="PCA components of the pack")
    args = parser.parse_args(argv)
    settings = asdict(SequenceSettings())
    settings.update(json.loads(args.settings) if args.settings else {})
    clips = check_training_clips(args.clips)
    if args.pack:
        clips = clips_to_simulate(clips, args.pack, Path(args.out) / args.garment)
    # shortest clips first: the most finished clips early, whatever the time available
    clips.sort(key=lambda p: p.stat().st_size)
    jobs = [SequenceJob(str(c), args.garment, args.vertices, tuple(REFERENCE_SHAPE), str(Path(args.out) /
                        args.garment / c.stem), settings) for c in clips]
    results = run_sequences(jobs, workers=args.workers, scheduler=args.scheduler) if jobs else []
    report = {"sequences": results}
    if args.pack:
        report["pack"] = pack_sequences(args.out, args.garment, args.vertices, args.pack, args.components)
    json.dump(report, sys.stdout, indent=1)
    print()
    return 0
