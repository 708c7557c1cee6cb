"""The Anny body without torch: shape, skeleton, forward kinematics and skinning against analytic truth."""
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from agentdress_ros.body import PHENOTYPE_NAMES, REFERENCE_SHAPE, check_shape, rotvec_to_matrix


@pytest.fixture(scope="module")
def rest(body):
    return body.shape(REFERENCE_SHAPE)


def test_rig_is_cmu_mb_with_31_bones(body):
    assert body.n_bones == 31
    assert body.bone_names[0] == "Hips" and body.parents[0] == -1
    assert all(0 <= p < j for j, p in enumerate(body.parents) if j > 0), "parents precede children"
    for name in ("LeftUpLeg", "LeftForeArm", "RightHand", "Spine1", "Neck1", "Head", "LThumb"):
        assert name in body.bone_names


def test_identity_pose_returns_the_rest_mesh(body, rest):
    transforms, joints = body.pose(rest, np.zeros((31, 3)))
    np.testing.assert_allclose(body.posed_vertices(rest, transforms), rest.vertices, atol=1e-12)
    np.testing.assert_allclose(joints, rest.heads, atol=1e-12)


def test_root_translation_moves_everything_rigidly(body, rest):
    shift = np.array([0.3, -1.2, 0.05])
    transforms, _ = body.pose(rest, np.zeros((31, 3)), shift)
    np.testing.assert_allclose(body.posed_vertices(rest, transforms), rest.vertices + shift, atol=1e-12)


def test_ninety_degree_elbow_rotation_moves_the_forearm_where_geometry_says(body, rest):
    forearm = body.bone_index("LeftForeArm")
    elbow = rest.heads[forearm]
    axis = np.array([1.0, 0.0, 0.0])  # flex about the world x axis through the elbow
    rotvecs = np.zeros((31, 3))
    rotvecs[forearm] = 0.5 * np.pi * axis
    transforms, joints = body.pose(rest, rotvecs)
    posed = body.posed_vertices(rest, transforms)
    rigid = np.flatnonzero((body.skin_indices[:, 0] == forearm) & (body.skin_weights[:, 0] == 1.0))
    assert len(rigid) > 50
    expected = (rest.vertices[rigid] - elbow) @ Rotation.from_rotvec(rotvecs[forearm]).as_matrix().T + elbow
    np.testing.assert_allclose(posed[rigid], expected, atol=1e-9)
    # the wrist joint travels on a circle about the elbow: same distance, 90 degrees apart
    hand = body.bone_index("LeftHand")
    before, after = rest.heads[hand] - elbow, joints[hand] - elbow
    assert np.isclose(np.linalg.norm(before), np.linalg.norm(after))
    perpendicular_part = before - before @ axis * axis
    cos = (after - after @ axis * axis) @ perpendicular_part / (perpendicular_part @ perpendicular_part)
    assert abs(cos) < 1e-9
    # the upper arm does not move
    upper = np.flatnonzero((body.skin_indices[:, 0] == body.bone_index("LeftArm")) & (body.skin_weights[:, 0] == 1.0))
    np.testing.assert_allclose(posed[upper], rest.vertices[upper], atol=1e-12)


def test_forward_kinematics_composes_rotations_down_the_chain(body, rest):
    rng = np.random.default_rng(3)
    rotvecs = rng.normal(scale=0.6, size=(31, 3))
    translation = rng.normal(size=3)
    _, joints = body.pose(rest, rotvecs, translation)
    # reference: plain scipy composition G_j = G_parent R_j, p_j = p_parent + G_parent (h_j - h_parent)
    rotations, positions = [], []
    for j, parent in enumerate(body.parents):
        local = Rotation.from_rotvec(rotvecs[j])
        if parent < 0:
            rotations.append(local)
            positions.append(rest.heads[j] + translation)
        else:
            rotations.append(rotations[parent] * local)
            positions.append(positions[parent] + rotations[parent].apply(rest.heads[j] - rest.heads[parent]))
    np.testing.assert_allclose(joints, np.array(positions), atol=1e-10)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-7, np.pi, 3 * np.pi])
def test_rodrigues_matches_scipy_at_every_angle(angle):
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    out = np.empty((3, 3))
    rotvec_to_matrix(angle * axis, out)
    np.testing.assert_allclose(out, Rotation.from_rotvec(angle * axis).as_matrix(), atol=1e-12)


def test_skinning_transforms_are_rigid(body, rest):
    transforms, _ = body.pose(rest, np.random.default_rng(0).normal(size=(31, 3)))
    rotation = transforms[:, :, :3]
    np.testing.assert_allclose(rotation @ rotation.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (31, 3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-12)


def test_shape_stands_on_the_ground_and_height_follows_the_phenotype(body):
    heights = []
    for h in (0.0, 0.5, 1.0):
        beta = REFERENCE_SHAPE.copy()
        beta[PHENOTYPE_NAMES.index("height")] = h
        shape = body.shape(beta)
        feet = shape.vertices[body.body_vertex_ids, 2]
        assert abs(feet.min()) < 1e-12
        heights.append(feet.max())
    assert heights[0] < heights[1] < heights[2]
    assert 1.2 < heights[0] and heights[2] < 2.5, heights


def test_bones_follow_the_shape_and_stay_inside_the_body(body):
    for beta in ([0, 2 / 3, 0, 0, 0, 0], [1, 2 / 3, 1, 1, 1, 1], REFERENCE_SHAPE):
        shape = body.shape(beta)
        mesh = trimesh.Trimesh(shape.vertices, body.body_faces, process=False)
        assert mesh.is_watertight
        trunk = [body.bone_index(n) for n in ("Hips", "Spine", "Spine1", "Neck", "LeftUpLeg", "LeftLeg",
                                              "LeftForeArm", "RightArm", "Head")]
        assert mesh.contains(shape.heads[trunk]).all(), "joint centres lie inside the body of every shape"


def test_out_of_range_shape_is_clamped_and_flagged(body):
    shape = body.shape([1.5, -0.2, 0.5, 0.5, 0.5, 0.5])
    assert shape.clamped
    np.testing.assert_allclose(shape.beta[:2], [1.0, 0.0])
    assert np.isfinite(shape.vertices).all()
    np.testing.assert_allclose(shape.vertices, body.shape([1.0, 0.0, 0.5, 0.5, 0.5, 0.5]).vertices)
    assert not body.shape(REFERENCE_SHAPE).clamped


@pytest.mark.parametrize(
    "beta, message",
    [
        ([0.5, np.nan, 0.5, 0.5, 0.5, 0.5], "non-finite values for age"),
        ([0.5, 0.5, 0.5, np.inf, 0.5, 0.5], "non-finite values for weight"),
        ([0.5, 0.5], "needs 6 values"),
    ],
)
def test_bad_shape_is_rejected_with_a_clear_error(body, beta, message):
    with pytest.raises(ValueError, match=message):
        body.shape(beta)


def test_strict_shape_check_names_the_phenotype():
    with pytest.raises(ValueError, match="outside \\[0, 1\\] for muscle"):
        check_shape([0.5, 0.5, 1.2, 0.5, 0.5, 0.5], clamp=False)


def test_extreme_shapes_give_finite_plausible_bodies(body):
    for corner in np.array(np.meshgrid(*[[0.0, 1.0]] * 6)).reshape(6, -1).T[::7]:
        shape = body.shape(corner)
        assert np.isfinite(shape.vertices).all() and np.isfinite(shape.heads).all()
        height = np.ptp(shape.vertices[body.body_vertex_ids, 2])
        assert 0.4 < height < 2.5  # age 0 is a baby in Anny's scale
