"""BVH reader, and a loader for the CMU MotionBuilder-skeleton clips converted to the project's conventions.

``parse_bvh`` reads any BVH (hierarchy, offsets, channel order per joint, frame time, frames) and keeps the file's
units and axes. ``load_cmu_bvh`` checks that the skeleton is the CMU MotionBuilder one (31 joints; the names of
the ``cmu_mb`` rig) and converts it:

- units: CMU units -> metres (1 unit = 0.0564 m, the CMU FAQ's scale);
- axes: BVH is Y up with characters facing +Z and their left at +X; ours is Z up, facing -Y, left at +X, so a BVH
  vector (x, y, z) becomes (x, -z, y) (the proper rotation ``BVH_TO_ZUP``) and a rotation R becomes
  ``BVH_TO_ZUP @ R @ BVH_TO_ZUP.T``;
- frame 0 of every CMU clip is a T-pose added by the conversion: it is dropped from the frames and kept apart as
  the reference (``tpose_*``); so are frames right after it whose every channel is exactly 0 (07_12 has one: the
  conversion's blank rest frame at the origin, which no capture produces);
- the CMU floor is at height 0 (the skeleton's lowest joint stays ~4 cm above it while standing: the joints are
  inside the foot);
- bone order: the rig's ``BONE_NAMES`` (``LeftHandIndex1`` -> ``LeftHandFinger1``).

BVH rotation channels are Euler angles in degrees, applied intrinsically in the order the channels are listed
(``Zrotation Yrotation Xrotation`` -> ``Rz @ Ry @ Rx``); a joint's global rotation is ``D_j = D_parent @ R_j`` and
``p_j = p_parent + D_parent @ offset_j``. At rest (all channels zero) every BVH joint frame is world-aligned.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .rotations import rotvec_to_matrix
from .skeleton import BONE_NAMES, BVH_TO_RIG_NAMES, NUM_BONES, PARENTS

__all__ = [
    "BVH_TO_ZUP",
    "CMU_UNIT_METRES",
    "BvhClip",
    "CmuClip",
    "channel_rotations",
    "load_cmu_bvh",
    "parse_bvh",
]

CMU_UNIT_METRES = 0.0564
# BVH (x, y, z) -> ours (x, -z, y): Y up / facing +Z  ->  Z up / facing -Y; det = +1.
BVH_TO_ZUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_AXES = {"X": 0, "Y": 1, "Z": 2}


@dataclass
class BvhClip:
    """A BVH file as written: file units and axes, all frames.

    joint_names (J,), parents (J,) (-1 root, parents before children), offsets (J, 3) head offset from the parent
    head, end_sites (J, 3) End Site offset or NaN, channels: per joint a tuple of channel names in file order,
    frame_time seconds, frames (F, C) with C = total channel count, in file order.
    """

    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    end_sites: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    frame_time: float
    frames: np.ndarray
    name: str = ""

    @property
    def num_frames(self) -> int:
        return self.frames.shape[0]

    @property
    def fps(self) -> float:
        # Files store the frame time truncated (".0083333"): snap to the integer rate it stands for.
        rate = 1.0 / self.frame_time
        return float(round(rate)) if abs(rate - round(rate)) < 1e-2 else rate

    def channel_slices(self) -> list[slice]:
        """Column range of each joint's channels in ``frames``."""
        slices, start = [], 0
        for ch in self.channels:
            slices.append(slice(start, start + len(ch)))
            start += len(ch)
        return slices

    def local_rotations(self) -> np.ndarray:
        """Local rotation matrices from the rotation channels, file axes. -> (F, J, 3, 3)."""
        out = np.empty((self.num_frames, len(self.joint_names), 3, 3))
        for j, (sl, ch) in enumerate(zip(self.channel_slices(), self.channels)):
            out[:, j] = channel_rotations(self.frames[:, sl], ch)
        return out

    def root_positions(self) -> np.ndarray:
        """Root joint position per frame (root OFFSET + position channels), file units and axes. -> (F, 3)."""
        return self.offsets[0] + _position_channels(self.frames[:, self.channel_slices()[0]], self.channels[0])


def channel_rotations(values: np.ndarray, channels) -> np.ndarray:
    """Rotation of one joint from its channel values (F, C) in degrees, channel names (C,) -> (F, 3, 3).

    Rotation channels compose intrinsically in file order; position channels are ignored.
    """
    values = np.asarray(values, dtype=np.float64)
    result = np.broadcast_to(np.eye(3), (values.shape[0], 3, 3)).copy()
    for c, name in enumerate(channels):
        if name.endswith("rotation"):
            axis = np.zeros(3)
            axis[_AXES[name[0].upper()]] = 1.0
            result = result @ rotvec_to_matrix(np.radians(values[:, c : c + 1]) * axis)
    return result


