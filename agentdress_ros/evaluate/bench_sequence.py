"""`agentdress bench sequence`: what the dynamic ground truth costs per mocap frame, and what cheaper stepping gives up.

One training clip (08_04 by default), one garment at beta0. The reference settings (`SequenceSettings()`: 60 fps,
16 substeps, 2 VBD iterations) settle the garment and simulate the first chunk (30 mocap frames). The baseline (the
reference, or with `--baseline` a finer stepping for a convergence study) and every variant then continue from that
same checkpoint for `--chunks` more chunks, so they differ in the stepping of the clip alone, not in the settle. Per
variant (JSON): seconds of wall time per 30 fps mocap frame, its ratio to the baseline's measured in the same run (the
machine may be loaded: compare ratios), the distance of every cloth vertex from the baseline's (mean, p95 and max over
frames of the per-frame mean; the max over all vertices), and the cloth's and the body's peak speed. A variant is a
JSON object of DrapeSettings fields (`{"substeps": 8}`) applied to the clip.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .testset import default_clip_paths

__all__ = ["bench_sequence", "main"]

DEFAULT_CLIP = default_clip_paths()[0].parent / "08_04.bvh"  # a training clip in ../shared/mocap/cmu
DEFAULT_VARIANTS = ({"substeps": 12}, {"substeps": 8}, {"iterations": 1}, {"collide_every": 2},
                    {"substeps": 8, "iterations": 3}, {"fps": 30.0})


def _continue(motion, garment, beta, start_folder, folder, settings, body, chunks: int):
    """Copy the shared first chunk into `folder` under `settings`' key and simulate `chunks` more; (stats, frames)."""
    from ..sim.sequence import _save_atomic, load_sequence, resample, sequence_key, simulate_sequence

    folder.mkdir(parents=True)
    rotvecs, roots = resample(motion, settings.fps)
    key = sequence_key(settings, beta, motion.name, len(rotvecs), garment, rotvecs, roots)
    with np.load(start_folder / "chunk_0000.npz") as data:
        arrays = {name: data[name] for name in data.files}
    _save_atomic(folder / "chunk_0000.npz", **{**arrays, "key": np.array(key)})
    start = time.perf_counter()
    stats = simulate_sequence(motion, garment, beta, folder, settings, body=body, max_chunks=chunks, progress=False)
    stats["seconds"] = time.perf_counter() - start
    return stats, load_sequence(folder)


def compare_stepping(motion, garment, beta, body, reference, variants, chunks: int = 2, progress: bool = True,
                     baseline: dict | None = None) -> dict:
    """Settle and simulate the first chunk with `reference` (SequenceSettings), then continue from it `chunks` more
    chunks with the baseline (the reference's drape with the `baseline` DrapeSettings overrides: a finer stepping
    for a convergence study) and with each variant (DrapeSettings overrides). -> {"settle_seconds", "rows"}: per
    row its settings, frames, seconds per mocap frame, ratio to the baseline's, distance from the baseline's frames
    (mm) and peak cloth / body speeds; "baseline_positions" (F, V, 3), the baseline's frames after the first chunk."""
    from ..sim.sequence import simulate_sequence

    with tempfile.TemporaryDirectory(prefix="bench-sequence-") as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        simulate_sequence(motion, garment, beta, root / "start", reference, body=body, max_chunks=1,
                          progress=progress)
        settle_seconds = time.perf_counter() - start
        results = []
        for index, fields in enumerate([dict(baseline or {})] + [dict(v) for v in variants]):
            settings = replace(reference, drape=replace(reference.drape, **fields))
            stats, frames = _continue(motion, garment, beta, root / "start", root / f"variant_{index}", settings,
                                      body, chunks)
            results.append((fields, stats, frames["positions"][reference.chunk_frames:]))
            if progress:
                label = json.dumps(fields) if fields else "reference"
                print(f"{label}: {stats['seconds'] / max(stats['frames'], 1):.3f} s/frame")
    _, base_stats, base_positions = results[0]
    base_rate = base_stats["seconds"] / base_stats["frames"]
    rows = []
    for index, (fields, stats, positions) in enumerate(results):
        distance = np.linalg.norm(positions - base_positions, axis=2)  # (F, V) m
        per_frame = distance.mean(axis=1)
        rate = stats["seconds"] / stats["frames"]
        rows.append({
            "settings": fields or "reference", "baseline": index == 0, "frames": int(stats["frames"]),
            "seconds_per_mocap_frame": round(rate, 4), "ratio_to_baseline": round(rate / base_rate, 3),
            "distance_mm": {"mean": round(float(per_frame.mean()) * 1e3, 3),
                            "p95_frame": round(float(np.percentile(per_frame, 95)) * 1e3, 3),
                            "max_frame": round(float(per_frame.max()) * 1e3, 3),
                            "max_vertex": round(float(distance.max()) * 1e3, 3)},
            "max_cloth_speed": round(float(stats["max_cloth_speed"]), 3),
            "max_body_speed": round(float(stats["max_body_speed"]), 3)})
    return {"settle_seconds": round(settle_seconds, 2), "rows": rows, "baseline_positions": base_positions}


def bench_sequence(clip=DEFAULT_CLIP, garment_name: str = "tshirt", vertices: int = 1200, chunks: int = 2,
                   variants=DEFAULT_VARIANTS, progress: bool = True, baseline: dict | None = None) -> dict:
    from ..offline.jobs import _body_and_garment
    from ..motion.retarget import load_cmu_motion
    from ..sim.sequence import SequenceSettings

    body, garment = _body_and_garment(garment_name, vertices)
    shape = body.shape(np.zeros(6))
    motion = load_cmu_motion(str(clip), shape.heads, shape.tails)
    reference = SequenceSettings()
    result = compare_stepping(motion, garment, shape.beta, body, reference, variants, chunks, progress, baseline)
    return {"benchmark": "sequence", "clip": Path(clip).stem, "garment": garment_name,
            "garment_vertices": int(garment.n_vertices), "mocap_fps": reference.fps,
            "reference": {"fps": reference.drape.fps, "substeps": reference.drape.substeps,
                          "iterations": reference.drape.iterations},
            "baseline": baseline or "reference",
            "settle_and_first_chunk_seconds": result["settle_seconds"], "variants": result["rows"],
            "goal_seconds_per_mocap_frame": 0.4}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress bench sequence", description=__doc__.split("\n")[0])
    parser.add_argument("--clip", default=str(DEFAULT_CLIP), help="a training clip (.bvh)")
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--vertices", type=int, default=1200)
    parser.add_argument("--chunks", type=int, default=2, help="chunks of 30 mocap frames timed after the first")
    parser.add_argument("--variants", default=json.dumps(DEFAULT_VARIANTS),
                        help="JSON list of DrapeSettings overrides (the reference is always run)")
    parser.add_argument("--baseline", default="{}", help="JSON DrapeSettings overrides of the stepping the variants "
                        "are measured against ({} : the reference; {\"substeps\": 48} for a convergence study)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    from ..offline.sequences import check_training_clips

    check_training_clips([args.clip])
    with contextlib.redirect_stdout(sys.stderr):  # warp's banner and progress lines: stdout is the JSON alone
        report = bench_sequence(args.clip, args.garment, args.vertices, args.chunks, json.loads(args.variants),
                                progress=not args.quiet, baseline=json.loads(args.baseline))
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
