"""Levels of detail by distance to the viewer, with hysteresis, and field-of-view culling (pure functions and small
state: no ROS; the engine only to check a tier's pose model name).

A tier is one line of text, so a list of them is a plain ROS string-array parameter:

    "near 3 synthesis"                                   full synthesis under 3 m
    "mid 8 synthesis neighbors=2 penetration=false projection=0 pose_model=examples"
                                                         fewer anchors blended, no penetration handling or body
                                                         projection, the cheaper pose model, under 8 m
    "far 20 skinned"                                     the garment fitted to the body and skinned, under 20 m
    "distant inf skinned every=6"                        beyond: dressed every sixth tick (15 Hz at 90 Hz)
    "far 20 skinned display=none"                        drawn without the display stages (DISPLAY_MODES)

`<name> <max distance in m | inf> <synthesis | skinned> [key=value ...]`: keys are the engine's per-frame knobs
(engine.config.PER_FRAME_KNOBS, read by EngineKnobs.parse like the node's `engine` parameter: neighbors,
penetration, projection (0 only: off), decay, damping, power, pose_model (where neither the agent's nor the tier's
folds anchor residuals; kept otherwise)) for synthesis tiers, and `every=n` and `display=full|none` for any tier.
Tiers are ordered by distance; the last one must reach `inf`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..engine.config import PER_FRAME_KNOBS, EngineKnobs

__all__ = ["DEFAULT_TIERS", "LodPolicy", "Tier", "Viewer", "parse_tier", "parse_tiers", "quaternion_forward"]

TIER_KINDS = ("synthesis", "skinned")
#: What a tier draws: "full" the single agent's display stages (layering, refinement, edges off the drawn body;
#: display.models), "none" each garment's own frames on its own (coarse) topology, for a fraction of the cost.
DISPLAY_MODES = ("full", "none")


@dataclass(frozen=True)
class Tier:
    name: str
    max_distance: float  # metres; the tier holds agents closer than this (inf for the last)
    kind: str = "synthesis"  # "synthesis" (the engine) | "skinned" (the fitted garment, skinned)
    engine: EngineKnobs = EngineKnobs()  # engine fork overrides of a synthesis tier
    every: int = 1  # dress on every n-th tick only (a lower pose rate for far agents)
    display: str = "full"  # "full": the single agent's display stages; "none": the garment's own frames

    def text(self) -> str:
        extra = self.engine.words()
        extra += [f"every={self.every}"] if self.every != 1 else []
        extra += [f"display={self.display}"] if self.display != "full" else []
        return " ".join([self.name, "inf" if math.isinf(self.max_distance) else f"{self.max_distance:g}",
                         self.kind] + extra)


DEFAULT_TIER_TEXT = ("near 3 synthesis",
                     "mid 8 synthesis neighbors=2 penetration=false projection=0 pose_model=examples display=none",
                     "far 20 skinned display=none", "distant inf skinned every=6 display=none")


def parse_tier(text: str) -> Tier:
    """One tier line (module docstring) -> Tier; ValueError naming the line and what is wrong."""
    words = str(text).split()
    try:
        if len(words) < 3:
            raise ValueError("needs '<name> <max distance> <synthesis|skinned> [key=value ...]'")
        name, distance, kind, extra = words[0], words[1], words[2], words[3:]
        try:
            max_distance = float(distance)
        except ValueError:
            raise ValueError(f"max distance {distance!r} is not a number (or inf)") from None
        if math.isnan(max_distance) or max_distance <= 0:
            raise ValueError(f"max distance must be > 0, got {distance}")
        if kind not in TIER_KINDS:
            raise ValueError(f"kind must be one of {', '.join(TIER_KINDS)}, got {kind!r}")
        knobs, every, display = [], 1, "full"
        for item in extra:
            key, sep, value = item.partition("=")
            if not sep or not value:
                raise ValueError(f"{item!r} must look like key=value")
            if key == "display":
                if value not in DISPLAY_MODES:
                    raise ValueError(f"display must be one of {', '.join(DISPLAY_MODES)}, got {value!r}")
                display = value
            elif key == "every":
                try:
                    every = int(value)
                except ValueError:
                    raise ValueError(f"every: {value!r} is not an integer") from None
                if every < 1:
                    raise ValueError(f"every must be >= 1, got {every}")
            elif key in PER_FRAME_KNOBS:
                if kind != "synthesis":
                    raise ValueError(f"{key} applies to synthesis tiers only")
                knobs.append(item)
            else:
                raise ValueError(f"unknown key {key!r}; one of every, display, {', '.join(PER_FRAME_KNOBS)}")
        return Tier(name, max_distance, kind, EngineKnobs.parse(knobs, per_frame=True), every, display)
    except ValueError as error:
        raise ValueError(f"tier {text!r}: {error}") from None


def parse_tiers(lines) -> tuple[Tier, ...]:
    """Tier lines -> tiers ordered by distance; ValueError for repeated names, unordered distances or a last tier
    that does not reach inf."""
    tiers = tuple(parse_tier(line) for line in lines if str(line).strip())
    if not tiers:
        raise ValueError("at least one tier is needed (e.g. 'all inf synthesis')")
    names = [t.name for t in tiers]
    if len(set(names)) != len(names):
        raise ValueError(f"tier names repeat: {names}")
    distances = [t.max_distance for t in tiers]
    if any(b <= a for a, b in zip(distances, distances[1:])):
        raise ValueError(f"tier distances must increase: {distances}")
    if not math.isinf(distances[-1]):
        raise ValueError(f"the last tier must reach inf (got {distances[-1]:g} m): agents beyond it need a tier")
    return tiers


DEFAULT_TIERS = parse_tiers(DEFAULT_TIER_TEXT)


def quaternion_forward(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The +x axis (REP-103 body frame: forward) of orientation quaternion (x, y, z, w), unit length."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError("orientation quaternion must be finite and non-zero")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)])


@dataclass(frozen=True)
class Viewer:
    """The viewer (headset) in the agents' frame: position (3,) and unit forward direction (3,)."""

    position: np.ndarray
    forward: np.ndarray

    @classmethod
    def from_pose(cls, position, quaternion, offset=(0.0, 0.0, 0.0, 0.0)) -> "Viewer":
        """A pose in the viewer's frame, mapped into the agents' frame by a fixed offset (x, y, z, yaw): the viewer
        frame's origin and heading in the agents' frame."""
        ox, oy, oz, yaw = (float(v) for v in offset)
        c, s = math.cos(yaw), math.sin(yaw)
        rotate = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        p = rotate @ np.asarray(position, dtype=np.float64) + (ox, oy, oz)
        f = rotate @ quaternion_forward(*quaternion)
        if not np.isfinite(p).all():
            raise ValueError("viewer position must be finite")
        return cls(p, f)


