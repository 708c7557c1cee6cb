"""Garments of a crowd: data loaded once per scene, a small state per agent.

`GarmentLibrary` loads each garment database (and builds its engine: pose-model examples, anchor features) or
skinned template once, keyed by what defines it, thread-safe. `AgentGarment` is one agent's garment: engine forks
per synthesis tier over the shared data (own frame buffers and decay history, one shape state that every tier
follows), the fitted garment skinned for skinned tiers (same vertices and topology), and a cross-fade over a few
frames when the level changes, so a tier change does not pop.
"""
from __future__ import annotations

import copy
import threading
from dataclasses import dataclass

import numpy as np

from ..body import REFERENCE_SHAPE
from ..engine.config import EngineKnobs
from ..motion.skeleton import NUM_BONES

__all__ = ["AgentGarment", "GarmentLibrary", "GarmentSpec"]


@dataclass(frozen=True)
class GarmentSpec:
    """What to run for one garment of an agent: template name, vertex budget of a skinned template (None: the
    template's default), database path (None: the skinned template), the engine knobs and model ("agentdress" or
    "santesteban", ros.params.GARMENT_MODELS) of a database garment, and for the body the garments covering it (its
    displayed faces change with them)."""

    name: str
    vertices: int | None = None
    database: str | None = None
    engine: EngineKnobs = EngineKnobs()
    model: str = "agentdress"
    covered_by: tuple = ()


class GarmentLibrary:
    """Shared, read-only garment data of a scene on one body. `get(spec)` returns the loaded model for a spec (an
    EngineGarmentModel or SkinnedGarmentModel from models.garment_models' makers), loading it on first use."""

    def __init__(self, body, make_model=None, make_body=None):
        self.body = body
        if make_model is None or make_body is None:  # the node's garment models (no rclpy in that module)
            from ..models import garment_models

            make_model = make_model or garment_models.make_garment_model
            make_body = make_body or garment_models.make_body_model
        self._make, self._make_body = make_model, make_body
        self._models: dict = {}
        self._shaped: dict = {}  # (spec, beta) -> a snapshot of a garment fitted to beta (shape state shareable)
        self._lock = threading.Lock()

    def get(self, spec: GarmentSpec):
        """The shared model of `spec` ("body": the visible body surface); raises what the makers raise."""
        with self._lock:
            model = self._models.get(spec)
            if model is None:
                if spec.name == "body":
                    model = self._make_body(self.body)
                else:
                    engine_config = spec.engine.config() if spec.database and spec.engine else None
                    model = self._make(spec.name, spec.database, spec.vertices, self.body, REFERENCE_SHAPE,
                                       engine_config, spec.model)
                self._models[spec] = model
            return model

    def covered_body(self, garments: tuple):
        """The shared body model without the faces that `garments` (GarmentSpecs) cover, the band kept under their
        edges sunk: the single agent's masking (display.models.dress_for_display), made once per set of garments.
        Raises what the makers raise."""
        key = ("body", garments)
        with self._lock:
            model = self._models.get(key)
        if model is None:
            from ..display.models import dress_for_display

            models = {g.name: self.get(g) for g in garments}
            equal_layers = {name: 0 for name in models}  # the garments are not layered here: only the body is made
            model = dress_for_display({**models, "body": self.get(GarmentSpec("body"))}, self.body,
                                      equal_layers, edge_clearance=False)["body"]
            with self._lock:
                model = self._models.setdefault(key, model)
        return model

    def fitted(self, spec: GarmentSpec, beta, garment: "AgentGarment") -> bool:
        """Fit `garment` (an AgentGarment of `spec`) to beta, sharing the shape state of an earlier agent fitted to
        the same beta (shape states are never changed in place: a later set_shape of either builds a new one).
        Returns whether beta was clamped."""
        key = (spec, tuple(float(b) for b in beta))
        with self._lock:
            source = self._shaped.get(key)
        if source is not None and garment.follow(source):
            return source.clamped
        clamped = garment.set_shape(beta)
        with self._lock:
            self._shaped[key] = garment.snapshot()
            while len(self._shaped) > 64:
                self._shaped.pop(next(iter(self._shaped)))
        return clamped

    def models(self) -> list:
        with self._lock:
            return list(self._models.values())

    def __len__(self) -> int:
        return len(self._models)