def _position_channels(values: np.ndarray, channels) -> np.ndarray:
    out = np.zeros((values.shape[0], 3))
    for c, name in enumerate(channels):
        if name.endswith("position"):
            out[:, _AXES[name[0].upper()]] = values[:, c]
    return out


class _Tokens:
    def __init__(self, text: str, source: str):
        self.items = text.split()
        self.pos = 0
        self.source = source

    def next(self) -> str:
        if self.pos >= len(self.items):
            raise ValueError(f"{self.source}: unexpected end of BVH file")
        tok = self.items[self.pos]
        self.pos += 1
        return tok

    def expect(self, *words: str) -> str:
        tok = self.next()
        if tok not in words:
            raise ValueError(f"{self.source}: expected {' or '.join(words)} in BVH, got {tok!r}")
        return tok

    def floats(self, n: int) -> list[float]:
        try:
            return [float(self.next()) for _ in range(n)]
        except ValueError as err:
            raise ValueError(f"{self.source}: bad number in BVH: {err}") from None


def parse_bvh(path_or_text, name: str | None = None) -> BvhClip:
    """Read a BVH file (a path, or the text itself when it contains a newline). Keeps file units and axes."""
    if isinstance(path_or_text, Path) or "\n" not in str(path_or_text):
        path = Path(path_or_text)
        text = path.read_text()
        source = str(path)
        name = name if name is not None else path.stem
    else:
        text, source = str(path_or_text), "<bvh text>"
    head, sep, motion = text.partition("MOTION")
    if not sep:
        raise ValueError(f"{source}: no MOTION section in BVH")
    tokens = _Tokens(head, source)
    tokens.expect("HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    end_sites: list[list[float]] = []
    channels: list[tuple[str, ...]] = []

    def joint(parent: int) -> None:
        index = len(names)
        names.append(tokens.next())
        parents.append(parent)
        end_sites.append([np.nan] * 3)
        tokens.expect("{")
        tokens.expect("OFFSET")
        offsets.append(tokens.floats(3))
        tokens.expect("CHANNELS")
        count = int(tokens.next())
        channels.append(tuple(tokens.next() for _ in range(count)))
        while True:
            tok = tokens.expect("JOINT", "End", "}")
            if tok == "}":
                return
            if tok == "JOINT":
                joint(index)
            else:
                tokens.expect("Site")
                tokens.expect("{")
                tokens.expect("OFFSET")
                end_sites[index] = tokens.floats(3)
                tokens.expect("}")

    tokens.expect("ROOT")
    joint(-1)
    if tokens.pos != len(tokens.items):
        raise ValueError(f"{source}: BVH with more than one ROOT is not supported")

    mt = motion.split()
    try:
        if mt[0] != "Frames:" or mt[2:4] != ["Frame", "Time:"]:
            raise ValueError
        num_frames, frame_time = int(mt[1]), float(mt[4])
    except (ValueError, IndexError):
        raise ValueError(f"{source}: BVH MOTION section must start with 'Frames: N' and 'Frame Time: T'") from None
    num_channels = sum(len(c) for c in channels)
    data = np.array(mt[5:], dtype=np.float64)
    if data.size != num_frames * num_channels:
        raise ValueError(
            f"{source}: BVH declares {num_frames} frames x {num_channels} channels but holds {data.size} values"
        )
    if frame_time <= 0:
        raise ValueError(f"{source}: BVH frame time must be positive, got {frame_time}")
    return BvhClip(
        joint_names=tuple(names),
        parents=tuple(parents),
        offsets=np.array(offsets, dtype=np.float64),
        end_sites=np.array(end_sites, dtype=np.float64),
        channels=tuple(channels),
        frame_time=frame_time,
        frames=data.reshape(num_frames, num_channels),
        name=name or "",
    )


@dataclass
class CmuClip:
    """A CMU MotionBuilder-skeleton clip in the project's conventions (metres, Z up, facing -Y, rig bone order).

    offsets (B, 3): rest offset of each bone's head from its parent's head (root: its OFFSET);
    end_sites (B, 3): End Site offset from the bone's head, NaN where the bone has none;
    local_rotations (F, B, 3, 3) and root_positions (F, 3): the motion without the T-pose frame;
    tpose_local_rotations (B, 3, 3) and tpose_root_position (3,): the dropped frame 0;
    dropped_frames: how many leading file frames were left out (1, or more with blank frames after the T-pose).
    """

    name: str
    fps: float
    offsets: np.ndarray
    end_sites: np.ndarray
    local_rotations: np.ndarray
    root_positions: np.ndarray
    tpose_local_rotations: np.ndarray
    tpose_root_position: np.ndarray
    dropped_frames: int = 1

    parents = PARENTS

    @property
    def num_frames(self) -> int:
        return self.local_rotations.shape[0]

    def rest_heads(self) -> np.ndarray:
        """Joint positions of the BVH rest skeleton (all channels zero, root at its OFFSET). -> (B, 3)."""
        heads = np.zeros((NUM_BONES, 3))
        for j, p in enumerate(PARENTS):
            heads[j] = self.offsets[j] if p < 0 else heads[p] + self.offsets[j]
        return heads

    def global_rotations(self, local_rotations: np.ndarray | None = None) -> np.ndarray:
        """D_j = D_parent @ R_j. local_rotations (..., B, 3, 3) (default: the clip's) -> (..., B, 3, 3)."""
        local = self.local_rotations if local_rotations is None else local_rotations
        out = np.empty_like(local)
        for j, p in enumerate(PARENTS):
            out[..., j, :, :] = local[..., j, :, :] if p < 0 else out[..., p, :, :] @ local[..., j, :, :]
        return out

    def joint_positions(self, local_rotations=None, root_positions=None) -> np.ndarray:
        """Forward kinematics of the BVH skeleton. -> (..., B, 3) metres, Z up."""
        local = self.local_rotations if local_rotations is None else local_rotations
        roots = self.root_positions if root_positions is None else root_positions
        glob = self.global_rotations(local)
        out = np.empty(local.shape[:-1])
        for j, p in enumerate(PARENTS):
            if p < 0:
                out[..., j, :] = roots
            else:
                out[..., j, :] = out[..., p, :] + glob[..., p, :, :] @ self.offsets[j]
        return out

    def tpose_joint_positions(self) -> np.ndarray:
        """Joint positions of the dropped T-pose frame 0. -> (B, 3)."""
        return self.joint_positions(self.tpose_local_rotations, self.tpose_root_position)


def _rig_order_from_bvh(clip: BvhClip, source: str) -> list[int]:
    """For each rig bone, its joint index in the BVH; ValueError if the skeleton is not CMU MotionBuilder's."""
    rig_names = [BVH_TO_RIG_NAMES.get(n, n) for n in clip.joint_names]
    expected = set(BONE_NAMES)
    missing = [n for n in BONE_NAMES if n not in rig_names]
    unknown = [n for n, r in zip(clip.joint_names, rig_names) if r not in expected]
    if missing or unknown or len(rig_names) != NUM_BONES:
        raise ValueError(
            f"{source}: not the CMU MotionBuilder skeleton (31 joints named as in the cmu_mb rig) that this loader "
            f"expects; missing joints: {', '.join(missing) or 'none'}; unknown joints: {', '.join(unknown) or 'none'}"
        )
    where = {n: i for i, n in enumerate(rig_names)}
    order = [where[n] for n in BONE_NAMES]
    for j, p in enumerate(PARENTS):
        bvh_parent = clip.parents[order[j]]
        if (p < 0) != (bvh_parent < 0) or (p >= 0 and bvh_parent != order[p]):
            got = "none" if bvh_parent < 0 else clip.joint_names[bvh_parent]
            raise ValueError(
                f"{source}: joint {BONE_NAMES[j]} has parent {got}, the CMU MotionBuilder skeleton has "
                f"{BONE_NAMES[p] if p >= 0 else 'none (root)'}"
            )
    return order


def load_cmu_bvh(path, drop_tpose: bool = True, unit_metres: float = CMU_UNIT_METRES) -> CmuClip:
    """Load a CMU MotionBuilder-skeleton BVH clip in metres, Z up, facing -Y, rig bone order.

    ``drop_tpose``: frame 0 of the CMU conversions is a T-pose, not motion; it is always kept as the reference
    (``tpose_*``) and, when True, left out of the frames with any blank (all channels exactly 0) frames right after
    it (F = file frames - 1 for all but one of the shipped clips).
    """
    clip = parse_bvh(path) if not isinstance(path, BvhClip) else path
    source = str(path) if not isinstance(path, BvhClip) else (clip.name or "<bvh>")
    order = _rig_order_from_bvh(clip, source)
    first = 0
    if drop_tpose:
        first = 1
        while first < clip.num_frames and not np.any(clip.frames[first]):
            first += 1
    if first >= clip.num_frames:
        raise ValueError(f"{source}: BVH has no motion frames after the T-pose frame (and blank frames)")
    c = BVH_TO_ZUP
    local = clip.local_rotations()[:, order]
    local = c @ local @ c.T  # conjugation: the same rotation expressed in Z-up axes
    roots = clip.root_positions() @ c.T * unit_metres
    offsets = clip.offsets[order] @ c.T * unit_metres
    end_sites = clip.end_sites[order] @ c.T * unit_metres
    return CmuClip(
        name=clip.name,
        fps=clip.fps,
        offsets=offsets,
        end_sites=end_sites,
        local_rotations=local[first:],
        root_positions=roots[first:],
        tpose_local_rotations=local[0],
        tpose_root_position=roots[0],
        dropped_frames=first,
    )
