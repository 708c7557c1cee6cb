"""Repair of limb flips in motion capture: a knee or elbow that jumps around its limb's axis in one frame.

With the hip and the ankle in place, a marker solver can put the knee anywhere on a circle around the hip-ankle
line, and with a straight or raised leg it sometimes picks another point of that circle for a few frames. The CMU
dance clips do this: in 05_16 the right knee jumps 35 cm in 1/120 s (frame 202) while hip and ankle move 1.3 cm,
and jumps back 17 frames later; the thigh's local rotation changes by 3.0 rad in one frame each time (360 rad/s) and
the foot's by 2.5 rad the other way, keeping the foot where it was. Skinned, the thigh wrings its skin round in one
frame (body vertices at 16-18 m/s), which no cloth simulation survives.

`repair_limb_flips` makes each limb's swivel continuous: where the upper bone's local rotation changes faster than
`max_speed`, the limb is turned about its root-to-end line (hip-ankle, shoulder-wrist) by the angle that best
continues the previous two (repaired) frames' motion, and that correction is carried until the data flips back
(where the best angle is ~0 again); the end bone (foot, hand), which flips on its own as well, gets the same
treatment with a free rotation of its local one. Every joint position other than the knee or elbow and what hangs
off the end bone (toes, fingers) is kept, so the foot stays where the capture has it. An injected flip is undone
to 3e-4 rad (the one frame's motion the extrapolation misses); frames without a flip are returned exactly as given.
"""
from __future__ import annotations

import numpy as np

from .rotations import axis_angle_matrix, matrix_to_rotvec, rotvec_to_matrix
from .skeleton import PARENTS, bone_index, forward_kinematics

__all__ = ["LIMBS", "MAX_LIMB_SPEED", "repair_limb_flips"]

# (upper, end) bones of each limb: the swivel turns the limb from its upper bone down about the line from the upper
# bone's head to the end bone's head (hip-ankle, shoulder-wrist), moving only the knee or elbow between them.
LIMBS = (("LeftUpLeg", "LeftFoot"), ("RightUpLeg", "RightFoot"), ("LeftArm", "LeftHand"), ("RightArm", "RightHand"))
# rad/s of a limb bone's local rotation above which a frame-to-frame change is a flip, not motion. In the 45 CMU
# clips, the fastest limb motion runs at up to 120 rad/s (a knee in 05_16: 1 rad in a 120 fps frame); the flips at
# 240-380 rad/s.
MAX_LIMB_SPEED = 150.0


def _best_swivel(axis, current, target) -> float:
    """Angle phi about the unit `axis` (3,) whose rotation C maximises trace(target^T C current): the turn about the
    limb's line that brings the rotation `current` (3, 3) closest to `target` (3, 3)."""
    m = current @ target.T
    along = axis @ m @ axis
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return float(np.arctan2(np.trace(cross @ m), np.trace(m) - along))


def _extrapolate(earlier, last) -> np.ndarray:
    """The rotation (3, 3) one frame after `last`, turning on as it turned from `earlier` (3, 3) to `last`."""
    return last @ earlier.T @ last


def _angle_between(a, b):
    """Angle (rad) of the rotation taking a (..., 3, 3) to b (..., 3, 3): trace(a^T b) = 1 + 2 cos(angle)."""
    return np.arccos(np.clip((np.einsum("...ij,...ij->...", a, b) - 1.0) / 2.0, -1.0, 1.0))


def _jumps(local, limit: float) -> np.ndarray:
    """Frames f (F,) bool whose local rotation (F, 3, 3) differs from frame f - 1's by more than `limit` rad."""
    return np.concatenate([[False], _angle_between(local[:-1], local[1:]) > limit])


def repair_limb_flips(rotvecs, rest_heads, fps: float, max_speed: float = MAX_LIMB_SPEED) -> tuple:
    """(rotvecs (F, B, 3) repaired, report) for a clip's local rotations rotvecs (F, B, 3) at `fps` on a rig with
    rest heads (B, 3). The report lists, per limb whose swivel was repaired, its upper bone's name, the frames where
    a flip began or ended, and the frames carried with a correction."""
    rotvecs = np.asarray(rotvecs, dtype=np.float64)
    limit = max_speed / float(fps)
    positions, rotations = forward_kinematics(rotvecs, np.zeros(3), rest_heads)
    local = rotvec_to_matrix(rotvecs)
    repaired = rotvecs.copy()
    report = []
    for upper_name, end_name in LIMBS:
        upper, end = bone_index(upper_name), bone_index(end_name)
        parent = PARENTS[upper]
        jumps = _jumps(local[:, upper], limit)
        phi, flips, corrected = 0.0, [], 0
        before = [rotations[0, upper]] * 2  # world rotations of the upper bone in the last two repaired frames
        for f in range(len(rotvecs)):
            upper_world = rotations[f, upper]
            if jumps[f] or phi != 0.0:
                axis = positions[f, end] - positions[f, upper]
                axis = axis / max(np.linalg.norm(axis), 1e-12)
            if jumps[f]:
                expected = _extrapolate(*before)
                best = _best_swivel(axis, upper_world, expected)
                if _angle_between(expected, axis_angle_matrix(axis, best) @ upper_world) < limit:
                    flips.append(f)  # a swivel explains the jump: repair it
                    phi = best if abs(best) >= 0.5 * limit else 0.0  # ~0: back where the data was, flip ended
            if phi != 0.0:
                upper_world = axis_angle_matrix(axis, phi) @ upper_world
                repaired[f, upper] = matrix_to_rotvec(rotations[f, parent].T @ upper_world)
                corrected += 1
            before = [before[1], upper_world]
        end_flips, end_corrected = _repair_end_bone(local[:, end], repaired, end, limit)
        if flips or end_flips:
            report.append({"limb": upper_name, "flips": flips, "frames_corrected": corrected,
                           "end_bone_flips": end_flips, "end_bone_frames_corrected": end_corrected})
    return repaired, report


def _repair_end_bone(local, repaired, bone: int, limit: float) -> tuple:
    """Make the end bone's (foot's, hand's) local rotations local (F, 3, 3) continuous, writing rotation vectors
    into repaired[:, bone]: where one changes by more than `limit` (rad) in a frame, the rotation K that takes it to
    where the previous repaired frames were turning is applied from there on (K local), until a later jump brings K
    back to ~identity. The flip is a fixed turn in the parent's frame, so K carries it. -> (flip frames, frames
    corrected)."""
    jumps = _jumps(local, limit)
    correction, flips, corrected = None, [], 0
    before = [local[0]] * 2
    for f in range(1, len(local)):
        if jumps[f]:
            flips.append(f)
            correction = _extrapolate(*before) @ local[f].T
            if _angle_between(np.eye(3), correction) < 0.5 * limit:
                correction = None
        current = local[f]
        if correction is not None:
            current = correction @ current
            repaired[f, bone] = matrix_to_rotvec(current)
            corrected += 1
        before = [before[1], current]
    return flips, corrected
