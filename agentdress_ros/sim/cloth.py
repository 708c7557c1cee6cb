"""A newton VBD cloth against an animated body: the simulation that drapes and sequences share.

`ClothSim` holds one garment (a triangle mesh with a rest shape) and one body collider (a triangle mesh whose
points may move every substep). `frame(body_to=...)` advances one frame while the body moves linearly from where
it is to `body_to`; `frame()` advances one frame with the body still.

Animating the collider (newton 1.8 has no deforming-mesh API, so this writes newton's own buffers):
- the body shape's `wp.Mesh` (`model.shape_source[0].mesh`) gets new points *and* vertex velocities every substep
  (contact friction uses the surface's velocity), then `refit()` (~0.5 ms at 26k triangles);
- the shape's local collision box (`model.shape_collision_aabb_lower/upper`) is reset to the new points' bounds,
  or contacts are silently dropped once the body leaves the box it had at build time;
- pinned (kinematic) garment vertices are written into both states of the pair every substep.
Moving the body once per frame instead of per substep lets the cloth tunnel through fast limbs. On the CPU the
solver's substeps are recorded once as warp graphs and replayed; the body's points, refit (a host call, never
recorded) and box are written between replays, into the buffers the graphs read.
"""
from __future__ import annotations

import math

import numpy as np

from .settings import DrapeSettings, require_newton

# Slack around the body's bounds for its collision box: contacts are detected up to radius + gap off the surface.
_BOX_PAD = 0.05


