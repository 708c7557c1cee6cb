"""Input checking for the node, as pure functions and small state holders (no rclpy: tested directly).

Every rejection has a short machine-readable reason (the key of the status topic's `rejected` counts) and a
human message naming what was wrong. Reasons:

| reason | what arrived |
|---|---|
| `empty` | a JointState with no names / a shape message with no values |
| `length_mismatch` | JointState names and positions of different lengths; a shape of the wrong length |
| `non_finite` | a NaN or Inf position / shape value (the joint or phenotype is named) |
| `out_of_range` | a joint value beyond +-MAX_ABS_JOINT (finite, but it would overflow float32 downstream) |
| `out_of_order` | a header stamp older than the last accepted one by less than the jump threshold |

A stamp that jumps back or forward by more than the threshold (a looped bag, a simulator or /clock reset, a message
stamped in the future and then the present again) starts a new timeline: accepted, and reported by `accept`.
| `no_known_joints` | a JointState whose names are all unknown (each unknown name is also reported once) |
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..body import PHENOTYPE_NAMES, check_shape
# the pose input is the scene's (an agent's state); re-exported here with the node's other input checks
from ..scene.pose import MAX_ABS_JOINT, MAX_UNKNOWN_NAMES, InputRejected, PoseInput, stamp_to_ns  # noqa: F401

__all__ = ["MAX_ABS_JOINT", "MAX_UNKNOWN_NAMES", "InputRejected", "PoseInput", "ShapeUpdate", "check_shape_values"]


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
