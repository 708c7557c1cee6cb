"""EngineConfig: every knob of the runtime engine that trades speed for accuracy, in one place."""
from __future__ import annotations

from dataclasses import dataclass

TAYLOR_MODES = ("augmented", "plain", "zeroth")


@dataclass(frozen=True)
class EngineConfig:
    """Runtime knobs. Defaults are the paper's method (Eq. 4, 7-10) at full accuracy in float32.

    pose_model: registered pose model name ("lbs", "examples", "sequence"; see engine.pose_models).
    neighbors: K anchors kept per region (paper: 5) for the shape models. Fewer is faster per vertex, blends less.
    pose_neighbors: K examples blended per region by the examples pose model (its own knob: the anchors' K does
        not change it); capped at the number of examples.
    components: PCA components of the shape models used (paper: 5; None = all the database holds, which may be
        more so that the trade can be measured). Only costs at a shape change.
    anchors: subset of anchors: None = all, an int n = n evenly spaced anchors, or a sequence of anchor indices.
        Fewer anchors: smaller memory and faster shape changes, coarser pose coverage. A subset also restricts the
        pose model's examples to those anchors' beta0 drapes (the extra examples of the database are dropped).
    vertices: garment level of detail, optional: None = all, or a sequence of vertex indices; the engine then
        outputs only those vertices (in that order) and `Engine.faces` keeps the triangles whose corners all survive.
    shape_model: False = the pose model alone, f(beta0, theta) skinned onto the current skeleton: no anchor blend,
        no shape correction, no penetration handling (the cheapest output; the evaluation's "pose model alone").
    penetration: Eq. 10 re-projection along the bound body vertex normal (eps_p = penetration_margin).
    projection: after Eq. 10, each garment vertex closer than penetration_margin to the nearest of its candidate
        body vertices, skinned exactly, moves out along the posed surface's normal there (that of the candidate's
        largest incident face); 0 = off. Its candidates: its `projection` nearest body vertices at rest, and its
        `projection_examples` nearest at each pose-model example pose (what a pose brings near: the arm at the
        torso's side), thinned to no two within `projection_spacing` (metres) at rest, the first kept (0 = every
        distinct one): 8 per example pose 2.5 cm apart leave less cloth inside than 1 per example pose for about the
        same number of checks. Eq. 10 keeps the anchors' own clearances, so cloth the anchors had inside the body
        stays inside; this catches it (README "Speed vs accuracy": truly-inside vertices from 3-4 % to 0.14-0.33 %,
        for ~0.1 ms per frame at 8).
    decay: Eq. 9 damping of the region distances over frames, ratio `damping` (eta). The paper picks eta per garment
        from a residual curve it does not print; 0.5 is our default (a ~1.4-frame time constant at the frame rate).
    dtype: "float32" (default) or "float64" for the per-frame buffers; pose and weight arithmetic is always float64.
    taylor: "augmented" = Eq. 4 (shape deltas re-posed by LBS); "plain" = Eq. 2 blended (deltas added unrotated);
        "zeroth" = the ablation of Sec. 4.6: sum_s w^s LBS^beta_{theta_s -> theta}(f(beta, theta_s)), no pose model,
        no first-order term.
    power: k of W = 1 / (D + eps)^k (paper: 3). eps_relative: eps of each region as a fraction of sum_m Q_{g,m}
        (the distance of a 1 rad difference in every dof), so it is scale free.
    clamp_to_training_range: clamp beta to the database's training range (the shape models extrapolate badly);
        False clamps to Anny's [0, 1] only. Either way ShapeReport.clamped says whether anything was clamped.
    fold: for a pose model that is not exact at the anchors (the learned `regressor`), add each anchor's residual
        f(beta0, theta_s) - pose_model(theta_s) to its shape delta, so synthesis stays exact at the anchors (Eq. 4
        with the taylor="augmented" form only; no cost per frame).
    max_root_translation: |root translation| components are clamped to this (metres) so float32 output stays finite.
    shape_residual: add the database's learned shape residual (shape_model/residual, `agentdress lab shape-residual`)
        to the blended shape delta every frame: what synthesis missed at other body shapes along the training
        clips, from pose and phenotypes (taylor="augmented" with the shape model only; a small MLP per frame).
    """

    pose_model: str = "lbs"
    neighbors: int = 5
    pose_neighbors: int = 5
    components: int | None = 5
    anchors: object = None
    vertices: object = None
    shape_model: bool = True
    penetration: bool = True
    penetration_margin: float = 0.005
    projection: int = 0
    projection_examples: int = 8
    projection_spacing: float = 0.025
    decay: bool = True
    damping: float = 0.5
    dtype: str = "float32"
    taylor: str = "augmented"
    power: float = 3.0
    eps_relative: float = 1e-6
    clamp_to_training_range: bool = True
    max_root_translation: float = 1.0e4
    fold: bool = True
    shape_residual: bool = False

    def __post_init__(self):
        if self.taylor not in TAYLOR_MODES:
            raise ValueError(f"taylor must be one of {TAYLOR_MODES}, got {self.taylor!r}")
        if self.shape_residual and (not self.shape_model or self.taylor != "augmented"):
            raise ValueError("shape_residual corrects the shape delta of Eq. 4: it needs shape_model=True and "
                             "taylor='augmented'")
        if not self.shape_model and self.taylor == "zeroth":
            raise ValueError("taylor='zeroth' is a blend of anchors: it needs shape_model=True")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if int(self.neighbors) < 1:
            raise ValueError(f"neighbors must be >= 1, got {self.neighbors}")
        if int(self.pose_neighbors) < 1:
            raise ValueError(f"pose_neighbors must be >= 1, got {self.pose_neighbors}")
        if not 0.0 <= float(self.damping) < 1.0:
            raise ValueError(f"damping (eta) must lie in [0, 1), got {self.damping}")
        if self.components is not None and int(self.components) < 1:
            raise ValueError(f"components must be >= 1 or None, got {self.components}")
