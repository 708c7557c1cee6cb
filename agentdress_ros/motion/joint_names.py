"""Mapping between a pose and ``sensor_msgs/JointState`` style (names, positions) lists.

Each rig bone has three scalar joints ``<Bone>_rx``, ``<Bone>_ry``, ``<Bone>_rz``: the components of its local
rotation vector (radians, relative to the rest orientation, in the parent frame; world axes at rest: Z up, body
facing -Y, left at +X). The root translation (metres, Hips displacement from rest, world) is
``Hips_tx``, ``Hips_ty``, ``Hips_tz``. No ROS imports: plain sequences in and out.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .skeleton import BONE_NAMES, NUM_BONES, Pose

__all__ = ["JOINT_INDEX", "JOINT_NAMES", "joint_positions_to_pose", "pose_to_joint_positions"]

JOINT_NAMES: tuple[str, ...] = tuple(f"{bone}_r{axis}" for bone in BONE_NAMES for axis in "xyz") + (
    "Hips_tx",
    "Hips_ty",
    "Hips_tz",
)
JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}
_NUM_ROTATION = 3 * NUM_BONES


def pose_to_joint_positions(rotvecs, root_translation) -> tuple[list[str], list[float]]:
    """rotvecs (B, 3), root_translation (3,) -> (names (3B+3,), positions (3B+3,)) in ``JOINT_NAMES`` order."""
    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    root_translation = np.asarray(root_translation, dtype=np.float64)
    if rotvecs.shape != (NUM_BONES, 3):
        raise ValueError(f"rotvecs must be ({NUM_BONES}, 3), got {rotvecs.shape}")
    if root_translation.shape != (3,):
        raise ValueError(f"root_translation must be (3,), got {root_translation.shape}")
    values = np.concatenate([rotvecs.reshape(-1), root_translation])
    return list(JOINT_NAMES), values.tolist()


def joint_positions_to_pose(
    names: Sequence[str], positions: Sequence[float], previous: Pose | None = None
) -> tuple[Pose, list[str]]:
    """Apply a (possibly partial) JointState to a pose.

    names (N,), positions (N,) -> (Pose, unknown names). Joints not named keep their value from ``previous``
    (or zero). Unknown names are skipped and returned so the caller can report them once.
    Raises ValueError on a length mismatch or a non-finite value (naming the joint); ``previous`` is never modified.
    """
    names = list(names)
    positions = list(positions)
    if len(names) != len(positions):
        raise ValueError(
            f"JointState has {len(names)} names but {len(positions)} positions; they must be the same length"
        )
    if previous is None:
        values = np.zeros(len(JOINT_NAMES))
    else:
        values = np.concatenate([np.asarray(previous.rotvecs, float).reshape(-1), previous.root_translation])
    unknown: list[str] = []
    updates: list[tuple[int, float]] = []
    # Validate everything before touching the output, so a bad message changes nothing.
    for name, value in zip(names, positions):
        index = JOINT_INDEX.get(name)
        if index is None:
            unknown.append(name)
            continue
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"joint {name!r} has non-finite position {value}")
        updates.append((index, value))
    for index, value in updates:
        values[index] = value
    pose = Pose(values[:_NUM_ROTATION].reshape(NUM_BONES, 3), values[_NUM_ROTATION:])
    return pose, unknown
