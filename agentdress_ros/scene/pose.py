"""An agent's pose input: the latest pose assembled from (possibly partial) joint-state messages, checked (no ROS).

The node's JointStates and the scene's own callers (benchmarks, tests: `set`) feed it; reasons of a rejection are
listed in agentdress_ros.ros.inputs.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..motion.joint_names import JOINT_INDEX, JOINT_NAMES
from ..motion.skeleton import NUM_BONES

__all__ = ["MAX_ABS_JOINT", "MAX_UNKNOWN_NAMES", "InputRejected", "PoseInput", "stamp_to_ns"]

#: Largest accepted |position| (radians or metres). Rotation vectors wrap every 2 pi and agents stay within
#: kilometres of the origin; anything larger is a broken sender, and it would overflow float32 garment vertices.
MAX_ABS_JOINT = 1.0e4

#: Unknown joint names remembered (each reported once); a sender inventing names cannot grow the node's memory.
#: Beyond this, unknown names are still returned (the node's throttled warning limits the log), never stored.
MAX_UNKNOWN_NAMES = 64
MAX_NAME_LENGTH = 80  # characters of an unknown name kept and shown


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
    A stamp more than `stamp_jump_ns` away from the last accepted one starts a new timeline: accepted, and
    `timeline_jump_ns` (signed: negative back) says so until the next accepted message (0 otherwise).
    """

    def __init__(self, stamp_jump_ns: int = 500_000_000):
        self.values = np.zeros(len(JOINT_NAMES))
        self.version = 0
        self.stamp_ns = 0
        self.last_stamp_ns = 0  # stamp of the last accepted stamped message: the timeline's newest
        self.stamp_jump_ns = int(stamp_jump_ns)
        self.timeline_jump_ns = 0
        self.unknown_names: set[str] = set()
        self._names: list = []  # the names of the last accepted message, and their (index, known, targets)
        self._index: tuple = ([], [], [])

    def accept(self, names: Sequence[str], positions: Sequence[float], stamp_ns: int = 0) -> list[str]:
        """Apply one JointState. Returns the unknown names not reported before (to report once; once
        MAX_UNKNOWN_NAMES are remembered, every new one is returned each time).

        Raises InputRejected (nothing changes) for the reasons in the module docstring.
        """
        self.timeline_jump_ns = 0
        n_names, n_positions = len(names), len(positions)
        if n_names == 0 and n_positions == 0:
            raise InputRejected("empty", "JointState has no names and no positions")
        if n_names != n_positions:
            raise InputRejected("length_mismatch",
                                f"JointState has {n_names} names but {n_positions} positions; they must match")
        step = stamp_ns - self.last_stamp_ns if stamp_ns and self.last_stamp_ns else 0
        jump = step if abs(step) > self.stamp_jump_ns else 0
        if step < 0 and not jump:
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
        reused = isinstance(names, list) and names == self._names
        if reused:  # a sender repeats its names: their mapping is reused (a third of the cost)
            index, known, targets = self._index
        else:
            index = [JOINT_INDEX.get(name, -1) for name in names]
            known = [i for i, j in enumerate(index) if j >= 0]
            targets = [index[i] for i in known]
        new_unknown = []
        if len(known) < n_names:
            for i, j in enumerate(index):
                name = str(names[i])[:MAX_NAME_LENGTH]
                if j < 0 and name not in self.unknown_names and name not in new_unknown:
                    new_unknown.append(name)
                    if len(self.unknown_names) < MAX_UNKNOWN_NAMES:
                        self.unknown_names.add(name)
        if not known:
            raise InputRejected("no_known_joints", f"JointState names no known joint (got {list(names)[:5]}...; "
                                f"expected <Bone>_rx/_ry/_rz and Hips_tx/_ty/_tz)")
        self.values[targets] = values[known]
        if not reused:
            self._names, self._index = list(names), (index, known, targets)
        self.version += 1
        self.stamp_ns = stamp_ns
        if stamp_ns:
            self.last_stamp_ns = stamp_ns
        self.timeline_jump_ns = jump
        return new_unknown

    @property
    def rotvecs(self) -> np.ndarray:
        """(B, 3) rotation vectors (a copy)."""
        return self.values[: 3 * NUM_BONES].reshape(NUM_BONES, 3).copy()

    @property
    def root_translation(self) -> np.ndarray:
        """(3,) Hips translation (a copy)."""
        return self.values[3 * NUM_BONES:].copy()

    def set(self, rotvecs, root_translation=(0.0, 0.0, 0.0), stamp_ns: int = 0) -> None:
        """A whole pose at once, unchecked (a caller that computed it: benchmarks, tests): rotvecs (B, 3), root
        translation (3,)."""
        self.values[: 3 * NUM_BONES] = np.asarray(rotvecs, dtype=np.float64).reshape(-1)
        self.values[3 * NUM_BONES:] = np.asarray(root_translation, dtype=np.float64)
        self.version += 1
        self.stamp_ns = int(stamp_ns)
