"""Left-right mirror images of training drapes (offline.mirror): the reflected pose poses the reflected skeleton, the
reflected rest-frame garment skins to the reflected drape, and an asymmetric garment is refused."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agentdress_ros.body.kinematics import forward_kinematics, linear_blend_skinning
from agentdress_ros.offline.mirror import (REFLECTION, Mirror, bone_twins, mirrored_poses, mirrored_positions,
                                         twin_name)
from agentdress_ros.offline.regressor import (RegressorSettings, example_data, pose_dofs, settled_data,
                                            validate_settled_copies)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mirror(database, body):
    return Mirror.of(database, body)


@pytest.fixture(scope="module")
def drapes(database):
    """Drapes from rest along the training clips (the shipped T-shirt's), every 20th."""
    data, _ = settled_data(ROOT / "data" / "tshirt_rest.npz", database, 0.5)
    return data.rows(np.arange(0, len(data.poses), 20))


def _posed(pose, heads, parents):
    transforms = np.empty((len(heads), 3, 4))
    joints = forward_kinematics(np.ascontiguousarray(pose), np.zeros(3), heads, parents, transforms)
    return transforms, joints


def test_bone_twins_swap_sides_and_keep_the_middle(body):
    assert twin_name("LeftArm") == "RightArm" and twin_name("RHipJoint") == "LHipJoint"
    assert twin_name("LThumb") == "RThumb" and twin_name("Spine1") == "Spine1" and twin_name("LowerBack") == "LowerBack"
    twins = bone_twins(body.bone_names)
    assert (twins[twins] == np.arange(len(twins))).all() and (twins != np.arange(len(twins))).sum() == 24
    with pytest.raises(ValueError, match="LeftArm"):
        bone_twins(["Hips", "RightArm"])


def test_the_reflected_pose_poses_the_reflected_skeleton(body, database, drapes, mirror):
    heads = np.ascontiguousarray(body.shape(database.beta0).heads, dtype=np.float64)
    for pose in drapes.poses[:8]:
        _, joints = _posed(pose, heads, body.parents)
        _, twin_joints = _posed(mirrored_poses(pose[None], mirror.twins)[0], heads, body.parents)
        # the skeleton at beta0 is symmetric to 1.8 mm; posing spreads that along the chains a little
        assert np.abs(twin_joints[mirror.twins] - joints * REFLECTION).max() < 0.006
    assert np.array_equal(mirrored_poses(mirrored_poses(drapes.poses, mirror.twins), mirror.twins), drapes.poses)


def test_the_reflected_garment_skins_to_the_reflected_drape(body, database, drapes, mirror):
    heads = np.ascontiguousarray(body.shape(database.beta0).heads, dtype=np.float64)
    skin_i = np.ascontiguousarray(database.skin_indices, dtype=np.int32)
    skin_w = np.ascontiguousarray(database.skin_weights, dtype=np.float64)
    images = mirror(drapes)
    assert np.array_equal(images.groups, drapes.groups)
    gaps = []
    for n in range(8):
        transforms, _ = _posed(drapes.poses[n], heads, body.parents)
        drape = np.empty(drapes.positions[n].shape)
        linear_blend_skinning(np.ascontiguousarray(drapes.positions[n]), skin_i, skin_w, transforms, drape)
        transforms, _ = _posed(images.poses[n], heads, body.parents)
        image = np.empty(drape.shape)
        linear_blend_skinning(np.ascontiguousarray(images.positions[n]), skin_i, skin_w, transforms, image)
        # the image's vertex v sits where the drape's surface passes the mirror image of v's rest place
        expected = mirrored_positions(drape[None], mirror.corners, mirror.weights)[0]
        gaps.append(np.linalg.norm(image - expected, axis=1))
    gaps = np.concatenate(gaps)
    assert gaps.mean() < 0.001 and np.percentile(gaps, 99) < 0.006
    # twice reflected is the drape again, up to interpolating twice across the refinement's asymmetry
    twice = mirror(images).positions - drapes.positions
    assert np.linalg.norm(twice, axis=2).mean() < 0.0005
    # the rest garment is its own mirror image
    rest = np.asarray(database.rest, dtype=np.float64)[None]
    assert np.linalg.norm(mirror(replace(drapes.rows([0]), positions=rest)).positions - rest, axis=2).max() < 0.003


def test_an_asymmetric_garment_is_refused_by_name(database, body):
    rest = np.asarray(database.rest, dtype=np.float64) + [0.01, 0.0, 0.0]  # its image: 2 cm off
    with pytest.raises(ValueError, match="tshirt rest garment is 20.0 mm from its mirror image"):
        Mirror.of(replace(database, rest=rest.astype(np.float32)), body)


def test_mirror_images_join_the_training_folds_only(database, drapes, mirror):
    settings = RegressorSettings(components=6, hidden=(12,), alpha=1.0, examples=1, max_iter=30, dynamic=False,
                                 settled_copies=1)
    dofs = pose_dofs(database, settings.features)
    plain, mirrored = (validate_settled_copies(None, drapes, example_data(database), dofs, settings, [1], 2, m)[0]
                       for m in (None, mirror))
    # scored on the same held-out drapes, trained on more
    assert plain["validation_error_m"] != mirrored["validation_error_m"]
    assert 0.0 < mirrored["validation_error_m"] < 0.1
