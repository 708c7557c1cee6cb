"""The garment models the node runs, behind one small protocol (no rclpy here: testable and reusable without ROS).

A `GarmentModel` turns a body shape and a pose into garment vertices:

    model.name          str, the topic name under the node (`~/<name>/points`)
    model.faces         (F, 3) int32 topology (vertex order = the synthesized vertices')
    model.n_vertices    V
    model.kind          "skinned" | "database" (for the status topic)
    model.shape_limits  optional, for the status topic: {"clamped": [phenotype, ...] the garment was clamped on,
                        "held": [...] only its shape models were held on (their training range; the garment's
                        fit follows the body)} after the last set_shape
    model.set_shape(beta (6,)) -> clamped: bool      rare: refits the model to a body shape (ValueError if
                                                     non-finite / wrong length, naming the phenotype)
    model.synthesize(rotvecs (B, 3), root_translation (3,)) -> (V, 3) float32
                                                     per frame; the array may be an internal buffer that the next
                                                     call overwrites (callers copy what they keep)
    model.reset()                                    forget frame-to-frame history (the engine's decay)
    model.clone() -> GarmentModel                    a model sharing the read-only data (topology, database,
                                                     skin weights) with its own frame buffers and a copy of the
                                                     history, whose set_shape and synthesize do not touch `model`:
                                                     the node refits a clone off the frame path and swaps it in

`SkinnedGarmentModel` is linear blend skinning of a garment template (used when no database is configured),
`BodyModel` the visible body surface under the same protocol (the node's optional body stream), and
`EngineGarmentModel` adapts the AgentDress engine (`agentdress_ros.engine`, imported lazily).
"""
from __future__ import annotations

import copy
import threading
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody, BodyShape
from ..body.kinematics import linear_blend_skinning

__all__ = [
    "BodyModel",
    "EngineGarmentModel",
    "GarmentDatabaseError",
    "GarmentModel",
    "SkinnedGarmentModel",
    "make_body_model",
    "make_garment_model",
]


class GarmentDatabaseError(RuntimeError):
    """A configured garment database cannot be used; the message names the garment and the file."""


@runtime_checkable
class GarmentModel(Protocol):
    name: str
    faces: np.ndarray
    kind: str

    @property
    def n_vertices(self) -> int: ...

    def set_shape(self, beta) -> bool: ...

    def synthesize(self, rotvecs, root_translation) -> np.ndarray: ...

    def reset(self) -> None: ...

    def clone(self) -> "GarmentModel": ...


class _ShapeCache:
    """The body's rest shape for the last few betas, shared by all skinned models of one body: a shape change of
    body + T-shirt + trousers evaluates the ~10 ms blendshape sum once, not three times. Thread-safe (the node
    refits on a worker thread)."""

    def __init__(self, body: AnnyBody, size: int = 2):
        self.body, self.size = body, size
        self._entries: list[tuple[bytes, BodyShape]] = []
        self._lock = threading.Lock()

    def get(self, beta) -> BodyShape:
        key = np.asarray(beta, dtype=np.float64).reshape(-1).tobytes()
        with self._lock:
            for k, shape in self._entries:
                if k == key:
                    return shape
        shape = self.body.shape(beta)  # ValueError (naming the phenotype) for a wrong length / non-finite value
        with self._lock:
            self._entries = [(key, shape)] + self._entries[: self.size - 1]
        return shape


_CACHES: dict[int, _ShapeCache] = {}


def _shape_cache(body: AnnyBody) -> _ShapeCache:
    cache = _CACHES.get(id(body))
    if cache is None or cache.body is not body:
        cache = _CACHES[id(body)] = _ShapeCache(body)
    return cache


