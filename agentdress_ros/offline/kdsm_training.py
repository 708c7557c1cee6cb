"""Training targets d(theta) from a sequence pack, and the dataset analysis of the paper's Table 1.

    python -m agentdress_ros.offline.kdsm_training --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz \
        --frames 200 [--spacing 0.025] [--save out/tshirt_kdsm.npz]

A pack frame's posed drape (root translation zero) is its rest-frame garment rest + offsets[f] skinned with the
garment's weights and the frame's beta0 transforms: the inverse of how offline.sequences unposed it. Each method of
Sec. 5 turns the drape into material positions u^m (d = u^m - u^{m_o}); the table pushes every d through the
run-time map (re-embed at rest, skin the parent tet; skinning outside the shell) and compares with the drape.
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..body.kinematics import forward_kinematics, linear_blend_skinning
from ..garment.binding import mesh_edges
from ..kdsm.embedding import KdsmPoser
from ..kdsm.inverse import (FALLBACK, STATUS_NAMES, candidate_parents, graph_laplacian, hybrid_material,
                            method1_material, region_groups, surface_offset_guess)
from ..kdsm.mesh import KDSM, KDSMSettings, build_kdsm, save_kdsm

#: fixed: the rest embedding (d = 0, Fig. 3); method1/method2/hybrid_paper: Sec. 5 as written (1 cm);
#: hybrid: the training targets, 1 cm then the relaxed thresholds of TargetSettings.
METHODS = ("fixed", "method1", "method2", "hybrid_paper", "hybrid")


@dataclass(frozen=True)
class TargetSettings:
    eps: float = 1e-4  # candidate parents hold the point with every barycentric weight >= -eps
    threshold: float = 0.01  # m: the paper's agreement threshold with Method 2 (and its morphs)
    relaxed: tuple = (0.02, 0.04)  # m: later thresholds of the hybrid targets (inverse.hybrid_material)
    region_minimum: float = 0.05  # Method 2 searches the body regions carrying this much of a vertex's weight
    # the hybrid's guess: "surface" (Method 2, the paper's) or "unposed" (the drape unposed with the garment's own
    # skinning: the rest-frame offsets, smooth in the pose, pick the parent among several)
    guess: str = "surface"


@dataclass(frozen=True)
class GarmentFrames:
    """Posed drapes of a garment at beta0. F frames, V vertices, B bones."""

    rest: np.ndarray  # (V, 3) u^{m_o}, the rest garment
    faces: np.ndarray  # (Fc, 3)
    skin_indices: np.ndarray  # (V, 4) int32
    skin_weights: np.ndarray  # (V, 4) float64
    transforms: np.ndarray  # (F, B, 3, 4) beta0 bone transforms of each frame (root translation zero)
    drapes: np.ndarray  # (F, V, 3) posed ground truth
    unposed: np.ndarray  # (F, V, 3) the drapes unposed with the garment's own weights (rest + offsets)
    frames: np.ndarray  # (F,) frame indices in the pack


def spread_frames(pack: dict, count: int) -> np.ndarray:
    """`count` frame indices spread evenly over the pack (so over its clips)."""
    total = len(pack["rotvecs"])
    return np.unique(np.linspace(0, total - 1, min(count, total)).round().astype(np.int64))


def pack_frames(pack: dict, db, body, shape, frames) -> GarmentFrames:
    """Posed drapes of the pack's `frames` (indices) for the database's garment on body `shape` (beta0)."""
    frames = np.asarray(frames, dtype=np.int64)
    rest = np.asarray(pack["rest"], dtype=np.float64)
    skin_i = np.ascontiguousarray(db.skin_indices, dtype=np.int32)
    skin_w = np.ascontiguousarray(db.skin_weights, dtype=np.float64)
    heads = np.ascontiguousarray(shape.heads, dtype=np.float64)
    transforms = np.empty((len(frames), body.n_bones, 3, 4))
    unposed = rest[None] + np.asarray(pack["offsets"][frames], dtype=np.float64)
    drapes = np.empty_like(unposed)
    for n, f in enumerate(frames):
        forward_kinematics(np.asarray(pack["rotvecs"][f], dtype=np.float64), np.zeros(3), heads, body.parents,
                           transforms[n])
        linear_blend_skinning(unposed[n], skin_i, skin_w, transforms[n], drapes[n])
    return GarmentFrames(rest, np.asarray(pack["faces"]), skin_i, skin_w, transforms, drapes, unposed, frames)


def drape_clearance(body, shape, data: GarmentFrames) -> np.ndarray:
    """(F,) per frame the largest distance of a drape vertex from the posed body's vertices (metres): how far the
    KDSM must reach beyond the body to hold the drapes."""
    from scipy.spatial import cKDTree

    ids = body.body_vertex_ids
    out = np.empty(len(data.drapes))
    for n, transforms in enumerate(data.transforms):
        distance, _ = cKDTree(body.posed_vertices(shape, transforms)[ids]).query(data.drapes[n])
        out[n] = distance.max()
    return out


@dataclass
class FrameTargets:
    """Material positions u^m (V, 3) and per-vertex status (V,) of each method for one frame."""

    material: dict  # method -> (V, 3)
    status: dict  # method -> (V,) int8 (inverse.SINGLE ... FALLBACK)
    morph_rounds: int
    candidate_counts: np.ndarray  # (V,) candidate parents after pruning
    overflow: int


class TargetBuilder:
    """Inverse embedding of the drapes of one garment in one KDSM (what stays the same from frame to frame)."""

    def __init__(self, kdsm: KDSM, body, shape, data: GarmentFrames, settings: TargetSettings = TargetSettings(),
                 seed: int = 0):
        self.kdsm, self.body, self.shape, self.data, self.settings = kdsm, body, shape, data, settings
        self.laplacian = graph_laplacian(mesh_edges(data.faces), len(data.rest))
        self.face_groups, self.point_groups = region_groups(body, data.skin_indices, data.skin_weights,
                                                            settings.region_minimum)
        self.rng = np.random.default_rng(seed)

    def frame(self, n: int) -> FrameTargets:
        """Every method's u^m for frame n of the data (see the module docstring)."""
        s, data = self.settings, self.data
        transforms = data.transforms[n]
        drape = data.drapes[n]
        candidates = candidate_parents(self.kdsm, self.kdsm.posed_vertices(transforms), drape, s.eps)
        guess = surface_offset_guess(self.body.posed_vertices(self.shape, transforms), self.shape.vertices,
                                     self.body.body_faces, drape, self.face_groups, self.point_groups)
        unposed = data.unposed[n]  # also the fallback of points in no tet
        method1, status1 = method1_material(candidates, unposed, self.rng)
        paper, status_p, _ = hybrid_material(candidates, guess, unposed, self.laplacian, s.threshold)
        hybrid_guess = unposed if s.guess == "unposed" else guess
        hybrid, status_h, rounds = hybrid_material(candidates, hybrid_guess, unposed, self.laplacian, s.threshold,
                                                   tuple(s.relaxed))
        v = len(drape)
        return FrameTargets(
            material={"fixed": data.rest.copy(), "method1": method1, "method2": guess, "hybrid_paper": paper,
                      "hybrid": hybrid},
            status={"fixed": np.zeros(v, np.int8), "method1": status1, "method2": np.zeros(v, np.int8),
                    "hybrid_paper": status_p, "hybrid": status_h},
            morph_rounds=rounds, candidate_counts=candidates.counts, overflow=candidates.overflow)


