"""One ground-truth drape: a garment settled on a posed, shaped body with newton's VBD cloth solver.

`drape(garment_vertices (V, 3), garment_faces (F, 3), body_vertices (N, 3), body_faces (G, 3), settings,
rest_vertices=None, pinned=None, body_path=None, pinned_path=None) -> DrapeResult`.

Two ways in. Animated (the ground truth's default): the cloth starts from the garment at rest on the body at rest,
where it is clean, and the body collider (`sim.cloth.ClothSim`) is carried through `body_path` into the pose while
the cloth simulates; a skinned start would already sit folded into the armpit in arms-down poses, and a static
collider cannot pull it out. Static: the cloth starts at `garment_vertices` (e.g. the garment skinned to the pose,
or a finished drape's offset carried to another shape) against the body standing in the pose; start vertices inside
the body are first lifted out (`push_out_of_body`). Either way the cloth then settles with the body still until it
is quasi-static (a high percentile of the per-frame vertex speed stays below a threshold for a few frames) or a
frame budget runs out. The result carries the convergence numbers, the garment vertices inside the body by
generalised winding number (split into those trapped where the body passes into itself and those truly inside,
`garment.inside`), per-triangle stretch, and the displacement from the start.

Rest shape. The cloth's undeformed shape is `rest_vertices`: for ground truth pass the garment as sewn, i.e. fitted
to the *same body shape at rest pose*, `garment.rest_vertices(body, body.shape(beta))`. Skinning to a pose
stretches and shears the garment (armpits, shoulders with raised arms, candy-wrapper twists); if the warm start
were also the rest shape, those skinning distortions would be the cloth's stress-free state and the simulation would
have no reason to undo them, biasing the "ground truth" towards plain skinning, the very baseline the data-driven
model is meant to improve on. With no `rest_vertices` the warm start is used as the rest shape (handy for tests and
for garments with no template).

Membrane. newton 1.8's VBD triangle energy is a *stable Neo-Hookean membrane* (Smith et al. 2018 adapted to shells,
`evaluate_neo_hookean_membrane_force_hessian` in newton/_src/solvers/vbd/particle_vbd_kernels.py), not StVK:
psi = mu/2 (I_C - 2) + lambda'/2 (J - 1 - mu/lambda')^2 with lambda' = lambda + mu, per unit rest area, where
(mu, lambda) = (tri_ke, tri_ka) (`tri_materials[:, 0]` and `[:, 1]`). Expanding about F = I gives
psi = mu |eps|^2 + lambda/2 tr(eps)^2 + O(eps^3): the same small-strain law as StVK, psi = mu |E|^2 + lambda/2 tr(E)^2,
with the same Lame pair. Drapes average ~2 % stretch, so the membrane is StVK's to first order; the two differ in
how they behave at large strain, which only a few triangles reach (20-40 % where a T-shirt hangs on the shoulder
points with this soft Y = 30 N/m; there the Neo-Hookean law is the softer one). See `membrane_lame`.

Bending is newton's dihedral-angle energy E = ke/2 * |e_rest| * (theta - theta_rest)^2 per interior edge
(`edge_ke` = `bending_stiffness`, N m/m = N), rest angles from the rest shape.

Determinism: on the CPU, warp runs kernels single-threaded, so the same inputs give bit-identical outputs.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .cloth import ClothSim, check_mesh
from .settings import NEWTON_VERSION, DrapeSettings, membrane_lame, require_newton  # noqa: F401


@dataclass
class DrapeResult:
    """A drape (V, 3) float64 and its diagnostics (all scalars, so a build can store them beside the drape)."""

    vertices: np.ndarray
    converged: bool  # the speed test passed before max_frames
    frames: int  # frames simulated (ramp included)
    ramp_frames: int  # frames spent carrying the body into the pose (0: a static collider)
    seconds: float  # wall time of the whole call (model build + simulation + checks)
    sim_seconds: float  # wall time of the frame loop alone
    max_speed: float  # [m/s] largest vertex speed over the last frame
    percentile_speed: float  # [m/s] the settings' percentile of vertex speed over the last frame
    residual: float  # [m] mean vertex displacement over the last frame
    inside_count: int  # garment vertices inside the body (generalised winding number > 1/2)
    inside_overlap_count: int  # of those, the ones trapped where the body passes into itself
    inside_true_count: int  # the others: cloth truly through the skin
    pushed_out: int  # warm-start vertices found inside the body and lifted out before simulating
    min_clearance: float  # [m] smallest signed distance of a garment vertex to the body surface
    strain_mean: float  # mean over triangles of (largest singular value of F) - 1, F vs the rest shape
    strain_max: float  # max over triangles of the same
    compression_max: float  # max over triangles of 1 - (smallest singular value of F)
    warm_strain_max: float  # strain_max of the warm start itself (the skinning's stretch)
    displacement_mean: float  # [m] mean distance of the drape from the warm start
    displacement_p95: float  # [m] its 95th percentile
    displacement_max: float  # [m] its maximum
    speed_history: np.ndarray  # (frames,) [m/s] the percentile speed of every frame (for tuning plots)


def triangle_stretch(vertices: np.ndarray, rest_vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Principal stretches (F, 2), descending: singular values of each triangle's deformation gradient.

    F maps the rest triangle (in its own 2D frame) to the deformed one (3D): F = Ds Dm^-1 with Dm the 2x2 rest edge
    matrix in an orthonormal in-plane basis and Ds the 3x2 deformed edge matrix. 1 = unstretched.
    """
    faces = np.asarray(faces)
    r = np.asarray(rest_vertices, dtype=np.float64)[faces]
    x = np.asarray(vertices, dtype=np.float64)[faces]
    e1, e2 = r[:, 1] - r[:, 0], r[:, 2] - r[:, 0]
    u = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    normal = np.cross(e1, e2)
    v = np.cross(normal / np.linalg.norm(normal, axis=1, keepdims=True), u)
    dm = np.stack([np.stack([(e1 * u).sum(1), (e2 * u).sum(1)], 1),
                   np.stack([(e1 * v).sum(1), (e2 * v).sum(1)], 1)], 1)  # (F, 2, 2) rows: u, v; columns: e1, e2
    ds = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]], axis=2)  # (F, 3, 2)
    deformation = ds @ np.linalg.inv(dm)
    return np.linalg.svd(deformation, compute_uv=False)