class _SkinnedBase:
    """LBS of rest vertices (V, 3) bound to the body's bones; subclasses say how the rest follows the shape."""

    kind = "skinned"

    def __init__(self, name: str, body: AnnyBody, faces, skin_indices, skin_weights, beta=REFERENCE_SHAPE):
        self.name = name
        self.body = body
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self._skin_indices = np.ascontiguousarray(skin_indices, dtype=np.int64)
        self._skin_weights = np.ascontiguousarray(skin_weights, dtype=np.float32)
        self._cache = _shape_cache(body)
        self.transforms = None
        self.set_shape(beta)

    @property
    def n_vertices(self) -> int:
        return len(self._skin_indices)

    def _rest_for(self, shape: BodyShape) -> np.ndarray:
        raise NotImplementedError

    def set_shape(self, beta) -> bool:
        """Refit to beta (6,); returns True when values were clamped into [0, 1]. ValueError if non-finite."""
        shape = self._cache.get(beta)
        rest = np.ascontiguousarray(self._rest_for(shape), dtype=np.float32)
        # Swap references only after everything is computed: a failed refit leaves the model as it was.
        self.shape, self.rest, self._out = shape, rest, np.empty_like(rest)
        return bool(shape.clamped)

    def synthesize(self, rotvecs, root_translation) -> np.ndarray:
        """rotvecs (B, 3), root_translation (3,) -> posed vertices (V, 3) float32 (an internal buffer)."""
        transforms, _ = self.body.pose(self.shape, rotvecs, root_translation)
        self.transforms = transforms  # (B, 3, 4) of this frame: a display client may skin the rest itself
        return linear_blend_skinning(self.rest, self._skin_indices, self._skin_weights,
                                     transforms.astype(np.float32), self._out)

    def pose_bones(self, rotvecs, root_translation) -> None:
        """Only the frame's bone transforms (B, 3, 4) into `transforms`, for a client that skins the rest itself:
        no vertices (the body's 13,380 are most of an agent's frame cost in a crowd)."""
        self.transforms, _ = self.body.pose(self.shape, rotvecs, root_translation)

    def skin_binding(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rest (V, 3) float32 on the current shape, bone indices (V, K), weights (V, K)): with `transforms` of a
        frame, what reproduces that frame exactly (messages.make_skin)."""
        return self.rest, self._skin_indices, self._skin_weights

    def reset(self) -> None:
        """LBS keeps no history."""

    def clone(self):
        twin = copy.copy(self)  # shares faces, skin weights, the garment template; set_shape rebinds the rest
        twin._out = np.empty_like(self._out)
        return twin


def skin_binding(model):
    """A plain LBS model's skin_binding() (rest, indices, weights), else None (a database's engine, a display model)."""
    return model.skin_binding() if isinstance(model, _SkinnedBase) else None


class SkinnedGarmentModel(_SkinnedBase):
    """A garment template (agentdress_ros.garment.Garment) fitted to the shape at rest and posed by LBS."""

    def __init__(self, garment, body: AnnyBody, beta=REFERENCE_SHAPE):
        self.garment = garment
        super().__init__(garment.name, body, garment.faces, garment.skin_indices, garment.skin_weights, beta)

    def _rest_for(self, shape: BodyShape) -> np.ndarray:
        return self.garment.rest_vertices(self.body, shape)


class BodyModel(_SkinnedBase):
    """The visible body surface (helper meshes dropped), named "body", under the garment protocol."""

    def __init__(self, body: AnnyBody, beta=REFERENCE_SHAPE):
        self.body_ids = body.body_vertex_ids
        remap = np.full(len(body.assets.template), -1, dtype=np.int64)
        remap[self.body_ids] = np.arange(len(self.body_ids))
        super().__init__("body", body, remap[body.body_faces], body.skin_indices[self.body_ids],
                         body.skin_weights[self.body_ids], beta)

    def _rest_for(self, shape: BodyShape) -> np.ndarray:
        return shape.vertices[self.body_ids]


class EngineGarmentModel:
    """The AgentDress engine (`agentdress_ros.engine.Engine`) behind the protocol. `clone()` is Engine.clone: the
    copy has its own frame buffers and starts from the live engine's decay history, so neither its refit nor the
    rest-pose drapes the display stages bind to (made on the worker thread while the live model runs) reach the
    live model's frames."""

    kind = "database"

    def __init__(self, name: str, engine, faces, path: Path, n_vertices: int):
        self.name, self.engine, self.path = name, engine, path
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self._n_vertices = int(n_vertices)

    @property
    def n_vertices(self) -> int:
        return self._n_vertices

    def set_shape(self, beta) -> bool:
        """True when the engine clamped beta for the garment (outside [0, 1], or the training range of a database
        without a surface binding); `shape_limits` names those phenotypes and the ones only the shape models held
        at their training range."""
        report = self.engine.set_shape(beta)
        self.shape_limits = {"clamped": list(report.clamped_names), "held": list(report.held_names)}
        return bool(report.clamped)

    def synthesize(self, rotvecs, root_translation) -> np.ndarray:
        return np.asarray(self.engine.synthesize(rotvecs, root_translation), dtype=np.float32)

    def reset(self) -> None:
        self.engine.reset()

    def clone(self):
        twin = copy.copy(self)
        clone = getattr(self.engine, "clone", None)
        twin.engine = clone() if callable(clone) else copy.copy(self.engine)
        return twin