def training_targets(kdsm: KDSM, body, shape, data: GarmentFrames, settings: TargetSettings = TargetSettings(),
                     progress: bool = False):
    """The hybrid method's plastic displacements d(theta) (F, V, 3) = u^m - u^{m_o} of every frame of `data`, and
    each vertex's status (F, V) int8 (inverse.SINGLE ... FALLBACK): what a pose model of d learns."""
    builder = TargetBuilder(kdsm, body, shape, data, settings)
    displacements = np.empty_like(data.drapes)
    status = np.empty(data.drapes.shape[:2], dtype=np.int8)
    for n in range(len(data.drapes)):
        targets = builder.frame(n)
        displacements[n] = targets.material["hybrid"] - data.rest
        status[n] = targets.status["hybrid"]
        if progress and n % 100 == 0:
            print(f"targets {n}/{len(data.drapes)}", file=sys.stderr)
    return displacements, status


def reconstruction_table(kdsm: KDSM, body, shape, data: GarmentFrames, settings: TargetSettings = TargetSettings(),
                         seed: int = 0, progress: bool = False) -> dict:
    """Table 1 of the paper for `data`: per method, the vertex error (mm: mean, 99th percentile, max) of its d
    pushed through the run-time map, the edge variation |Delta d| (mm: mean, max), vertices skinned outside the
    shell at run time and, for the inverse methods, vertices in no posed tet (fallback). For scale,
    "garment_skinning": the error of the rest garment skinned with its own weights (no KDSM)."""
    builder = TargetBuilder(kdsm, body, shape, data, settings, seed)
    edges = mesh_edges(data.faces)
    poser = KdsmPoser(kdsm, data.rest, data.skin_indices, data.skin_weights)
    errors = {m: [] for m in METHODS}
    delta = {m: [] for m in METHODS}
    outside = {m: 0 for m in METHODS}
    fallback = {m: 0 for m in METHODS}
    statuses = np.zeros(len(STATUS_NAMES), dtype=np.int64)
    rounds, overflow, started = [], 0, time.perf_counter()
    skinned_error = []
    for n in range(len(data.drapes)):
        skinned = linear_blend_skinning(data.rest, data.skin_indices, data.skin_weights, data.transforms[n],
                                        np.empty_like(data.rest))
        skinned_error.append(np.linalg.norm(skinned - data.drapes[n], axis=1))
        targets = builder.frame(n)
        rounds.append(targets.morph_rounds)
        overflow += targets.overflow
        statuses += np.bincount(targets.status["hybrid"], minlength=len(STATUS_NAMES))
        for m in METHODS:
            d = targets.material[m] - data.rest
            posed = poser.pose(data.transforms[n], d)
            errors[m].append(np.linalg.norm(posed - data.drapes[n], axis=1))
            delta[m].append(np.linalg.norm(d[edges[:, 0]] - d[edges[:, 1]], axis=1))
            outside[m] += poser.fallback_count
            fallback[m] += int((targets.status[m] == FALLBACK).sum())
        if progress and n % 20 == 0:
            print(f"frame {n}/{len(data.drapes)} {time.perf_counter() - started:.0f}s", file=sys.stderr)
    table = {}
    total = len(data.drapes) * len(data.rest)
    for m in METHODS:
        e = np.concatenate(errors[m]) * 1e3
        dd = np.concatenate(delta[m]) * 1e3
        table[m] = {"error_mean_mm": float(e.mean()), "error_p99_mm": float(np.percentile(e, 99)),
                    "error_max_mm": float(e.max()), "within_0.5mm": float((e <= 0.5).mean()),
                    "delta_d_mean_mm": float(dd.mean()), "delta_d_max_mm": float(dd.max()),
                    "skinned_outside_shell": int(outside[m]), "fallback_vertices": int(fallback[m]),
                    "fallback_fraction": fallback[m] / total}
    e = np.concatenate(skinned_error) * 1e3
    skinned = {"error_mean_mm": float(e.mean()), "error_p99_mm": float(np.percentile(e, 99)),
               "error_max_mm": float(e.max())}
    return {"frames": int(len(data.drapes)), "vertices": int(len(data.rest)), "methods": table,
            "garment_skinning": skinned,
            "hybrid_status": dict(zip(STATUS_NAMES, statuses.tolist())),
            "morph_rounds_mean": float(np.mean(rounds)), "candidate_overflow": int(overflow),
            "seconds_per_frame": (time.perf_counter() - started) / max(1, len(data.drapes))}


