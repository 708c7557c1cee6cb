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
from ..display.models import dress_for_display
from ..scene.garments import GarmentSpec
from ..models.garment_models import GarmentDatabaseError, make_body_model, make_garment_model

__all__ = ["GarmentSpec", "ModelSet", "ModelWorker", "OutputGuard", "TickStats", "build_model_set", "inherit_topology",
           "scene_key"]


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
    topology: dict = field(default_factory=dict)  # name -> topology message, filled by the worker's `prepare`


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


class ModelWorker:
    """Builds the latest requested SceneSpec on a background thread; `take_ready()` hands over the newest result.

    Requests coalesce: a flood of shape messages builds only the newest shape. `prepare(set, previous)` runs on the
    worker before a set is handed over (e.g. topology messages for the models that are new in it). A failed build
    leaves the live set as it was and is kept for `take_failure()` (the node reports it and rolls its parameters
    back); `on_built(set, seconds)` / `on_error(message)` are called on the worker thread. Nothing raised in a build
    or a callback ends the thread: callback errors are kept for `take_errors()`, and `ensure_running()` restarts a
    thread that died all the same.
    """

    def __init__(self, body, current: ModelSet, on_error=None, on_built=None, prepare=None):
        self.body = body
        self._current = current  # the newest built set (live or about to be)
        self._wanted: SceneSpec | None = None
        self._building: SceneSpec | None = None  # the scene the thread is building now
        self._ready: ModelSet | None = None
        self._failure: tuple[SceneSpec, str] | None = None
        self._errors: deque[str] = deque(maxlen=16)
        self._cond = threading.Condition()
        self._stop = False
        self._busy = False
        self.restarts = 0
        self.on_error = on_error or (lambda message: None)
        self.on_built = on_built or (lambda model_set, seconds: None)
        self.prepare = prepare or (lambda model_set, previous: None)
        self._start_thread()

    def _start_thread(self):
        self._thread = threading.Thread(target=self._run, name="agentdress-model-worker", daemon=True)
        self._thread.start()

    def _latest(self) -> SceneSpec:
        """The newest scene asked for: pending, else being built, else built. A shape change that arrives while a
        new garment list builds must keep that list, not the one the running set has."""
        for scene in (self._wanted, self._building):
            if scene is not None:
                return scene
        return self._current.scene

    @property
    def wanted(self) -> SceneSpec:
        with self._cond:
            return self._latest()

    def request(self, **changes) -> SceneSpec:
        """Ask for the newest scene with `changes` (SceneSpec fields). Returns the requested spec."""
        with self._cond:
            scene = replace(self._latest(), **changes)
            self._wanted = scene
            self._cond.notify()
            return scene

    def take_ready(self) -> ModelSet | None:
        with self._cond:
            ready, self._ready = self._ready, None
            return ready

    def take_failure(self) -> tuple[SceneSpec, str] | None:
        """(scene, message) of the newest build that failed since the last call, or None."""
        with self._cond:
            failure, self._failure = self._failure, None
            return failure

    def take_errors(self) -> list[str]:
        """Messages of the callbacks that raised on the worker thread since the last call."""
        with self._cond:
            errors = list(self._errors)
            self._errors.clear()
            return errors

    def idle(self) -> bool:
        with self._cond:
            return self._wanted is None and not self._busy and self._ready is None

    def ensure_running(self) -> bool:
        """Restart the thread if it died (True when it had to)."""
        with self._cond:
            if self._stop or self._thread.is_alive():
                return False
            self._busy, self._building = False, None
            self.restarts += 1
            self._start_thread()
            return True

    def _callback(self, name: str, callback, *args):
        try:
            callback(*args)
        except Exception as error:  # a failing observer must not stop the builds
            with self._cond:
                self._errors.append(f"model worker: {name} callback failed: {error!r}")

    def _run(self):
        while True:
            with self._cond:
                while not self._stop and (self._wanted is None or self._wanted == self._current.scene):
                    self._wanted = None
                    self._cond.wait()
                if self._stop:
                    return
                scene, previous = self._wanted, self._current
                self._wanted, self._busy, self._building = None, True, scene
            start = time.perf_counter()
            try:
                built = build_model_set(scene, self.body, previous)
                self.prepare(built, previous)
            except Exception as error:  # a bad request never kills the node: report, keep the live set
                message = f"cannot rebuild garment models: {error}"
                with self._cond:
                    self._busy, self._building = False, None
                    self._failure = (scene, message)
                    if self._wanted is not None and scene_key(self._wanted) == scene_key(scene):
                        # a shape change asked for during the failed build: apply it to the models that run
                        self._wanted = replace(self._current.scene, beta=self._wanted.beta)
                self._callback("on_error", self.on_error, message)
                continue
            with self._cond:
                superseded = self._ready
                if superseded is not None:
                    inherit_topology(built, superseded)
                self._current = self._ready = built
                self._busy, self._building = False, None
            self._callback("on_built", self.on_built, built, time.perf_counter() - start)

    def stop(self):
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=5.0)


def scene_key(scene: SceneSpec) -> tuple:
    """What decides the models of a scene, all but the body shape (which only refits them)."""
    return scene.garments, scene.publish_body, scene.skinned_fallback


def inherit_topology(built: ModelSet, superseded: ModelSet) -> None:
    """`built` replaces `superseded` before anyone took it: keep the topology messages of superseded's new models
    that `built` reuses (same spec). Otherwise a new level of detail followed at once by a shape change would hand
    over clouds of the new size with no mesh for them."""
    for name, message in superseded.topology.items():
        if name not in built.topology and built.specs.get(name) == superseded.specs.get(name):
            built.topology[name] = message


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


def default_scene(garments=("tshirt",), publish_body=False, beta=REFERENCE_SHAPE) -> SceneSpec:
    return SceneSpec(tuple(GarmentSpec(g) for g in garments), publish_body, tuple(float(b) for b in beta))