def _load_engine_model(name: str, path: Path, body: AnnyBody, beta, engine_config=None) -> EngineGarmentModel:
    """Import the engine lazily (the skinned path never needs it) and build a model from the database file."""
    try:
        from ..engine import Engine, EngineConfig
    except (ImportError, AttributeError) as error:
        raise GarmentDatabaseError(
            f"garment {name!r}: cannot use database {path}: agentdress_ros.engine is not usable ({error}); "
            "set skinned_fallback: true to dress it with the skinned template instead"
        ) from None
    db = _read_database(name, path)
    try:
        engine = Engine(db, body, engine_config if engine_config is not None else EngineConfig())
    except Exception as error:
        raise GarmentDatabaseError(f"garment {name!r}: the engine cannot load database {path}: {error}") from None
    model = EngineGarmentModel(name, engine, engine.faces, path, engine.n_vertices)
    model.set_shape(beta)
    return model


def _read_database(name: str, path: Path):
    """The database at `path`, a failure raised as GarmentDatabaseError naming the garment and the file."""
    from ..engine import read_database

    try:
        return read_database(path)  # DatabaseError names the file and the field
    except Exception as error:
        text = str(error)
        raise GarmentDatabaseError(f"garment {name!r}: {text}" if str(path) in text
                                   else f"garment {name!r}: database {path}: {text}") from None


def _load_santesteban_model(name: str, path: Path, body: AnnyBody, beta):
    """Santesteban et al.'s system from the database file (engine.santesteban.SantestebanModel, which is a garment
    model under the protocol itself)."""
    from ..engine.santesteban import SantestebanModel

    db = _read_database(name, path)
    if db.santesteban is None:
        raise GarmentDatabaseError(f"garment {name!r}: database {path} has no garment_model/santesteban group "
                                   "(model santesteban): train it with `agentdress lab santesteban`")
    model = SantestebanModel(db, body, name=name, path=path)
    model.set_shape(beta)
    return model


def make_garment_model(name: str, database_path=None, vertices: int | None = None, body: AnnyBody | None = None,
                       beta=REFERENCE_SHAPE, engine_config=None, model: str = "agentdress") -> GarmentModel:
    """The model for garment `name`: the AgentDress engine on `database_path` if given (or with model
    "santesteban", Santesteban et al.'s system from the same file), else the skinned template
    with about `vertices` vertices (None: the template's default). A database fixes its own vertex count; its level
    of detail is the engine's (`EngineConfig.vertices`, passed as `engine_config`), so `vertices` applies to
    skinned templates only.

    Raises GarmentDatabaseError naming the file when the database is missing or cannot be used (never falls back
    silently: the caller decides), ValueError for an unknown garment name or a bad vertex count.
    """
    body = body if body is not None else AnnyBody()
    if database_path not in (None, ""):
        path = Path(database_path).expanduser()
        if not path.is_file():
            raise GarmentDatabaseError(f"garment {name!r}: database file {path.resolve()} does not exist")
        if model == "santesteban":
            return _load_santesteban_model(name, path, body, beta)
        return _load_engine_model(name, path, body, beta, engine_config)
    from ..garment import TEMPLATES, make_garment

    if name not in TEMPLATES:
        raise ValueError(f"unknown garment {name!r}; templates: {', '.join(TEMPLATES)} (or configure a database)")
    if vertices is not None and int(vertices) < 100:
        raise ValueError(f"garment {name!r}: vertex budget {vertices} is too small (at least 100)")
    garment = make_garment(name, body, None if vertices is None else int(vertices))
    return SkinnedGarmentModel(garment, body, beta)


def make_body_model(body: AnnyBody, beta=REFERENCE_SHAPE) -> BodyModel:
    return BodyModel(body, beta)
