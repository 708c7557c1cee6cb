"""Motion: BVH reading and retargeting, procedural motions, JointState naming (pure numpy, no ROS).

Conventions: metres, radians, seconds; world Z up, the body faces -Y, its left side at +X. A pose is
``rotvecs (B, 3)`` (per bone, the local rotation vector relative to its world-aligned rest orientation,
``G_j = G_parent @ exp(rotvecs[j])``) plus ``root_translation (3,)`` (Hips displacement from rest, world);
zero is the rig's rest A-pose. Bones: the 31 of the ``cmu_mb`` rig in ``BONE_NAMES`` order.
"""
from .bvh import BVH_TO_ZUP, CMU_UNIT_METRES, BvhClip, CmuClip, load_cmu_bvh, parse_bvh
from .joint_names import JOINT_NAMES, joint_positions_to_pose, pose_to_joint_positions
from .procedural import MOTIONS, ProceduralMotion, get_motion, make_motion, motion_names
from .retarget import load_cmu_motion, retarget_clip
from .rotations import euler_to_matrix, matrix_to_rotvec, rotation_between, rotvec_to_matrix, wrap_rotvec
from .skeleton import (
    BONE_NAMES,
    NUM_BONES,
    PARENTS,
    Motion,
    Pose,
    bone_index,
    forward_kinematics,
    rig_default_heads_tails,
)

__all__ = [
    "BONE_NAMES",
    "BVH_TO_ZUP",
    "CMU_UNIT_METRES",
    "JOINT_NAMES",
    "MOTIONS",
    "NUM_BONES",
    "PARENTS",
    "BvhClip",
    "CmuClip",
    "Motion",
    "Pose",
    "ProceduralMotion",
    "bone_index",
    "euler_to_matrix",
    "forward_kinematics",
    "get_motion",
    "joint_positions_to_pose",
    "load_cmu_bvh",
    "load_cmu_motion",
    "make_motion",
    "matrix_to_rotvec",
    "motion_names",
    "parse_bvh",
    "pose_to_joint_positions",
    "retarget_clip",
    "rig_default_heads_tails",
    "rotation_between",
    "rotvec_to_matrix",
    "wrap_rotvec",
]
