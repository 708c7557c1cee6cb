"""Drape and sequence settings (every knob, in physical units) and the lazy newton import.

Importing this module needs neither newton nor warp, so build configurations can be read anywhere.
"""
from __future__ import annotations

from dataclasses import dataclass

NEWTON_VERSION = "1.8.0"
INSTALL_HINT = f"pip install newton=={NEWTON_VERSION} (the project's `build` extra)"
#: DrapeSettings overrides of a drape warm-started from a finished one (the builder's and the held-out set's)
WARM_DRAPE = {"velocity_retention": 0.75}


def require_newton():
    """Import and return (warp, newton), or raise ImportError naming the install command."""
    try:
        import warp as wp

        wp.config.quiet = True  # no banner on every worker process
        # Drapes never differentiate: without the adjoint code a cold kernel cache compiles in 47 s instead of 82 s
        # on one core, and the forward kernels (and so every drape) are the same.
        wp.config.enable_backward = False
        import newton
        import newton.solvers  # noqa: F401
    except ImportError as error:
        raise ImportError(f"agentdress_ros.sim needs NVIDIA newton to drape garments: {INSTALL_HINT}") from error
    _reuse_narrow_phase_kernel()
    return wp, newton


def _reuse_narrow_phase_kernel() -> None:
    """Every newton.CollisionPipeline builds its GJK/MPR narrow-phase kernel anew from the same arguments: warp's
    code generation in Python, 0.45 s of each drape's setup (a drape of 500 vertices and 20 frames costs 4-6 s). The
    kernel depends only on those arguments (the compiled module is keyed by its source), so one built kernel per
    argument set serves every pipeline of the process."""
    import functools

    from newton._src.geometry import narrow_phase

    factory = narrow_phase.create_narrow_phase_kernel_gjk_mpr
    if not hasattr(factory, "cache_info"):
        narrow_phase.create_narrow_phase_kernel_gjk_mpr = functools.cache(factory)


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
      graph               on the CPU, record the solver's substeps as warp graphs (APIC capture) after the first frame
                          and replay them, still or moving (needs an even substep count): bit-identical results,
                          without Python's launch overhead.
                          Not used on CUDA (untested there: no GPU was available when this was tuned).

      Tuning (2k-vertex T-shirt, reference body, rest pose, against an 8 x 10 run of 300 frames stopped at a 99th
      percentile speed of 2 mm/s): VBD needs *small steps*, not many iterations. Few substeps leave each step
      unconverged and the cloth creeps like a viscous sheet, stretching without end (4 x 5: strain max 77 % and
      growing at 240 frames; 1 x 20: 190 %; both never converged). 16 x 2 at 5 mm/s stopped at 151 frames, 2.8 mm
      mean from the reference; 8 x 4 was 6.4 mm off, 8 x 3 10 mm, 4 x 20 (4x the cost) 9.6 mm, 16 x 1 and 32 x 1
      stopped early (5 mm/s is reached while still creeping) 16-19 mm off. Thresholds of 1 cm/s stop 1-2 cm short.
    Animated collider:
      ramp_frames         frames over which a drape job carries the body (and the cloth) from the rest pose into
                          the target pose before settling (`drape(body_path=...)`); 0, the default, keeps the
                          static collider the shipped databases were built with. Drapes from the skinned garment
                          only: a warm start from a finished drape starts in the pose.
      warm_ramp_frames    for a drape warm-started from another drape (another shape in the same pose, the previous
                          frame of a sequence): frames over which the body moves from the source drape's shape and
                          pose into this drape's, the cloth starting as the source drape itself. 0, the default,
                          transfers the source's offset onto this drape's skinned garment instead and lifts out the
                          vertices that land inside the body (the static collider).
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

    ramp_frames: int = 0
    warm_ramp_frames: int = 0
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
