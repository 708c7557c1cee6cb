"""EngineConfig: every knob of the runtime engine that trades speed for accuracy, in one place."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

TAYLOR_MODES = ("augmented", "plain", "zeroth")
DTYPES = ("float32", "float64")


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
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if int(self.neighbors) < 1:
            raise ValueError(f"neighbors must be >= 1, got {self.neighbors}")
        if int(self.pose_neighbors) < 1:
            raise ValueError(f"pose_neighbors must be >= 1, got {self.pose_neighbors}")
        if not 0.0 <= float(self.damping) < 1.0:
            raise ValueError(f"damping (eta) must lie in [0, 1), got {self.damping}")
        if self.components is not None and int(self.components) < 1:
            raise ValueError(f"components must be >= 1 or None, got {self.components}")


# ---- knobs set by text (the node's `engine` parameter, its per-garment entries, a crowd's tier lines) ----------
@dataclass(frozen=True)
class Knob:
    """How one EngineConfig field is read from text: its type, the least value of a number, whether "none"/"all"
    mean None (every one), the names a text knob takes, and whether it acts per frame (a fork of a loaded engine,
    a crowd tier, may change it without touching the shared data)."""

    kind: type
    per_frame: bool = False
    least: float | None = None
    all_word: bool = False
    choices: object = None  # () -> names, for a text knob

    def read(self, name: str, text: str):
        """`text` -> the knob's value; ValueError naming the knob and what is wrong."""
        text = str(text).strip()
        if self.kind is bool:
            if text.lower() not in ("true", "false"):
                raise ValueError(f"{name} must be true or false, got {text!r}")
            return text.lower() == "true"
        if self.kind is str:
            names = self.choices()
            if text not in names:
                raise ValueError(f"{name} must be one of {', '.join(sorted(names))}, got {text!r}")
            return text
        if self.all_word and text.lower() in ("none", "all"):
            return None
        try:
            value = self.kind(text)
        except ValueError:
            raise ValueError(f"{name}: {text!r} is not {'an integer' if self.kind is int else 'a number'}") from None
        if self.kind is float and not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {text!r}")
        if self.least is not None and value < self.least:
            raise ValueError(f"{name} must be >= {self.least:g}, got {value}")
        return value


def _pose_model_names():
    from .pose_models import POSE_MODELS  # the registry imports this module

    return tuple(POSE_MODELS)


#: The EngineConfig fields that text may set (the rest are library-only: anchor lists, vertex subsets, ...).
ENGINE_KNOBS: dict[str, Knob] = {
    "pose_model": Knob(str, per_frame=True, choices=_pose_model_names),
    "taylor": Knob(str, choices=lambda: TAYLOR_MODES),
    "dtype": Knob(str, choices=lambda: DTYPES),
    "neighbors": Knob(int, per_frame=True, least=1),
    "pose_neighbors": Knob(int, least=1),
    "components": Knob(int, least=1, all_word=True),
    "anchors": Knob(int, least=1, all_word=True),
    "projection": Knob(int, per_frame=True, least=0),
    "shape_model": Knob(bool),
    "penetration": Knob(bool, per_frame=True),
    "decay": Knob(bool, per_frame=True),
    "clamp_to_training_range": Knob(bool),
    "fold": Knob(bool),
    "damping": Knob(float, per_frame=True),
    "penetration_margin": Knob(float),
    "power": Knob(float, per_frame=True),
}
#: The knobs a fork of a loaded engine may change (Engine.fork): they act per frame.
PER_FRAME_KNOBS = tuple(name for name, knob in ENGINE_KNOBS.items() if knob.per_frame)


@dataclass(frozen=True)
class EngineKnobs:
    """Engine knobs set by name, the others left at EngineConfig's defaults (or a parent engine's): `values` is
    ((field, value), ...) sorted by field, so equal settings compare and hash equal (a shared garment's key)."""

    values: tuple = ()

    @classmethod
    def of(cls, **values) -> "EngineKnobs":
        bad = sorted(set(values) - set(ENGINE_KNOBS))
        if bad:
            raise ValueError(f"unknown engine knob {', '.join(bad)}; one of {', '.join(ENGINE_KNOBS)}")
        return cls(tuple(sorted(values.items())))

    @classmethod
    def parse(cls, words, per_frame: bool = False, prefix: str = "") -> "EngineKnobs":
        """["neighbors=2", "penetration=false", ...] -> EngineKnobs; ValueError naming the word and what is wrong
        (a knob named `prefix` + field). `per_frame`: only the knobs a fork may change (a crowd tier)."""
        allowed = PER_FRAME_KNOBS if per_frame else tuple(ENGINE_KNOBS)
        values = {}
        for word in words:
            key, sep, text = (part.strip() for part in str(word).partition("="))
            if not sep or not key or not text:
                raise ValueError(f"{word!r} must look like field=value")
            if key not in allowed:
                raise ValueError(f"unknown field {prefix + key!r}; one of {', '.join(sorted(allowed))}")
            if key in values:
                raise ValueError(f"{prefix}{key} appears twice")
            values[key] = ENGINE_KNOBS[key].read(prefix + key, text)
        return cls(tuple(sorted(values.items())))

    def __bool__(self) -> bool:
        return bool(self.values)

    def as_dict(self) -> dict:
        return dict(self.values)

    def get(self, name: str, default=None):
        return self.as_dict().get(name, default)

    def without(self, *names) -> "EngineKnobs":
        return EngineKnobs(tuple((k, v) for k, v in self.values if k not in names))

    def over(self, base: "EngineKnobs") -> "EngineKnobs":
        """These knobs set on top of `base`'s."""
        return EngineKnobs(tuple(sorted({**base.as_dict(), **self.as_dict()}.items())))

    def config(self, base: "EngineConfig | None" = None) -> "EngineConfig":
        """An EngineConfig with these knobs (on `base`, default EngineConfig()); ValueError from its checks."""
        return replace(base or EngineConfig(), **self.as_dict())

    def words(self) -> list[str]:
        """Back to "field=value" words (parse(words()) == self)."""
        return [f"{k}={'all' if v is None else str(v).lower() if isinstance(v, bool) else v}" for k, v in self.values]