@dataclass(frozen=True)
class LodPolicy:
    """Tiers with hysteresis (metres) and the viewing cone (full field of view and margin, degrees).

    `agent_radius` is the bounding sphere of an agent around its hips (1 m holds a person with raised arms)."""

    tiers: tuple = DEFAULT_TIERS
    hysteresis: float = 0.5
    fov_deg: float = 110.0
    margin_deg: float = 10.0
    agent_radius: float = 1.0
    cull: bool = True

    def tier(self, distance: float, current: int | None) -> int:
        """Tier index for `distance`, keeping `current` until the distance is `hysteresis` beyond the boundary (no
        flicker at a boundary; a large jump goes straight to the tier it lands in)."""
        return int(self.tiers_of(np.array([distance]), np.array([-1 if current is None else current]))[0])

    def tiers_of(self, distances: np.ndarray, current: np.ndarray) -> np.ndarray:
        """`tier` of every agent at once: distances (N,), current tiers (N,) int, -1 for none -> (N,) int."""
        bounds = np.array([t.max_distance for t in self.tiers])
        distances = np.asarray(distances, dtype=np.float64)
        current = np.asarray(current)
        raw = np.minimum(np.searchsorted(bounds, distances, side="right"), len(bounds) - 1)
        held = (current >= 0) & (current < len(bounds)) & (raw != current)
        h = self.hysteresis
        # moving out: must clear the boundary of the tier below by h; moving in: clear its own boundary by h
        moving_out = np.where(distances >= bounds[np.maximum(raw - 1, 0)] + h, raw, raw - 1)
        moving_in = np.where(distances <= bounds[raw] - h, raw, raw + 1)
        return np.where(held, np.where(raw > current, moving_out, moving_in), raw)

    def visible(self, viewer: Viewer | None, centre) -> bool:
        """Inside the viewing cone widened by the margin and by the agent's angular radius (always when close)."""
        return bool(self.visible_of(viewer, np.asarray(centre, dtype=np.float64)[None])[0])

    def visible_of(self, viewer: Viewer | None, centres: np.ndarray) -> np.ndarray:
        """`visible` of every agent at once: centres (N, 3) -> (N,) bool."""
        if viewer is None or not self.cull:
            return np.ones(len(centres), dtype=bool)
        d = centres - viewer.position
        distance = np.sqrt(np.einsum("ij,ij->i", d, d))
        safe = np.maximum(distance, 1e-12)
        angle = np.degrees(np.arccos(np.clip(d @ viewer.forward / safe, -1.0, 1.0)))
        widen = np.degrees(np.arcsin(np.minimum(1.0, self.agent_radius / safe)))
        return (distance <= self.agent_radius) | (angle <= 0.5 * self.fov_deg + self.margin_deg + widen)
