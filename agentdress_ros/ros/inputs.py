"""Input checking for the node, as pure functions and small state holders (no rclpy: tested directly).

Every rejection has a short machine-readable reason (the key of the status topic's `rejected` counts) and a
human message naming what was wrong. Reasons:

| reason | what arrived |
|---|---|
| `empty` | a JointState with no names / a shape message with no values |
| `length_mismatch` | JointState names and positions of different lengths; a shape of the wrong length |
| `non_finite` | a NaN or Inf position / shape value (the joint or phenotype is named) |
| `out_of_range` | a joint value beyond +-MAX_ABS_JOINT (finite, but it would overflow float32 downstream) |
| `out_of_order` | a header stamp older than the last accepted one |
| `no_known_joints` | a JointState whose names are all unknown (each unknown name is also reported once) |
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..body import PHENOTYPE_NAMES, check_shape
from ..motion.joint_names import JOINT_INDEX, JOINT_NAMES
from ..motion.skeleton import NUM_BONES

__all__ = ["MAX_ABS_JOINT", "InputRejected", "PoseInput", "ShapeUpdate", "check_shape_values"]

#: Largest accepted |position| (radians or metres). Rotation vectors wrap every 2 pi and agents stay within
#: kilometres of the origin; anything larger is a broken sender, and it would overflow float32 garment vertices.
MAX_ABS_JOINT = 1.0e4


class InputRejected(ValueError):
    """A message that was not applied: `reason` (status key) and the message (what was wrong)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def stamp_to_ns(sec: int, nanosec: int) -> int:
    return int(sec) * 1_000_000_000 + int(nanosec)


class PoseInput:
    """The latest pose assembled from (possibly partial) JointState messages.

    `values` (3B + 3,) float64 in JOINT_NAMES order (rotation vectors, then Hips translation); `version` counts
    accepted messages (the node's timer works only when it changed); `stamp_ns` is the header stamp of the last
    accepted message (0: unstamped). A zero stamp is accepted without an ordering check (senders that do not stamp).
    """

    def __init__(self):
        self.values = np.zeros(len(JOINT_NAMES))
        self.version = 0
        self.stamp_ns = 0
        self.last_stamp_ns = 0  # newest stamp accepted so far (never goes back)
        self.unknown_names: set[str] = set()

    def accept(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int = 0) -> list[str]:
        """Apply one JointState. Returns the unknown names seen here for the first time (to report once).

        Raises InputRejected (nothing changes) for the reasons in the module docstring.
        """
        n_names, n_positions = len(names), len(positions)
        if n_names == 0 and n_positions == 0:
            raise InputRejected("empty", "JointState has no names and no positions")
        if n_names != n_positions:
            raise InputRejected("length_mismatch",
                                f"JointState has {n_names} names but {n_positions} positions; they must match")
        if stamp_ns and stamp_ns < self.last_stamp_ns:
            raise InputRejected("out_of_order", f"JointState stamp {stamp_ns * 1e-9:.6f} s is older than the last "
                                f"accepted {self.last_stamp_ns * 1e-9:.6f} s")
        values = np.asarray(positions, dtype=np.float64)
        finite = np.isfinite(values)
        if not finite.all():
            bad = [f"{names[i]}={values[i]}" for i in np.flatnonzero(~finite)[:5]]
            raise InputRejected("non_finite", f"JointState has non-finite positions: {', '.join(bad)}")
        large = np.abs(values) > MAX_ABS_JOINT
        if large.any():
            bad = [f"{names[i]}={values[i]:g}" for i in np.flatnonzero(large)[:5]]
            raise InputRejected("out_of_range", f"JointState positions beyond +-{MAX_ABS_JOINT:g}: {', '.join(bad)}")
        index = [JOINT_INDEX.get(name, -1) for name in names]
        known = [i for i, j in enumerate(index) if j >= 0]
        new_unknown = []
        if len(known) < n_names:
            for i, j in enumerate(index):
                if j < 0 and names[i] not in self.unknown_names:
                    self.unknown_names.add(names[i])
                    new_unknown.append(names[i])
        if not known:
            raise InputRejected("no_known_joints", f"JointState names no known joint (got {list(names)[:5]}...; "
                                f"expected <Bone>_rx/_ry/_rz and Hips_tx/_ty/_tz)")
        self.values[[index[i] for i in known]] = values[known]
        self.version += 1
        self.stamp_ns = stamp_ns
        if stamp_ns:
            self.last_stamp_ns = stamp_ns
        return new_unknown

    @property
    def rotvecs(self) -> np.ndarray:
        """(B, 3) rotation vectors (a copy)."""
        return self.values[: 3 * NUM_BONES].reshape(NUM_BONES, 3).copy()

    @property
    def root_translation(self) -> np.ndarray:
        """(3,) Hips translation (a copy)."""
        return self.values[3 * NUM_BONES:].copy()


@dataclass(frozen=True)
class ShapeUpdate:
    beta: np.ndarray  # (6,) float64 in [0, 1]
    clamped: bool  # some value lay outside [0, 1] and was clamped (warn, naming them)
    message: str  # what was clamped ("" when nothing)


def check_shape_values(values) -> ShapeUpdate:
    """A body-shape message's data -> checked beta (6,); out-of-range values clamped (reported), non-finite or
    wrong-length rejected with InputRejected naming the phenotype."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if values.size == 0:
        raise InputRejected("empty", "body shape message has no values")
    if values.size != len(PHENOTYPE_NAMES):
        raise InputRejected("length_mismatch", f"body shape needs {len(PHENOTYPE_NAMES)} values "
                            f"({', '.join(PHENOTYPE_NAMES)}), got {values.size}")
    try:
        checked = check_shape(values, clamp=True)
    except ValueError as error:  # non-finite: check_shape names the phenotype
        raise InputRejected("non_finite", str(error)) from None
    message = ""
    if checked.clamped:
        outside = [f"{n}={v:g}" for n, v in zip(PHENOTYPE_NAMES, values) if not 0.0 <= v <= 1.0]
        message = f"body shape values outside [0, 1] clamped: {', '.join(outside)}"
    return ShapeUpdate(checked.beta, checked.clamped, message)


def is_finite_frame(vertices: np.ndarray) -> bool:
    """True when every coordinate is finite (the output guard; ~10 us for 12k vertices)."""
    return bool(np.isfinite(vertices).all())
