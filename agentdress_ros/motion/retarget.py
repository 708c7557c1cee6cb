"""Retarget a CMU BVH clip onto the ``cmu_mb`` rig convention (see ``skeleton``: metres, Z up, facing -Y).

The BVH rest skeleton (arms horizontal, legs spread ~20 degrees) differs from the rig's rest (an A-pose), so local
rotations cannot be copied. Both rests have world-aligned bone frames, so instead each rig bone is made to point
where its BVH bone points:

- ``b_j``: BVH rest direction of bone j (head -> mean of its children's heads, or its End Site), Z up;
- ``a_j``: rig rest direction (``rest_tails[j] - rest_heads[j]``);
- ``A_j``: the minimal rotation taking ``b_j`` to ``a_j``. Where ``b_j`` is undefined (all children sit on the
  head: Hips, Spine1, the hands) ``A_j = A_parent`` (identity at the root), so the joint keeps the BVH's local
  rotation, expressed in the parent's retargeted frame;
- the rig's global rotation ``Delta_j = D_j @ A_j.T`` with ``D_j`` the BVH global rotation (Z up), hence
  ``Delta_j @ a_j`` is parallel to ``D_j @ b_j``; the local rotation is ``R_j = Delta_parent.T @ Delta_j``.

Root translation: horizontally, the BVH root's displacement from its first frame (where the dropped T-pose stood:
the CMU conversion copies it there, except in 07_12 whose T-pose sits at the origin) times ``leg_scale``.
Vertically (``vertical="feet"``, the default) the rig is lifted so that its lowest joint is as high above its rest
floor as the BVH's lowest joint is above the CMU floor (height 0) less ``CMU_FOOT_CLEARANCE``, times
``leg_scale``. Measured over the 21 clips with the default rig: the median per clip of the rig's lowest joint
lies -3..+2 cm from its rest floor on flat ground (-7 cm in the 05_06 cartwheels), against -6..+15 cm with
``vertical="root"`` (the BVH root's height change since the first frame, times ``leg_scale``), which puts a clip
that starts crouched (08_07) or away from the floor at rest height.
"""
from __future__ import annotations

import numpy as np

from .bvh import CmuClip, load_cmu_bvh
from .cleanup import repair_limb_flips
from .rotations import matrix_to_rotvec, rotation_between
from .skeleton import NUM_BONES, PARENTS, Motion, bone_index, children_of, forward_kinematics, rig_default_heads_tails

__all__ = [
    "CMU_FOOT_CLEARANCE",
    "bvh_rest_directions",
    "hip_height",
    "load_cmu_motion",
    "retarget_clip",
    "retarget_rotations",
]

# Height of the CMU skeleton's lowest joint (or End Site) above the floor while standing or walking: the median over
# frames is 3-6 cm in the flat-ground clips (the joints are inside the foot).
CMU_FOOT_CLEARANCE = 0.04
# Bones shorter than this (metres) have no direction.
_MIN_BONE_LENGTH = 1e-6


def bvh_rest_directions(clip: CmuClip) -> tuple[np.ndarray, np.ndarray]:
    """Rest direction of each BVH bone (not normalised) and whether it is defined. -> (B, 3), (B,) bool."""
    heads = clip.rest_heads()
    kids = children_of(PARENTS)
    directions = np.zeros((NUM_BONES, 3))
    for j in range(NUM_BONES):
        if kids[j]:
            directions[j] = heads[kids[j]].mean(axis=0) - heads[j]
        elif np.all(np.isfinite(clip.end_sites[j])):
            directions[j] = clip.end_sites[j]
    defined = np.linalg.norm(directions, axis=1) > _MIN_BONE_LENGTH
    return directions, defined


def _alignments(clip: CmuClip, rest_heads, rest_tails) -> np.ndarray:
    """A_j (B, 3, 3): minimal rotation from BVH rest bone direction to rig rest bone direction."""
    rig_dirs = np.asarray(rest_tails, dtype=np.float64) - np.asarray(rest_heads, dtype=np.float64)
    if rig_dirs.shape != (NUM_BONES, 3):
        raise ValueError(f"rest_heads and rest_tails must be ({NUM_BONES}, 3), got {rig_dirs.shape}")
    bvh_dirs, defined = bvh_rest_directions(clip)
    rig_defined = np.linalg.norm(rig_dirs, axis=1) > _MIN_BONE_LENGTH
    aligned = rotation_between(bvh_dirs, rig_dirs)
    out = np.empty((NUM_BONES, 3, 3))
    for j, p in enumerate(PARENTS):
        if defined[j] and rig_defined[j]:
            out[j] = aligned[j]
        else:
            out[j] = np.eye(3) if p < 0 else out[p]
    return out


def retarget_rotations(clip: CmuClip, rest_heads, rest_tails) -> np.ndarray:
    """Local rig rotation vectors for every frame. -> (F, B, 3)."""
    align = _alignments(clip, rest_heads, rest_tails)
    bvh_global = clip.global_rotations()  # (F, B, 3, 3), Z up
    rig_global = bvh_global @ np.swapaxes(align, -1, -2)
    local = np.empty_like(rig_global)
    for j, p in enumerate(PARENTS):
        local[:, j] = rig_global[:, j] if p < 0 else np.swapaxes(rig_global[:, p], -1, -2) @ rig_global[:, j]
    return matrix_to_rotvec(local)


