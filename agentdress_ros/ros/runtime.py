"""The node's working state without ROS: which models run, refits off the frame path, guarded outputs, statistics.

Threads: the ROS executor thread calls `take_ready`, `synthesize` and the input methods; one worker thread
(`ModelWorker`) builds model sets for a new body shape or garment list. A built set is handed over by reference
under a lock and swapped in by the next tick, so a tick never waits for a refit (a T-shirt + trousers shape change
is ~30 ms, a new garment template ~1-2 s).
"""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field, replace

import numpy as np

from ..body import REFERENCE_SHAPE
from .garment_models import GarmentDatabaseError, make_body_model, make_garment_model

__all__ = ["GarmentSpec", "ModelSet", "ModelWorker", "OutputGuard", "TickStats", "build_model_set"]


@dataclass(frozen=True)
class GarmentSpec:
    """What to run for one garment: template name, vertex budget (None: template default), database (None: none),
    engine knobs."""

    name: str
    vertices: int | None = None
    database: str | None = None
    engine: tuple = ()  # EngineConfig overrides ((field, value), ...) for a garment with a database


@dataclass(frozen=True)
class SceneSpec:
    """Everything the scene requires: garments (in publishing order), the body stream, the shape."""

    garments: tuple[GarmentSpec, ...]
    publish_body: bool
    beta: tuple[float, ...]
    skinned_fallback: bool = False


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
    topology: dict = field(default_factory=dict)  # name -> topology message, filled by the worker's `prepare`


def _build_garment(spec: GarmentSpec, body, beta, skinned_fallback: bool, warnings: list):
    if spec.database and spec.vertices is not None:
        warnings.append(f"garment {spec.name!r}: the vertex budget {spec.vertices} applies to skinned templates; "
                        f"the database {spec.database} fixes its own vertex count")
    try:
        engine_config = None
        if spec.database and spec.engine:
            from ..engine.config import EngineConfig

            engine_config = EngineConfig(**dict(spec.engine))
        return make_garment_model(spec.name, spec.database, spec.vertices, body, beta, engine_config)
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
    wanted = list(scene.garments) + ([GarmentSpec("body")] if scene.publish_body else [])
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
    generation = previous.generation + 1 if previous is not None else 0
    return ModelSet(scene, models, specs, clamped, warnings, generation)


class ModelWorker:
    """Builds the latest requested SceneSpec on a background thread; `take_ready()` hands over the newest result.

    Requests coalesce: a flood of shape messages builds only the newest shape. `on_error(message)` is called from
    the worker thread when a build fails (the live set stays as it was); `on_built(set, seconds)` after a build.
    """

    def __init__(self, body, current: ModelSet, on_error=None, on_built=None, prepare=None):
        self.body = body
        self._current = current  # the newest built set (live or about to be)
        self._wanted: SceneSpec | None = None
        self._ready: ModelSet | None = None
        self._cond = threading.Condition()
        self._stop = False
        self._busy = False
        self.on_error = on_error or (lambda message: None)
        self.on_built = on_built or (lambda model_set, seconds: None)
        # prepare(new_set, previous_set) runs on the worker before the set is handed over (e.g. topology messages).
        self.prepare = prepare or (lambda model_set, previous: None)
        self._thread = threading.Thread(target=self._run, name="agentdress-model-worker", daemon=True)
        self._thread.start()

    @property
    def wanted(self) -> SceneSpec:
        with self._cond:
            return self._wanted if self._wanted is not None else self._current.scene

    def request(self, **changes) -> SceneSpec:
        """Ask for the current (or pending) scene with `changes` (SceneSpec fields). Returns the requested spec."""
        with self._cond:
            base = self._wanted if self._wanted is not None else self._current.scene
            scene = replace(base, **changes)
            self._wanted = scene
            self._cond.notify()
            return scene

    def take_ready(self) -> ModelSet | None:
        with self._cond:
            ready, self._ready = self._ready, None
            return ready

    def idle(self) -> bool:
        with self._cond:
            return self._wanted is None and not self._busy and self._ready is None

    def _run(self):
        while True:
            with self._cond:
                while not self._stop and (self._wanted is None or self._wanted == self._current.scene):
                    self._wanted = None
                    self._cond.wait()
                if self._stop:
                    return
                scene, previous = self._wanted, self._current
                self._wanted, self._busy = None, True
            start = time.perf_counter()
            try:
                built = build_model_set(scene, self.body, previous)
                self.prepare(built, previous)
            except Exception as error:  # a bad request never kills the node: report, keep the live set
                with self._cond:
                    self._busy = False
                self.on_error(f"cannot rebuild garment models: {error}")
                continue
            with self._cond:
                self._current = self._ready = built
                self._busy = False
            self.on_built(built, time.perf_counter() - start)

    def stop(self):
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=5.0)


class OutputGuard:
    """Keeps the last good frame per model; a non-finite or failed synthesis falls back to it (never emitted)."""

    def __init__(self):
        self.last_good: dict[str, np.ndarray] = {}

    def reset(self, name: str):
        self.last_good.pop(name, None)

    def check(self, name: str, vertices) -> tuple[np.ndarray | None, str]:
        """vertices (V, 3) or None (synthesis raised) -> (frame to publish or None, problem "" | reason)."""
        if vertices is not None and np.isfinite(vertices).all():
            good = self.last_good.get(name)
            if good is None or good.shape != vertices.shape:
                good = self.last_good[name] = np.empty(vertices.shape, dtype=np.float32)
            np.copyto(good, vertices)
            return good, ""
        return self.last_good.get(name), "synthesis_error" if vertices is None else "non_finite_output"


class TickStats:
    """Rolling timing statistics for the status topic (the last `window` ticks) and counters since start."""

    def __init__(self, window: int = 1000):
        self.tick_times = deque(maxlen=window)  # monotonic seconds of every timer tick
        self.synthesis_ms = deque(maxlen=window)  # per computing tick, all models together
        self.tick_ms = deque(maxlen=window)  # per computing tick, whole callback (synthesis + pack + publish)
        self.counts = Counter()  # published_frames, keepalive_frames, computed_ticks, idle_ticks, late_ticks, ...
        self.rejected = Counter()  # reason -> messages

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


def percentiles(values, digits: int = 4) -> dict:
    """p50, p99, max and count of a sequence of timings (None when empty), rounded for JSON."""
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    array = np.fromiter(values, dtype=np.float64)
    p50, p99 = np.percentile(array, [50, 99])
    return {"p50": round(float(p50), digits), "p99": round(float(p99), digits),
            "max": round(float(array.max()), digits), "n": int(array.size)}


def default_scene(garments=("tshirt",), publish_body=False, beta=REFERENCE_SHAPE) -> SceneSpec:
    return SceneSpec(tuple(GarmentSpec(g) for g in garments), publish_body, tuple(float(b) for b in beta))