def check_mesh(name: str, vertices, faces=None) -> tuple[np.ndarray, np.ndarray | None]:
    """(vertices (N, 3) float64, faces (F, 3) int32 or None) after checking shapes, finiteness and indices."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"{name} vertices must be (N, 3), got {vertices.shape}")
    if not np.isfinite(vertices).all():
        raise ValueError(f"{name} vertices contain NaN or Inf")
    if faces is None:
        return vertices, None
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"{name} faces must be (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{name} faces index outside 0..{len(vertices) - 1}")
    return vertices, faces.astype(np.int32)


class ClothSim:
    """One garment simulated against one (possibly moving) body mesh; see the module docstring.

    start (V, 3) the cloth's initial positions, faces (F, 3), rest (V, 3) its undeformed shape (default: start),
    body_vertices (N, 3) and body_faces (G, 3) the collider's initial surface (outward normals), pinned (P,) the
    indices of kinematic garment vertices (held at `start`, or moved by `frame(pinned_to=...)`).
    """

    def __init__(self, start, faces, body_vertices, body_faces, settings: DrapeSettings | None = None,
                 rest=None, pinned=None):
        self.settings = s = DrapeSettings() if settings is None else settings
        start, faces = check_mesh("garment", start, faces)
        rest = start if rest is None else check_mesh("rest", rest)[0]
        if rest.shape != start.shape:
            raise ValueError(f"rest vertices {rest.shape} must match the start {start.shape}")
        body, body_faces = check_mesh("body", body_vertices, body_faces)
        if s.substeps < 1 or s.iterations < 1 or s.collide_every < 1 or s.max_frames < 1:
            raise ValueError("substeps, iterations, collide_every and max_frames must be >= 1")
        pinned = np.unique(np.asarray([] if pinned is None else pinned, dtype=np.int64))
        if len(pinned) and (pinned[0] < 0 or pinned[-1] >= len(start)):
            raise ValueError(f"pinned vertex indices must lie in 0..{len(start) - 1}")
        self.faces, self.rest, self.pinned = faces, rest, pinned
        wp, newton = require_newton()
        self._wp = wp
        mu, lam = s.lame
        self.device = device = wp.get_device(s.device)
        with wp.ScopedDevice(device):
            builder = newton.ModelBuilder(gravity=(0.0, 0.0, s.gravity))
            builder.add_cloth_mesh(
                pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                vertices=rest.astype(np.float32), indices=faces.ravel(), density=s.area_density,
                tri_ke=mu, tri_ka=lam, tri_kd=s.membrane_damping,
                edge_ke=s.bending_stiffness, edge_kd=s.bending_damping,
                particle_radius=s.particle_radius,
            )
            if len(builder.tri_indices) != len(faces):
                raise ValueError("the garment's rest shape has degenerate triangles (newton drops them)")
            body_cfg = newton.ModelBuilder.ShapeConfig(
                ke=s.contact_stiffness, kd=s.contact_damping, mu=s.friction, margin=s.body_margin, density=0.0,
                has_shape_collision=False, has_particle_collision=True,
            )
            mesh = newton.Mesh(body.astype(np.float32), body_faces.ravel(), compute_inertia=False)
            self.body_shape = builder.add_shape_mesh(-1, mesh=mesh, cfg=body_cfg)
            builder.color(include_bending=True)
            self.model = model = builder.finalize(device=device)
            # Particle-shape contacts average ke/kd arithmetically and mu geometrically between the model's soft
            # contact values and the shape's: set both to the same numbers.
            model.soft_contact_ke = s.contact_stiffness
            model.soft_contact_kd = s.contact_damping
            model.soft_contact_mu = s.friction
            if len(pinned):  # kinematic vertices: the solver leaves inactive particles where they are
                flags = model.particle_flags.numpy()
                flags[pinned] &= ~np.asarray(newton.ParticleFlags.ACTIVE, dtype=flags.dtype)
                model.particle_flags = wp.array(flags, dtype=model.particle_flags.dtype, device=device)
            self.pipeline = newton.CollisionPipeline(
                model, soft_contact_gap=s.contact_gap,
                enable_rigid_soft_full_surface_contact=s.full_surface_contact,
            )
            self.contacts = self.pipeline.contacts()
            self.solver = newton.solvers.SolverVBD(
                model, iterations=s.iterations,
                particle_enable_self_contact=s.self_contact,
                particle_self_contact_margin=s.self_contact_margin,
                particle_self_contact_gap=s.self_contact_gap,
            )
            self.states = [model.state(), model.state()]
            self.control = model.control()
        self.body_mesh = model.shape_source[self.body_shape].mesh
        self.body_vertices = body.copy()
        self.pinned_positions = start[pinned].copy()
        self.set_state(start, np.zeros_like(start))
        self.frame_dt = 1.0 / s.fps
        self._graphs = None  # one recorded substep per index of the repeating run (see _capture_substeps)
        self._eager_frames = 0

    # -- state ------------------------------------------------------------------------------------------------
    def set_state(self, positions, velocities) -> None:
        """Set every particle's position and velocity (V, 3) in both states of the pair."""
        q = np.asarray(positions, dtype=np.float32)
        qd = np.asarray(velocities, dtype=np.float32)
        for state in self.states:
            state.particle_q.assign(q)
            state.particle_qd.assign(qd)

    def positions(self) -> np.ndarray:
        """Current particle positions (V, 3) float64."""
        return self.states[0].particle_q.numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Current particle velocities (V, 3) float64."""
        return self.states[0].particle_qd.numpy().astype(np.float64)

    def scale_velocities(self, factor: float) -> None:
        """Multiply every particle velocity by factor (the settings' drag, applied once per frame)."""
        state = self.states[0]
        state.particle_qd.assign(state.particle_qd.numpy() * np.float32(factor))

    # -- the body ---------------------------------------------------------------------------------------------
    def _write_body(self, points: np.ndarray, velocities: np.ndarray) -> None:
        wp = self._wp
        mesh = self.body_mesh
        mesh.points.assign(points.astype(np.float32))
        mesh.velocities.assign(velocities.astype(np.float32))
        mesh.refit()
        lower = points.min(axis=0) - _BOX_PAD
        upper = points.max(axis=0) + _BOX_PAD
        index = self.body_shape
        for array, value in ((self.model.shape_collision_aabb_lower, lower),
                             (self.model.shape_collision_aabb_upper, upper)):
            host = array.numpy()
            host[index] = value
            array.assign(wp.array(host, dtype=array.dtype, device=self.device))

    def _write_pinned(self, positions: np.ndarray) -> None:
        if not len(self.pinned):
            return
        for state in self.states:
            q = state.particle_q.numpy()
            q[self.pinned] = positions
            state.particle_q.assign(q)
            qd = state.particle_qd.numpy()
            qd[self.pinned] = 0.0
            state.particle_qd.assign(qd)

    # -- stepping ---------------------------------------------------------------------------------------------
    def _substep(self, substep: int, dt: float) -> None:
        a, b = self.states[substep % 2], self.states[(substep + 1) % 2]
        if substep % self.settings.collide_every == 0:
            self.pipeline.collide(a, self.contacts)
        self.solver.step(a, b, self.control, self.contacts, dt)

    def _finish_frame(self, substeps: int) -> None:
        if substeps % 2:  # an odd count leaves the newest state in the second slot
            self.states.reverse()

    def frame(self, body_to=None, pinned_to=None, substeps: int | None = None) -> np.ndarray:
        """Advance one frame (1 / fps) and return the positions (V, 3) float64.

        body_to (N, 3): the body surface at the end of the frame; every substep moves it linearly from where it is,
        with the matching velocity. pinned_to (P, 3): the pinned vertices at the end of the frame, likewise.
        None keeps the body (or the pinned vertices) still. substeps: this frame's solver steps (default
        settings.substeps), more where the body moves fast, so that no step carries it through the cloth.
        """
        s = self.settings
        substeps = s.substeps if substeps is None else int(substeps)
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        dt = self.frame_dt / substeps
        replay = self._graphs if substeps == s.substeps else None  # the graphs hold the default step's dt
        body_from, pinned_from = self.body_vertices, self.pinned_positions
        if body_to is not None:
            body_to = np.asarray(body_to, dtype=np.float64)
            if body_to.shape != body_from.shape:
                raise ValueError(f"body_to must be {body_from.shape}, got {body_to.shape}")
            body_velocity = (body_to - body_from) / self.frame_dt
        if pinned_to is not None:
            pinned_to = np.asarray(pinned_to, dtype=np.float64).reshape(pinned_from.shape)
        with self._wp.ScopedDevice(self.device):
            for substep in range(substeps):
                alpha = (substep + 1) / substeps
                if body_to is not None:
                    self._write_body(body_from + alpha * (body_to - body_from), body_velocity)
                if pinned_to is not None:
                    self._write_pinned(pinned_from + alpha * (pinned_to - pinned_from))
                if replay:
                    self._wp.capture_launch(replay[substep % len(replay)])
                else:
                    self._substep(substep, dt)
            if body_to is not None:  # the surface stops with the frame
                self._write_body(body_to, np.zeros_like(body_to))
                self.body_vertices = body_to.copy()
            if pinned_to is not None:
                self.pinned_positions = pinned_to.copy()
        self._finish_frame(substeps)
        if substeps == s.substeps:
            self._capture_substeps()
        return self.positions()

    def _capture_substeps(self) -> None:
        """After one eager frame every lazily built buffer exists: record each substep of the shortest run that
        repeats (two, the state pair swapping, or the collision period if longer) as a warp graph, once - recording
        does not execute it, but costs as much Python as running it - and replay those from then on, without
        Python's launch overhead (on the CPU a substep of a 1,200-vertex shirt runs 3-5x faster). The body and the
        pinned vertices are written into the same buffers between replays, so moving frames replay too."""
        s = self.settings
        self._eager_frames += 1
        period = math.lcm(2, s.collide_every)
        if not (s.graph and self.device.is_cpu and s.substeps % period == 0 and self._eager_frames == 1):
            return
        dt = self.frame_dt / s.substeps
        graphs = []
        try:
            for substep in range(period):
                with self._wp.ScopedCapture(device=self.device) as capture:
                    self._substep(substep, dt)
                graphs.append(capture.graph)
        except Exception:  # noqa: BLE001 - capture is an optimisation only
            graphs = None
        self._graphs = graphs