def push_out_of_body(points, body_vertices, body_faces, clearance: float, mesh=None):
    """Move the points (V, 3) that lie inside the closed body surface to `clearance` outside its surface along the
    closest face's normal. Returns (points (V, 3) float64, moved count). mesh: that surface as a trimesh.Trimesh when
    the caller has one (its search tree, most of a query's cost, is then built once).

    A skinned warm start can put a few garment vertices inside the body (a swinging arm against the torso): newton
    only detects particle-shape contacts within radius + gap of the surface, so a vertex deeper than that is never
    pushed out. Lifting them out before simulating costs one closest-point query.
    """
    import trimesh

    points = np.array(points, dtype=np.float64, copy=True)
    mesh = trimesh.Trimesh(body_vertices, body_faces, process=False) if mesh is None else mesh
    closest, distance, face_ids = trimesh.proximity.closest_point(mesh, points)
    normals = mesh.face_normals[face_ids]
    inside = ((points - closest) * normals).sum(axis=1) < 0.0
    points[inside] = closest[inside] + clearance * normals[inside]
    return points, int(np.count_nonzero(inside))


def drape(garment_vertices, garment_faces, body_vertices, body_faces, settings: DrapeSettings | None = None,
          rest_vertices=None, pinned=None, body_path=None, pinned_path=None) -> DrapeResult:
    """Drape a garment on a body to quasi-static equilibrium; see the module docstring.

    garment_vertices (V, 3) the cloth's start, garment_faces (F, 3), body_vertices (N, 3) and body_faces (G, 3) the
    posed body's closed surface (outward normals), rest_vertices (V, 3) the cloth's undeformed shape (default: the
    start), pinned (P,) indices of garment vertices held kinematically (a waistband: friction alone cannot hold
    trousers on the hips).

    Animated collider: body_path (R, N, 3) are body surfaces the body passes through, one per frame, before it
    reaches `body_vertices` (the target pose); the cloth starts where it is clean (the garment at rest on the body
    at rest) and is carried into the pose, then settles with the body still. pinned_path (R + 1, P, 3) holds the
    pinned vertices at each keyframe and, last, in the target pose. Without a path the body stands in the pose from
    the start, and start vertices inside it are first lifted out (`push_out_of_body`).
    Raises RuntimeError if the simulation produces non-finite positions.
    """
    import trimesh

    from ..garment.inside import inside_report

    s = DrapeSettings() if settings is None else settings
    start = time.perf_counter()
    warm, faces = check_mesh("garment", garment_vertices, garment_faces)
    body, body_tris = check_mesh("body", body_vertices, body_faces)
    path = None if body_path is None else np.asarray(body_path, dtype=np.float64)
    if path is not None and (path.ndim != 3 or path.shape[1:] != body.shape or not np.isfinite(path).all()):
        raise ValueError(f"body_path must be finite (R, {len(body)}, 3), got {path.shape}")
    pinned = np.unique(np.asarray([] if pinned is None else pinned, dtype=np.int64))
    if len(pinned) and (pinned[0] < 0 or pinned[-1] >= len(warm)):
        raise ValueError(f"pinned vertex indices must lie in 0..{len(warm) - 1}")
    body_mesh = trimesh.Trimesh(body, body_tris, process=False)  # the pose's surface: one search tree per drape
    if path is None:
        start_vertices, pushed_out = push_out_of_body(warm, body, body_tris, s.particle_radius + s.body_margin,
                                                      mesh=body_mesh)
        collider = body
    else:
        start_vertices, pushed_out, collider = warm, 0, path[0]
    sim = ClothSim(start_vertices, faces, collider, body_tris, s, rest=rest_vertices, pinned=pinned)
    rest = sim.rest
    if pinned_path is not None:
        pinned_path = np.asarray(pinned_path, dtype=np.float64)
        if path is None or pinned_path.shape != (len(path) + 1, len(pinned), 3):
            raise ValueError(f"pinned_path must be (R + 1, {len(pinned)}, 3) beside a body_path of R keyframes")
    sim_start = time.perf_counter()
    frame = 0
    if path is not None:  # carry the cloth from the first keyframe into the pose, then settle
        targets = list(path[1:]) + [body]
        for k, target in enumerate(targets):
            pin = None if pinned_path is None else pinned_path[k + 1]
            current = sim.frame(body_to=target, pinned_to=pin)
            frame += 1
            _check_finite(current, frame, s)
            if s.velocity_retention != 1.0:
                sim.scale_velocities(s.velocity_retention)
    ramp_frames = frame
    previous = sim.positions()
    calm = 0
    history = []
    converged = False
    current, speed, moved, percentile_speed = previous, np.zeros(len(previous)), np.zeros(len(previous)), 0.0
    for settle in range(1, s.max_frames + 1):
        current = sim.frame()
        frame += 1
        _check_finite(current, frame, s)
        if s.velocity_retention != 1.0:
            sim.scale_velocities(s.velocity_retention)
        moved = np.linalg.norm(current - previous, axis=1)
        previous = current
        speed = moved / sim.frame_dt
        percentile_speed = float(np.percentile(speed, s.speed_percentile))
        history.append(percentile_speed)
        calm = calm + 1 if percentile_speed < s.speed_threshold else 0
        if settle >= s.min_frames and calm >= s.converged_frames:
            converged = True
            break
    sim_seconds = time.perf_counter() - sim_start

    from ..garment.binding import signed_clearance

    clearance = signed_clearance(current, body, body_tris, mesh=body_mesh)
    inside = inside_report(current, body, body_tris)
    stretch = triangle_stretch(current, rest, faces)
    warm_stretch = triangle_stretch(warm, rest, faces)
    displacement = np.linalg.norm(current - warm, axis=1)
    return DrapeResult(
        vertices=current,
        converged=converged,
        frames=frame,
        ramp_frames=ramp_frames,
        seconds=time.perf_counter() - start,
        sim_seconds=sim_seconds,
        max_speed=float(speed.max()),
        percentile_speed=percentile_speed,
        residual=float(moved.mean()),
        inside_count=inside["inside_count"],
        inside_overlap_count=inside["overlap_count"],
        inside_true_count=inside["truly_inside_count"],
        pushed_out=pushed_out,
        min_clearance=float(clearance.min()),
        strain_mean=float((stretch[:, 0] - 1.0).mean()),
        strain_max=float((stretch[:, 0] - 1.0).max()),
        compression_max=float((1.0 - stretch[:, 1]).max()),
        warm_strain_max=float((warm_stretch[:, 0] - 1.0).max()),
        displacement_mean=float(displacement.mean()),
        displacement_p95=float(np.percentile(displacement, 95)),
        displacement_max=float(displacement.max()),
        speed_history=np.asarray(history),
    )


def _check_finite(positions, frame: int, settings: DrapeSettings) -> None:
    if not np.isfinite(positions).all():
        raise RuntimeError(f"drape diverged at frame {frame} (non-finite positions); settings: {settings}")