def main(argv=None) -> int:
    import argparse

    from ..body import AnnyBody
    from ..offline.sequences import load_sequence_pack
    from ..engine.database import read_database

    parser = argparse.ArgumentParser(prog="python -m agentdress_ros.offline.kdsm_training", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True)
    parser.add_argument("--pack", required=True)
    parser.add_argument("--frames", type=int, default=200, help="frames spread evenly over the pack")
    defaults = KDSMSettings()
    parser.add_argument("--spacing", type=float, default=defaults.spacing)
    parser.add_argument("--margin", type=float, default=0.02, help="thickness = the drapes' clearance + margin")
    parser.add_argument("--clearance-frames", type=int, default=0,
                        help="frames measured for the clearance, spread over the pack (0: every frame)")
    parser.add_argument("--clearance-quantile", type=float, default=1.0,
                        help="quantile of the frames' clearances the shell holds (1: every frame; below 1 the "
                        "drapes of the farthest frames partly fall back to skinning)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", default=None, help="write the KDSM to this .npz (mesh.save_kdsm)")
    args = parser.parse_args(argv)

    db = read_database(args.database)
    body = AnnyBody()
    shape = body.shape(db.beta0)
    pack = load_sequence_pack(args.pack)
    measured = spread_frames(pack, args.clearance_frames or len(pack["rotvecs"]))
    clearance = drape_clearance(body, shape, pack_frames(pack, db, body, shape, measured))
    thickness = float(np.quantile(clearance, args.clearance_quantile) + args.margin)
    settings = KDSMSettings(spacing=args.spacing, thickness=thickness, reach=thickness)
    kdsm = build_kdsm(body, shape, settings, crop_points=db.rest)
    if args.save:
        save_kdsm(args.save, kdsm)
    data = pack_frames(pack, db, body, shape, spread_frames(pack, args.frames))
    report = {"kdsm": {**kdsm.info, "clearance_max_m": float(clearance.max()),
                       "clearance_p99_m": float(np.percentile(clearance, 99)), "clearance_frames": int(len(measured))},
              "table": reconstruction_table(kdsm, body, shape, data, seed=args.seed, progress=True),
              "settings": asdict(settings)}
    json.dump(report, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