class AgentGarment:
    """One agent's garment over a shared model, with one level per tier (lod.Tier).

    dress(level, rotvecs, root) -> (V, 3) float32 (an internal buffer, valid until the next call), or None while
    `bones_only` is set on a skinned template (its model then holds only the frame's bone transforms).
    set_shape(beta) -> clamped (off the frame path; swaps state by reference).
    """

    def __init__(self, shared, tiers, fade_frames: int = 6):
        self.shared, self.name, self.kind = shared, shared.name, shared.kind
        self.coarse_faces, self.coarse_vertices = shared.faces, shared.n_vertices
        self.display = None  # display.models.DisplayModel over this garment's levels (set_display), or None
        self._drawn = [tier.display == "full" for tier in tiers]  # per level: through `display` (when set)
        self.next_level = 0  # the level `synthesize` dresses (the display model calls it)
        self.fade_frames = int(fade_frames)
        self.clamped = False
        engine = getattr(shared, "engine", None)
        self._levels = []  # per tier: ("synthesis", engine) | ("skinned", engine) | ("model", model)
        if engine is not None:
            self.base = engine.fork()
            forks = {}
            for tier in tiers:
                if tier.kind == "skinned":
                    self._levels.append(("skinned", self.base))
                else:
                    key = tier.engine
                    if not self.base.can_fork_pose_model(key.get("pose_model", self.base.config.pose_model)):
                        key = key.without("pose_model")  # a fold: the agent's model stays
                    if key not in forks:
                        forks[key] = self.base.fork(**key.as_dict()) if key else self.base
                    self._levels.append(("synthesis", forks[key]))
            self._engines = list(forks.values()) + ([self.base] if EngineKnobs() not in forks else [])
        else:  # a skinned template: every tier is the same model
            self.base = shared.clone()
            self._engines = []
            self._levels = [("model", self.base)] * len(tiers)
        self._out = np.zeros((self.coarse_vertices, 3), dtype=np.float32)
        self._old = np.zeros_like(self._out)
        self.bones_only = False  # set by the owner while nobody takes this template's vertices, only its bones
        self.level: int | None = None
        self._fade_from: int | None = None
        self._fade_left = 0

    @property
    def fading(self) -> bool:
        return self._fade_left > 0

    def set_display(self, display) -> None:
        """Dress the levels whose tier draws the display (`display=full`) through `display` (a
        display.models.DisplayModel whose base is this garment: the single agent's layering, refinement and edge
        stages on each frame of this garment's level), or none (None). Swapped by reference: a refit's new bindings
        go live at once."""
        self.display = display

    def display_at(self, level: int):
        """The display model that level `level` is drawn through, or None (the level's own frames)."""
        return self.display if self.display is not None and self._drawn[level] else None

    def faces_at(self, level: int) -> np.ndarray:
        """(F, 3) faces of the frames drawn at `level`."""
        display = self.display_at(level)
        return display.faces if display is not None else self.coarse_faces

    def topology_at(self, level: int) -> str:
        """Which topology `level` draws: "display" (the display model's) or "coarse" (the garment's own)."""
        return "display" if self.display_at(level) is not None else "coarse"

    @property
    def shape_limits(self):
        """{"clamped": [...], "held": [...]}: the phenotypes a database garment cannot follow (clamped) or only
        held at its training range; None for a skinned template, which follows every shape in [0, 1]."""
        if self._engines:
            report = getattr(self.base, "shape_report", None)
            return None if report is None else {"clamped": list(report.clamped_names),
                                                "held": list(report.held_names)}
        return getattr(self.base, "shape_limits", None)

    @property
    def faces(self) -> np.ndarray:
        """Faces of the frame dressed last (of the first level before any)."""
        return self.faces_at(self.level or 0)

    @property
    def n_vertices(self) -> int:
        display = self.display_at(self.level or 0)
        return display.n_vertices if display is not None else self.coarse_vertices

    def fitted_model(self):
        """A model under the garment protocol fitted to this garment's current shape, with frame buffers of its own
        (what the display bindings are made from, off the frame path): the shared model with this garment's engine
        cloned, or its skinned model cloned."""
        if not self._engines:
            return self.base.clone()
        twin = copy.copy(self.shared)
        twin.engine = self.base.clone()
        return twin

    def skin_binding(self):
        """(rest, indices, weights) that reproduce this garment's frames by LBS (a display client skins them from
        bones), or None: an engine's frames, or a display that changes the LBS frame (refinement, layering)."""
        from ..models.garment_models import skin_binding

        return skin_binding(self.base) if self.display is None and not self._engines else None

    def synthesize(self, rotvecs, root) -> np.ndarray | None:
        """The garment protocol for the display model: this garment at level `next_level`."""
        return self._dress_level(self.next_level, rotvecs, root)

    def set_shape(self, beta) -> bool:
        if self._engines:
            self.clamped = bool(self.base.set_shape(beta).clamped)
            self._follow_base()
        else:
            self.clamped = bool(self.base.set_shape(beta))
        return self.clamped

    def _follow_base(self):
        for engine in self._engines:
            if engine is not self.base:
                engine.follow_shape(self.base)

    def snapshot(self) -> "AgentGarment":
        """A shallow copy holding the current shape state (a later set_shape of this garment does not change it)."""
        twin = copy.copy(self)
        twin.base = copy.copy(self.base)
        return twin

    def follow(self, source: "AgentGarment") -> bool:
        """Take the shape state of `source` (another agent's garment on the same data, already fitted). Returns
        False where it cannot (a skinned template: refit instead)."""
        if not self._engines or not source._engines:
            return False
        self.base.follow_shape(source.base)
        self._follow_base()
        self.clamped = source.clamped
        return True

    def _run(self, level: int, rotvecs, root) -> np.ndarray:
        kind, target = self._levels[level]
        if kind == "synthesis":
            return target.synthesize(rotvecs, root)
        if kind == "skinned":
            return target.skin(rotvecs, root)
        return target.synthesize(rotvecs, root)

    def same_output(self, a: int, b: int) -> bool:
        """Levels a and b compute the same thing (no fade needed between them)."""
        return self._levels[a] == self._levels[b]

    def dress(self, level: int, rotvecs, root) -> np.ndarray | None:
        """The frame drawn at `level`: the level's garment (faded across a level change), through the display
        stages when there are any."""
        display = self.display_at(level)
        if display is None:
            return self._dress_level(level, rotvecs, root)
        self.next_level = level
        return display.synthesize(rotvecs, root)

    def _dress_level(self, level: int, rotvecs, root) -> np.ndarray | None:
        if self.bones_only and not self._engines:  # every tier is the same LBS model: nothing to fade
            self.level = level
            self.base.pose_bones(rotvecs, root)
            return None
        if self.level is not None and level != self.level and not self.same_output(level, self.level) \
                and self.fade_frames > 0:
            self._fade_from, self._fade_left = self.level, self.fade_frames
            kind, target = self._levels[level]
            if kind == "synthesis":
                target.reset()  # its decay history is from the last time it ran
        self.level = level
        new = self._run(level, rotvecs, root)
        if self._fade_left > 0:
            np.copyto(self._old, new)
            old = self._run(self._fade_from, rotvecs, root)
            a = (self.fade_frames - self._fade_left + 1.0) / self.fade_frames  # 1/F, 2/F, ..., 1
            np.multiply(old, 1.0 - a, out=self._out, casting="unsafe")
            self._out += a * self._old
            self._fade_left -= 1
        else:
            np.copyto(self._out, new, casting="unsafe")
        return self._out

    def rest_frame(self, level: int = 0) -> np.ndarray:
        """(V, 3) float32 copy of the garment at the rest pose on the current shape (for the topology message);
        leaves no decay history behind. Call before the agent goes live (it uses the frame buffers)."""
        zeros, root = np.zeros((NUM_BONES, 3)), np.zeros(3)
        if self.display_at(level) is not None:  # the drawn topology, as the single agent's topology message
            dressed = self.level
            frame = np.array(self.dress(level, zeros, root), dtype=np.float32)
            self.level = dressed  # not a level change: no cross-fade from it
        else:
            frame = self.base.skin(zeros, root) if self._engines else self.base.synthesize(zeros, root)
            frame = np.array(frame, dtype=np.float32)
        self.reset()
        return frame

    def reset(self) -> None:
        """Forget decay history (the agent's motion was interrupted: back into view, a cut)."""
        for engine in self._engines:
            engine.reset()
        self._fade_left = 0
        if self.display is not None:
            self.display.forget_motion()