def hip_height(heads, tails=None) -> float:
    """Height of the hip joints (mean of the ``LeftUpLeg`` and ``RightUpLeg`` heads) above the lowest head or tail.
    heads (B, 3), tails (B, 3) or None (rows with NaN skipped). The leg length that sets the stride; the ``Hips``
    joint itself is no measure of it (10 cm above the hip joints in the CMU skeleton, level with them in the rig)."""
    heads = np.asarray(heads, dtype=np.float64)
    points = heads
    if tails is not None:
        points = np.concatenate([points, np.asarray(tails, dtype=np.float64)])
    points = points[np.all(np.isfinite(points), axis=1)]
    hips = heads[[bone_index("LeftUpLeg"), bone_index("RightUpLeg")], 2].mean()
    return float(hips - points[:, 2].min())


def _bvh_tpose_hip_height(clip: CmuClip) -> float:
    # The T-pose frame has straight, closed legs, like the rig's rest; the BVH rest (offsets) has them spread.
    joints = clip.tpose_joint_positions()
    glob = clip.global_rotations(clip.tpose_local_rotations)
    has_end = np.all(np.isfinite(clip.end_sites), axis=1)
    ends = joints[has_end] + np.einsum("bik,bk->bi", glob[has_end], clip.end_sites[has_end])
    return hip_height(joints, ends)


def _lowest_points(positions, rotations, tails_offsets) -> np.ndarray:
    """Per frame, the lowest z over joints and bone ends. positions (F, B, 3), rotations (F, B, 3, 3),
    tails_offsets (B, 3) from each head (NaN rows skipped) -> (F,)."""
    has = np.all(np.isfinite(tails_offsets), axis=1)
    ends = positions[:, has] + np.einsum("fbik,bk->fbi", rotations[:, has], tails_offsets[has])
    return np.minimum(positions[..., 2].min(axis=1), ends[..., 2].min(axis=1))


def retarget_clip(
    clip: CmuClip, rest_heads, rest_tails, leg_scale: float | None = None, vertical: str = "feet"
) -> Motion:
    """Map a CMU clip onto the rig whose rest bones are rest_heads (B, 3) -> rest_tails (B, 3) (metres, Z up).

    leg_scale: factor on the root translation. None (default) uses rig hip height / BVH hip height (``hip_height``,
    BVH in its T-pose frame), so feet travel as far as the rig's legs allow; 1.0 keeps the BVH's metres.
    vertical: "feet" (default) keeps the rig's lowest joint as high above its rest floor as the BVH's is above the
    CMU floor; "root" uses the BVH root's height change since the first frame (see the module docstring).
    Returns a Motion with rotvecs (F, B, 3), root_translation (F, 3), the clip's fps.
    """
    rest_heads = np.asarray(rest_heads, dtype=np.float64)
    rest_tails = np.asarray(rest_tails, dtype=np.float64)
    rotvecs = retarget_rotations(clip, rest_heads, rest_tails)
    if vertical not in ("feet", "root"):
        raise ValueError(f"vertical must be 'feet' or 'root', got {vertical!r}")
    if leg_scale is None:
        leg_scale = hip_height(rest_heads, rest_tails) / _bvh_tpose_hip_height(clip)
    if not (np.isfinite(leg_scale) and leg_scale > 0):
        raise ValueError(f"leg_scale must be a positive finite number, got {leg_scale}")
    translation = (clip.root_positions - clip.root_positions[0]) * float(leg_scale)
    if vertical == "feet":
        bvh_lowest = _lowest_points(clip.joint_positions(), clip.global_rotations(), clip.end_sites)
        rig_positions, rig_rotations = forward_kinematics(rotvecs, np.zeros(3), rest_heads)
        rig_lowest = _lowest_points(rig_positions, rig_rotations, rest_tails - rest_heads)
        rig_floor = min(rest_heads[:, 2].min(), rest_tails[:, 2].min())
        translation[:, 2] = rig_floor - rig_lowest + (bvh_lowest - CMU_FOOT_CLEARANCE) * float(leg_scale)
    return Motion(rotvecs=rotvecs, root_translation=translation, fps=clip.fps, name=clip.name)


def load_cmu_motion(
    path, rest_heads=None, rest_tails=None, leg_scale: float | None = None, vertical: str = "feet",
    repair_flips: bool = True,
) -> Motion:
    """Read a CMU BVH file and retarget it (default rig rest from the rig JSON when heads/tails are None).

    repair_flips: make knee and elbow swivels continuous where the capture flips a limb round in one frame
    (``cleanup.repair_limb_flips``; the four CMU dance clips 05_05, 05_06, 05_08 and 05_16 have such flips, no
    other clip is changed by it)."""
    if rest_heads is None or rest_tails is None:
        default_heads, default_tails = rig_default_heads_tails()
        rest_heads = default_heads if rest_heads is None else rest_heads
        rest_tails = default_tails if rest_tails is None else rest_tails
    motion = retarget_clip(load_cmu_bvh(path), rest_heads, rest_tails, leg_scale=leg_scale, vertical=vertical)
    if repair_flips:
        motion.rotvecs, _ = repair_limb_flips(motion.rotvecs, rest_heads, motion.fps)
    return motion
