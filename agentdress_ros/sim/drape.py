"""One ground-truth drape: a garment settled on a static, posed, shaped body with newton's VBD cloth solver.

`drape(garment_vertices (V, 3), garment_faces (F, 3), body_vertices (N, 3), body_faces (G, 3), settings,
rest_vertices=None) -> DrapeResult`.

The cloth starts at `garment_vertices` (the caller passes the garment skinned to the pose: a warm start that is
already close to the drape) and is simulated under gravity against the body as a static triangle-mesh collider
until it is quasi-static (a high percentile of the per-frame vertex speed stays below a threshold for a few frames)
or a frame budget runs out. Warm-start vertices inside the body are first lifted out (`push_out_of_body`). The result carries the convergence numbers, the count of garment vertices inside the
body (`signed_clearance` < 0), per-triangle stretch, and the displacement from the warm start.

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

NEWTON_VERSION = "1.8.0"
INSTALL_HINT = f"pip install newton=={NEWTON_VERSION} (the project's `build` extra)"


def require_newton():
    """Import and return (warp, newton), or raise ImportError naming the install command."""
    try:
        import warp as wp

        wp.config.quiet = True  # no banner on every worker process
        import newton
        import newton.solvers  # noqa: F401
    except ImportError as error:
        raise ImportError(f"agentdress_ros.sim needs NVIDIA newton to drape garments: {INSTALL_HINT}") from error
    return wp, newton


def membrane_lame(stretch_stiffness: float, poisson_ratio: float) -> tuple[float, float]:
    """Lame parameters (mu, lambda) [N/m] of a membrane with 2D Young's modulus Y [N/m] and Poisson ratio nu.

    Plane stress (a thin sheet: no stress through the thickness). Hooke's law for plane stress,
        sigma = Y / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]] (eps_xx, eps_yy, 2 eps_xy),
    written as sigma = 2 mu eps + lambda tr(eps) I gives
        mu = Y / (2 (1 + nu)),   lambda = Y nu / (1 - nu^2),
    i.e. the 3D shear modulus and the plane-stress ("2D") lambda = 2 mu lambda_3D / (lambda_3D + 2 mu) rather than
    the 3D lambda_3D = Y nu / ((1 + nu)(1 - 2 nu)). Sources: Sadd, Elasticity (3rd ed.), Sec. 7.2 plane stress; the
    same conversion is used for cloth membranes in e.g. Narain et al. 2012 (ARCSim) and Bridson's course notes.
    With Y in N/m (Young's modulus times thickness) mu and lambda come out in N/m, the units of newton's
    tri_ke/tri_ka (energy per unit rest area). Y = 30 N/m, nu = 0.3 -> mu = 11.54 N/m, lambda = 9.89 N/m.
    """
    Y, nu = float(stretch_stiffness), float(poisson_ratio)
    if not (Y > 0.0 and -1.0 < nu < 1.0):
        raise ValueError(f"need Y > 0 and -1 < nu < 1, got Y={Y}, nu={nu}")
    return Y / (2.0 * (1.0 + nu)), Y * nu / (1.0 - nu * nu)


@dataclass(frozen=True)
class DrapeSettings:
    """Every knob of a drape, with its default. Units: metres, seconds, kilograms, newtons.

    Material (the paper's cloth, in physical units):
      stretch_stiffness   2D Young's modulus Y [N/m] (Young's modulus x thickness), 30.
      poisson_ratio       nu, 0.3. (mu, lambda) = membrane_lame(Y, nu) are newton's tri_ke, tri_ka.
      bending_stiffness   dihedral bending stiffness [N] (newton edge_ke), 1e-5.
      area_density        [kg/m^2], 0.1 (a light T-shirt jersey is 0.12-0.18).
      friction            cloth-body Coulomb friction coefficient, 0.3.
      membrane_damping    newton tri_kd, strain-rate damping of the membrane (objective: rigid motion is not
                          damped), 0. Equilibrium does not depend on it.
      bending_damping     newton edge_kd, 0.
      gravity             [m/s^2] along z (Z up), -9.81.

    Time stepping (VBD: implicit Euler, block Gauss-Seidel over a vertex colouring):
      fps                 frames per second of simulated time, 60. The convergence test runs once per frame.
      substeps            solver steps per frame, 16: dt = 1 / (fps * substeps).
      iterations          VBD iterations per step, 2.
      velocity_retention  factor applied to every particle velocity after each frame, 0.9 (1 = none). Drag speeds
                          the settling; with friction the equilibrium is path dependent, so it moves the result a
                          little (the tuning below includes it).
      graph               on the CPU, record one frame as a warp graph (APIC capture) after the first and replay it
                          (needs an even substep count): ~15 % less Python launch overhead, bit-identical results.
                          Not used on CUDA (untested there: no GPU was available when this was tuned).

      Tuning (2k-vertex T-shirt, reference body, rest pose, against an 8 x 10 run of 300 frames stopped at a 99th
      percentile speed of 2 mm/s): VBD needs *small steps*, not many iterations. Few substeps leave each step
      unconverged and the cloth creeps like a viscous sheet, stretching without end (4 x 5: strain max 77 % and
      growing at 240 frames; 1 x 20: 190 %; both never converged). 16 x 2 at 5 mm/s stopped at 151 frames, 2.8 mm
      mean from the reference; 8 x 4 was 6.4 mm off, 8 x 3 10 mm, 4 x 20 (4x the cost) 9.6 mm, 16 x 1 and 32 x 1
      stopped early (5 mm/s is reached while still creeping) 16-19 mm off. Thresholds of 1 cm/s stop 1-2 cm short.
    Stopping:
      max_frames          frame budget, 360 (6 s simulated); a drape that hits it reports converged=False.
      min_frames          never stop before this frame, 10 (gravity needs a few frames to act on a warm start).
      speed_percentile    the percentile of per-vertex speed (frame displacement / frame time) tested, 99. A few
                          vertices chatter in contact (raised arms), so the maximum never settles.
      speed_threshold     [m/s]: converged when the percentile speed stays below it (5 mm/s) ...
      converged_frames    ... for this many consecutive frames, 3.

    Body contact (a static newton mesh shape; VBD particle-vs-shape penalty contact):
      contact_stiffness   normal stiffness [N/m] of body contact (model.soft_contact_ke = shape ke), 1e4.
      contact_damping     normal damping [N s/m] (model.soft_contact_kd = shape kd), 0.01.
      particle_radius     contact thickness [m] of each cloth vertex: contact pushes vertices to this distance
                          off the body surface, 2 mm.
      body_margin         extra thickness [m] of the body shape (ShapeConfig.margin), added to particle_radius, 0.
      contact_gap         detection-only slack [m] beyond radius + margin (CollisionPipeline soft_contact_gap), 5 mm.
      collide_every       run body collision detection every this many substeps (1 = every substep). Contacts
                          are planes at detection time, so detection can lag motion by a substep or two.
      full_surface_contact  also collide cloth edges/triangle interiors with the body (newton's
                          enable_rigid_soft_full_surface_contact), catching body features that poke between
                          vertices of large triangles; slower.

    Self-contact (off by default: it costs 2-2.5x; newton's own default margin of 0.2 m made the cloth explode):
      self_contact        enable VBD cloth self-contact.
      self_contact_margin interaction distance [m] of vertex-triangle and edge-edge pairs, 3 mm.
      self_contact_gap    extra detection distance [m], 2 mm.

    Device:
      device              warp device, "cpu" (bit-deterministic) or "cuda" / "cuda:0".
    """

    stretch_stiffness: float = 30.0
    poisson_ratio: float = 0.3
    bending_stiffness: float = 1.0e-5
    area_density: float = 0.1
    friction: float = 0.3
    membrane_damping: float = 0.0
    bending_damping: float = 0.0
    gravity: float = -9.81

    fps: float = 60.0
    substeps: int = 16
    iterations: int = 2
    velocity_retention: float = 0.9

    max_frames: int = 360
    min_frames: int = 10
    speed_percentile: float = 99.0
    speed_threshold: float = 0.005
    converged_frames: int = 3

    contact_stiffness: float = 1.0e4
    contact_damping: float = 1.0e-2
    particle_radius: float = 2.0e-3
    body_margin: float = 0.0
    contact_gap: float = 5.0e-3
    collide_every: int = 1
    full_surface_contact: bool = False

    self_contact: bool = False
    self_contact_margin: float = 3.0e-3
    self_contact_gap: float = 2.0e-3

    device: str = "cpu"
    graph: bool = True

    @property
    def lame(self) -> tuple[float, float]:
        """(mu, lambda) [N/m] of the membrane: `membrane_lame(stretch_stiffness, poisson_ratio)`."""
        return membrane_lame(self.stretch_stiffness, self.poisson_ratio)


@dataclass
class DrapeResult:
    """A drape (V, 3) float64 and its diagnostics (all scalars, so a build can store them beside the drape)."""

    vertices: np.ndarray
    converged: bool  # the speed test passed before max_frames
    frames: int  # frames simulated
    seconds: float  # wall time of the whole call (model build + simulation + checks)
    sim_seconds: float  # wall time of the frame loop alone
    max_speed: float  # [m/s] largest vertex speed over the last frame
    percentile_speed: float  # [m/s] the settings' percentile of vertex speed over the last frame
    residual: float  # [m] mean vertex displacement over the last frame
    inside_count: int  # garment vertices inside the body (signed clearance < 0)
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


def push_out_of_body(points, body_vertices, body_faces, clearance: float):
    """Move the points (V, 3) that lie inside the closed body surface to `clearance` outside its surface along the closest face's normal. Returns (points (V, 3) float64, moved count).

    A skinned warm start can put a few garment vertices inside the body (a swinging arm against the torso): newton
    only detects particle-shape contacts within radius + gap of the surface, so a vertex deeper than that is never
    pushed out. Lifting them out before simulating costs one closest-point query.
    """
    import trimesh

    points = np.array(points, dtype=np.float64, copy=True)
    mesh = trimesh.Trimesh(body_vertices, body_faces, process=False)
    closest, distance, face_ids = trimesh.proximity.closest_point(mesh, points)
    normals = mesh.face_normals[face_ids]
    inside = ((points - closest) * normals).sum(axis=1) < 0.0
    points[inside] = closest[inside] + clearance * normals[inside]
    return points, int(np.count_nonzero(inside))


def _check_mesh(name: str, vertices, faces=None) -> tuple[np.ndarray, np.ndarray | None]:
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


def drape(garment_vertices, garment_faces, body_vertices, body_faces, settings: DrapeSettings | None = None,
          rest_vertices=None, pinned=None) -> DrapeResult:
    """Drape a garment on a static body to quasi-static equilibrium; see the module docstring.

    garment_vertices (V, 3) the warm start (the garment skinned to the pose), garment_faces (F, 3),
    body_vertices (N, 3) and body_faces (G, 3) the posed body's closed surface (outward normals),
    rest_vertices (V, 3) the cloth's undeformed shape (default: the warm start), pinned (P,) indices of garment
    vertices held at their warm-start positions (a waistband: friction alone cannot hold trousers on the hips).
    Raises RuntimeError if the simulation produces non-finite positions.
    """
    settings = DrapeSettings() if settings is None else settings
    s = settings
    start = time.perf_counter()
    warm, faces = _check_mesh("garment", garment_vertices, garment_faces)
    rest = warm if rest_vertices is None else _check_mesh("rest", rest_vertices)[0]
    if rest.shape != warm.shape:
        raise ValueError(f"rest_vertices {rest.shape} must match garment_vertices {warm.shape}")
    body, body_tris = _check_mesh("body", body_vertices, body_faces)
    if s.substeps < 1 or s.iterations < 1 or s.collide_every < 1 or s.max_frames < 1:
        raise ValueError("substeps, iterations, collide_every and max_frames must be >= 1")
    pinned = np.unique(np.asarray([] if pinned is None else pinned, dtype=np.int64))
    if len(pinned) and (pinned[0] < 0 or pinned[-1] >= len(warm)):
        raise ValueError(f"pinned vertex indices must lie in 0..{len(warm) - 1}")
    wp, newton = require_newton()
    start_vertices, pushed_out = push_out_of_body(warm, body, body_tris, s.particle_radius + s.body_margin)

    mu, lam = s.lame
    device = wp.get_device(s.device)
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
        mesh = newton.Mesh(body.astype(np.float32), body_tris.ravel(), compute_inertia=False)
        builder.add_shape_mesh(-1, mesh=mesh, cfg=body_cfg)
        builder.color(include_bending=True)
        model = builder.finalize(device=device)
        # Particle-shape contacts average ke/kd arithmetically and mu geometrically between the model's soft
        # contact values and the shape's: set both to the same numbers.
        model.soft_contact_ke = s.contact_stiffness
        model.soft_contact_kd = s.contact_damping
        model.soft_contact_mu = s.friction
        if len(pinned):  # kinematic vertices: the solver leaves inactive particles where they are
            flags = model.particle_flags.numpy()
            flags[pinned] &= ~np.asarray(newton.ParticleFlags.ACTIVE, dtype=flags.dtype)
            model.particle_flags = wp.array(flags, dtype=model.particle_flags.dtype, device=device)

        pipeline = newton.CollisionPipeline(
            model, soft_contact_gap=s.contact_gap,
            enable_rigid_soft_full_surface_contact=s.full_surface_contact,
        )
        contacts = pipeline.contacts()
        solver = newton.solvers.SolverVBD(
            model, iterations=s.iterations,
            particle_enable_self_contact=s.self_contact,
            particle_self_contact_margin=s.self_contact_margin,
            particle_self_contact_gap=s.self_contact_gap,
        )
        state_0, state_1, control = model.state(), model.state(), model.control()
        warm32 = start_vertices.astype(np.float32)
        for state in (state_0, state_1):
            state.particle_q.assign(warm32)
            state.particle_qd.zero_()

        frame_dt = 1.0 / s.fps
        dt = frame_dt / s.substeps
        previous = warm32.astype(np.float64)
        calm = 0
        history = []
        converged = False
        sim_start = time.perf_counter()
        states = [state_0, state_1]

        def simulate_frame():
            # One frame of substeps. An even number of substeps leaves the state pair in place, so a captured graph
            # (fixed buffers) can be replayed; with an odd number the roles swap every frame.
            for substep in range(s.substeps):
                a, b = states[substep % 2], states[(substep + 1) % 2]
                if substep % s.collide_every == 0:
                    pipeline.collide(a, contacts)
                solver.step(a, b, control, contacts, dt)

        graph = None
        for frame in range(1, s.max_frames + 1):
            if graph is not None:
                wp.capture_launch(graph)
            else:
                simulate_frame()
                if s.substeps % 2:
                    states.reverse()
                elif s.graph and device.is_cpu and frame == 1:
                    # After one eager frame every lazily built buffer and kernel exists: record the frame once
                    # (recording does not execute it) and replay it from then on, without Python launch overhead.
                    try:
                        with wp.ScopedCapture(device=device) as capture:
                            simulate_frame()
                        graph = capture.graph
                    except Exception:  # noqa: BLE001 - capture is an optimisation only
                        graph = None
            state_0 = states[0]
            if s.velocity_retention != 1.0:
                state_0.particle_qd.assign(state_0.particle_qd.numpy() * np.float32(s.velocity_retention))
            current = state_0.particle_q.numpy().astype(np.float64)
            if not np.isfinite(current).all():
                raise RuntimeError(f"drape diverged at frame {frame} (non-finite positions); settings: {s}")
            moved = np.linalg.norm(current - previous, axis=1)
            previous = current
            speed = moved / frame_dt
            percentile_speed = float(np.percentile(speed, s.speed_percentile))
            history.append(percentile_speed)
            calm = calm + 1 if percentile_speed < s.speed_threshold else 0
            if frame >= s.min_frames and calm >= s.converged_frames:
                converged = True
                break
        sim_seconds = time.perf_counter() - sim_start

    from ..garment.binding import signed_clearance

    clearance = signed_clearance(current, body, body_tris)
    stretch = triangle_stretch(current, rest, faces)
    warm_stretch = triangle_stretch(warm, rest, faces)
    displacement = np.linalg.norm(current - warm, axis=1)
    return DrapeResult(
        vertices=current,
        converged=converged,
        frames=frame,
        seconds=time.perf_counter() - start,
        sim_seconds=sim_seconds,
        max_speed=float(speed.max()),
        percentile_speed=percentile_speed,
        residual=float(moved.mean()),
        inside_count=int(np.count_nonzero(clearance < 0.0)),
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
