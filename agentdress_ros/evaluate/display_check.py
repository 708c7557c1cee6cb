"""`python -m agentdress_ros.evaluate.display_check`: what the display shows, measured geometrically (JSON on stdout).

The models are those the node runs for `make run` (T-shirt and trousers from the shipped databases with the node
default's engine knobs, the body published), over the demo walk at 30 fps and a shape sweep (the demo's --shape-sweep shapes), for each display
refinement asked:
- skin through the cloth: drawn body faces whose centre lies outside a garment where it covers the body (the
  closest cloth facing the skin's way at least `edge_band` inside the garment's open edges), with the covered
  faces left out and the kept band sunk (as published), and with every body face drawn (before); and the drawn
  faces poking through within `edge_band` of the open edges (a cuff, a hem, a collar: where the rest leaves them
  out, and where a viewer sees a saw-tooth of skin along the edge);
- gaps: body faces left out whose centre no garment lies over (no cloth facing the skin's way within 6 cm along
  its normal: coverage.cloth_over), and those of them a viewer sees from outside (holes: facing one of 16 views
  around the agent with nothing drawn in front of them on a 4 mm depth buffer);
- layering: the share of T-shirt vertices inside the trousers where the trousers cover them, and of trousers vertices
  outside the T-shirt where the T-shirt covers them (through its triangles), with and without the layering;
- cost per frame (median, one thread): the engine's synthesis, the layering push, the refinement.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numba
import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _models(body, databases: dict, subdivision: int, layered: bool):
    from ..ros.params import PARAMETERS, validate
    from ..ros.runtime import GarmentSpec, SceneSpec, build_model_set

    engine = validate("engine", PARAMETERS["engine"].default)  # the node default's knobs, per garment
    garments = tuple(GarmentSpec(g, None, str(p), engine.for_garment(g)) for g, p in databases.items())
    layers = () if layered else tuple((g, 1) for g in databases)  # equal layers: no push
    scene = SceneSpec(garments, True, (0.5, 2 / 3, 0.5, 0.5, 0.5, 0.5), False, subdivision, layers)
    return build_model_set(scene, body)


def check(subdivisions=(0, 1), frames_step: int = 2, sweep_times=(0.0, 5.0, 10.0, 15.0), edge_band: float = 0.03,
          data=ROOT / "data") -> dict:
    from dataclasses import replace

    from ..body import AnnyBody
    from ..garment.coverage import body_part_labels, poke_through, surface_side
    from ..ros.demo import load_clip, sweep_shape
    from ..models.garment_models import BodyModel
    from ..ros.runtime import build_model_set

    body = AnnyBody()
    databases = {g: Path(data, f"{g}_default.h5") for g in ("trousers", "tshirt")}
    motion = load_clip("walk", 30.0)
    frames = range(0, len(motion.rotvecs), frames_step)
    shapes = [tuple(float(b) for b in sweep_shape(t, 20.0)) for t in sweep_times]
    report = {"frames_per_shape": len(frames), "shapes": shapes, "edge_band_m": edge_band, "runs": {}}
    parts = body_part_labels(body, body.body_vertex_ids)  # both body models keep every visible vertex, in this order
    for subdivision in subdivisions:
        for layered in (True, False):
            model_set = _models(body, databases, subdivision, layered)
            plain = BodyModel(body)  # before: every face drawn, nothing sunk
            every_face = plain.faces
            counts = {"drawn_poking": 0, "drawn_poking_at_edges": 0, "poking_all_faces": 0, "outer_inside_inner": 0,
                      "outer_vertices": 0, "inner_through_outer": 0, "inner_under_outer": 0, "gaps": 0, "seen": 0,
                      "drawn_inner_through_outer": 0}
            timing = {"engine_ms": [], "layer_ms": [], "refine_ms": [], "skin_ms": []}
            for beta in shapes:
                model_set = build_model_set(replace(model_set.scene, beta=beta), body, model_set)
                plain.set_shape(beta)
                models = model_set.models
                for model in models.values():
                    model.reset()
                left_out = _left_out(every_face, models["body"].faces)
                for f in frames:
                    rotvecs, root = motion.rotvecs[f], motion.root_translation[f]
                    out = {}
                    for name, model in models.items():
                        start = time.perf_counter()
                        out[name] = np.array(model.synthesize(rotvecs, root), dtype=np.float64)
                        total = 1e3 * (time.perf_counter() - start)
                        if name != "body":
                            stages = {key: getattr(model, key, 0.0) for key in ("layer_ms", "refine_ms", "skin_ms")}
                            for key, value in stages.items():
                                timing[key].append(value)
                            timing["engine_ms"].append(total - sum(stages.values()))
                    skin = out["body"]
                    plain_skin = np.array(plain.synthesize(rotvecs, root), dtype=np.float64) if layered else None
                    drawn = models["body"].faces
                    if layered:  # the body is the same without layering
                        gaps, seen = _gaps(skin, left_out, out, models)
                        counts["gaps"] += gaps
                        counts["seen"] += seen
                    for name in ("tshirt", "trousers"):
                        garment, faces = out[name], models[name].faces
                        inside_band = int(poke_through(skin, drawn, garment, faces, edge_band=edge_band,
                                                       vertex_parts=parts).sum())
                        counts["drawn_poking"] += inside_band
                        counts["drawn_poking_at_edges"] += int(poke_through(skin, drawn, garment, faces, edge_band=0.0,
                                                                            vertex_parts=parts).sum()) - inside_band
                        if layered:
                            counts["poking_all_faces"] += int(poke_through(plain_skin, every_face, garment, faces,
                                                                           edge_band=edge_band,
                                                                           vertex_parts=parts).sum())
                    coarse = {g: getattr(models[g], "coarse", None) for g in ("tshirt", "trousers")}
                    shirt = np.array(out["tshirt"] if coarse["tshirt"] is None else coarse["tshirt"], dtype=np.float64)
                    trousers = np.array(out["trousers"] if coarse["trousers"] is None else coarse["trousers"],
                                        dtype=np.float64)
                    inner_faces = getattr(models["trousers"], "base", models["trousers"]).faces
                    inside = surface_side(shirt, trousers, inner_faces, edge_band=0.01) < 0
                    counts["outer_inside_inner"] += int(inside.sum())
                    counts["outer_vertices"] += len(shirt)
                    outer_faces = getattr(models["tshirt"], "base", models["tshirt"]).faces
                    through = surface_side(trousers, shirt, outer_faces, max_gap=0.03, edge_band=0.02)
                    counts["inner_through_outer"] += int((through > 0).sum())
                    counts["inner_under_outer"] += int((through != 0).sum())
                    # the same on the garments as drawn (refined): what the viewer sees of the trousers
                    counts["drawn_inner_through_outer"] += int((surface_side(
                        out["trousers"], out["tshirt"], models["tshirt"].faces, max_gap=0.03, edge_band=0.02) > 0).sum())
            n = len(frames) * len(shapes)
            report["runs"][f"subdivision={subdivision},layered={layered}"] = {
                "frames": n,
                "drawn_body_faces_poking_per_frame": counts["drawn_poking"] / n,
                "drawn_body_faces_poking_at_edges_per_frame": counts["drawn_poking_at_edges"] / n,
                "all_body_faces_poking_per_frame": counts["poking_all_faces"] / n if layered else None,
                "hidden_body_faces_without_cloth_per_frame": counts["gaps"] / n if layered else None,
                "hidden_body_faces_seen_from_outside_per_frame": counts["seen"] / n if layered else None,
                "tshirt_vertices_inside_trousers_pct": 100.0 * counts["outer_inside_inner"] / counts["outer_vertices"],
                "trousers_vertices_through_tshirt_pct": 100.0 * counts["inner_through_outer"]
                / max(counts["inner_under_outer"], 1),
                "drawn_trousers_vertices_through_tshirt_per_frame": counts["drawn_inner_through_outer"] / n,
                "garment_vertices": {g: models[g].n_vertices for g in ("tshirt", "trousers")},
                "body_faces_drawn": len(models["body"].faces), "body_faces": len(every_face),
                "ms_per_garment_frame_p50": {k: float(np.median(v)) for k, v in timing.items()},
            }
    return report


def _left_out(every_face: np.ndarray, drawn: np.ndarray) -> np.ndarray:
    """(H, 3) the faces of every_face (F, 3) that drawn (D, 3) leaves out (either winding)."""
    kept = {tuple(f) for f in np.sort(drawn, axis=1).tolist()}
    return every_face[[tuple(f) not in kept for f in np.sort(every_face, axis=1).tolist()]]


def _gaps(skin, hidden, out: dict, models: dict) -> tuple:
    """(how many of the body's faces left out - hidden (H, 3) over its vertices skin (N, 3) - have no garment over
    their centre along their normal, how many of them a viewer outside sees: seen_from_outside over everything
    drawn)."""
    from ..garment.binding import face_normals
    from ..garment.coverage import cloth_over

    centres = skin[hidden].mean(axis=1)
    directions = face_normals(skin, hidden)
    covered = np.zeros(len(hidden), dtype=bool)
    for name, model in models.items():
        if name != "body":
            covered |= cloth_over(centres, directions, out[name], model.faces, edge_band=0.0)
    meshes = [(out[name], model.faces) for name, model in models.items()]
    return int((~covered).sum()), int(seen_from_outside(meshes, centres, directions).sum())


@numba.njit(cache=True, nogil=True)
def _depth_buffer(screen, depth, faces, buffer):
    """buffer (H, W): the nearest depth (V,) of the triangles faces (G, 3) over each pixel whose centre they cover,
    screen (V, 2) in pixels."""
    height, width = buffer.shape
    for t in range(faces.shape[0]):
        a, b, c = faces[t, 0], faces[t, 1], faces[t, 2]
        x0, y0, x1, y1, x2, y2 = screen[a, 0], screen[a, 1], screen[b, 0], screen[b, 1], screen[c, 0], screen[c, 1]
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if abs(det) < 1e-12:
            continue
        left, right = max(int(np.floor(min(x0, x1, x2))), 0), min(int(np.ceil(max(x0, x1, x2))), width - 1)
        top, bottom = max(int(np.floor(min(y0, y1, y2))), 0), min(int(np.ceil(max(y0, y1, y2))), height - 1)
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                sx, sy = px + 0.5, py + 0.5
                l0 = ((y1 - y2) * (sx - x2) + (x2 - x1) * (sy - y2)) / det
                l1 = ((y2 - y0) * (sx - x2) + (x0 - x2) * (sy - y2)) / det
                l2 = 1.0 - l0 - l1
                if l0 >= 0.0 and l1 >= 0.0 and l2 >= 0.0:
                    z = l0 * depth[a] + l1 * depth[b] + l2 * depth[c]
                    if z < buffer[py, px]:
                        buffer[py, px] = z


def view_directions(azimuths: int = 8, elevations=(0.0, 0.5)) -> np.ndarray:
    """(A x E, 3) unit directions a viewer looks along: around the agent (Z up) at each elevation (radians, looking
    down)."""
    angles = 2 * np.pi * np.arange(azimuths) / azimuths
    return np.array([[np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), -np.sin(e)] for e in elevations for a in angles])


def seen_from_outside(meshes, points, normals, pixel: float = 0.004, tolerance: float = 0.006,
                      directions=None) -> np.ndarray:
    """(P,) bool: points (P, 3) with outward normals (P, 3) - centres of body faces left out - that a viewer sees
    from one of the directions (view_directions): facing it, with nothing of meshes [(vertices (V, 3), faces (G,
    3)), ...] (what is drawn) in front of them by more than `tolerance` on an orthographic depth buffer of `pixel`
    metres. What a hole in the drawn surface looks like from outside."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    everything = np.concatenate([np.asarray(v, dtype=np.float64) for v, _ in meshes])
    centre = everything.mean(axis=0)
    seen = np.zeros(len(points), dtype=bool)
    for look in view_directions() if directions is None else directions:
        up = np.array([0.0, 0.0, 1.0]) - look * look[2]
        up /= np.linalg.norm(up)
        right = np.cross(look, up)
        axes = np.stack([right / pixel, -up / pixel], axis=1)  # metres to pixels, rows down
        corner = (everything - centre) @ axes
        origin = corner.min(axis=0) - 2
        width, height = (corner.max(axis=0) - origin + 3).astype(int)
        buffer = np.full((height, width), np.inf)
        for vertices, faces in meshes:
            local = np.asarray(vertices, dtype=np.float64) - centre
            _depth_buffer(np.ascontiguousarray(local @ axes - origin), np.ascontiguousarray(local @ look),
                          np.ascontiguousarray(faces, dtype=np.int64), buffer)
        local = points - centre
        pixels = np.clip((local @ axes - origin).astype(int), 0, [width - 1, height - 1])
        seen |= (normals @ look < 0) & (local @ look < buffer[pixels[:, 1], pixels[:, 0]] - tolerance)
    return seen


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="display_check", description=__doc__)
    parser.add_argument("--subdivision", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--step", type=int, default=2, help="every n-th frame of the 30 fps walk")
    parser.add_argument("--sweep", type=float, nargs="+", default=[0.0, 5.0, 10.0, 15.0],
                        help="times (s) of the demo's 20 s shape sweep to take shapes at")
    parser.add_argument("--out", default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        report = check(tuple(args.subdivision), args.step, tuple(args.sweep))
    text = json.dumps(report, indent=1)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
