"""The node's statistics, and the single agent's garment models as one set (no ROS).

`build_model_set(SceneSpec)` makes the models one agent wears, dressed for display (display.models), from the
garment makers directly: the display check and the coverage tests measure them. The node runs the same code
through its scene (scene.Scene, whose near tier is bit for bit these models: test_scene.py).
"""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from ..display.models import dress_for_display
from ..scene.garments import GarmentSpec
from ..models.garment_models import GarmentDatabaseError, make_body_model, make_garment_model

__all__ = ["GarmentSpec", "ModelSet", "SceneSpec", "TickStats", "build_model_set"]


@dataclass(frozen=True)
class SceneSpec:
    """Everything the scene requires: garments (in publishing order), the body stream, the shape, and how it is
    dressed for display (agentdress_ros.display.models): Loop subdivision rounds, layer overrides ((garment, layer),
    ...; template layers otherwise), the body's covered faces left out."""

    garments: tuple[GarmentSpec, ...]
    publish_body: bool
    beta: tuple[float, ...]
    skinned_fallback: bool = False
    display_subdivision: int = 0
    layers: tuple = ()


@dataclass
class ModelSet:
    """Models built for one SceneSpec. `models` maps topic name -> GarmentModel ("body" included when asked);
    `specs` the GarmentSpec each was built from; `warnings` what happened while building (fallbacks)."""

    scene: SceneSpec
    models: dict
    specs: dict
    clamped: bool
    warnings: list = field(default_factory=list)
    generation: int = 0


def _build_garment(spec: GarmentSpec, body, beta, skinned_fallback: bool, warnings: list):
    if spec.database and spec.vertices is not None:
        warnings.append(f"garment {spec.name!r}: the vertex budget {spec.vertices} applies to skinned templates; "
                        f"the database {spec.database} fixes its own vertex count")
    try:
        engine_config = spec.engine.config() if spec.database and spec.engine else None
        return make_garment_model(spec.name, spec.database, spec.vertices, body, beta, engine_config, spec.model)
    except GarmentDatabaseError as error:
        if not skinned_fallback:
            raise
        warnings.append(f"{error}; using the skinned {spec.name} template instead (skinned_fallback)")
        return make_garment_model(spec.name, None, spec.vertices, body, beta)


def build_model_set(scene: SceneSpec, body, previous: ModelSet | None = None) -> ModelSet:
    """Models for `scene`, reusing `previous`' models where their spec is unchanged (cloned and refitted when only
    the shape changed, so the live models are never touched). Raises GarmentDatabaseError / ValueError."""
    beta = np.asarray(scene.beta, dtype=np.float64)
    models, specs, warnings, clamped = {}, {}, [], False
    same_shape = previous is not None and previous.scene.beta == scene.beta
    # the body's spec names the garments that cover it: its topology changes with them
    covering = GarmentSpec("body", covered_by=tuple(g.name for g in scene.garments))
    wanted = list(scene.garments) + ([covering] if scene.publish_body else [])
    for spec in wanted:
        old = previous.models.get(spec.name) if previous is not None else None
        if old is not None and previous.specs.get(spec.name) == spec:
            if same_shape:
                model = old
            else:
                model = old.clone()
                clamped |= model.set_shape(beta)
        elif spec.name == "body":
            model = make_body_model(body, beta)
        else:
            model = _build_garment(spec, body, beta, scene.skinned_fallback, warnings)
        models[spec.name], specs[spec.name] = model, spec
    if not models:
        clamped = bool(np.any((beta < 0) | (beta > 1)))
    models = dress_for_display(models, body, dict(scene.layers), scene.display_subdivision, beta)
    generation = previous.generation + 1 if previous is not None else 0
    return ModelSet(scene, models, specs, clamped, warnings, generation)


class TickStats:
    """Rolling timing statistics for the status topic (the last `window` ticks) and counters since start."""

    def __init__(self, window: int = 1000):
        self.tick_times = deque(maxlen=window)  # monotonic seconds of every timer tick
        self.synthesis_ms = deque(maxlen=window)  # per agent frame dressed, all its garments together
        self.tick_ms = deque(maxlen=window)  # per timer tick (input, dressing, publishing) and per pose answered
        # on arrival (dressing, publishing)
        self.counts = Counter()  # published_frames, keepalive_frames, computed_ticks, idle_ticks, late_ticks, ...
        self.rejected = Counter()  # reason -> messages
        self.errors = Counter()  # where -> exceptions caught there (the node went on)

    def tick(self, now: float, period: float):
        if self.tick_times and now - self.tick_times[-1] > 1.5 * period:
            self.counts["late_ticks"] += 1
        self.tick_times.append(now)

    def rate(self, now: float, span: float = 2.0) -> float:
        """Ticks per second over the last `span` seconds."""
        times = [t for t in self.tick_times if now - t <= span]
        if len(times) < 2:
            return 0.0
        return (len(times) - 1) / max(times[-1] - times[0], 1e-9)

    @staticmethod
    def percentiles(values) -> dict:
        return percentiles(values)


# one percentile summary for the node status, the crowd scene and the benchmarks
from ..scene.scene import percentiles  # noqa: E402,F401
