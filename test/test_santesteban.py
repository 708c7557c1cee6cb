"""Santesteban et al. 2019 as a garment model of its own (engine.santesteban, offline.santesteban): training,
numpy inference, the post-process, storage."""
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from agentdress_ros.body.kinematics import forward_kinematics, linear_blend_skinning
from agentdress_ros.offline.jobs import read_drape_pack
from agentdress_ros.offline.regressor import RegressorSettings, predict
from agentdress_ros.offline.santesteban import SantestebanSettings, inputs, train, unposed_anchor_drapes
from agentdress_ros.offline.sequences import load_sequence_pack
from agentdress_ros.engine import DatabaseError, EngineConfig, read_database, write_database
from agentdress_ros.engine.database import as_stored
from agentdress_ros.engine.engine import permute_vertices, select_database
from agentdress_ros.engine.pose_models import canonical_poses
from agentdress_ros.engine.santesteban import SantestebanModel, push_out_of_body

from .conftest import assert_no_learning_library_after, run_training_command

ROOT = Path(__file__).resolve().parents[1]
DATABASE = ROOT / "data" / "tshirt_default.h5"
DRAPES = ROOT / "data" / "tshirt_default.drapes.npz"
PACK = ROOT / "data" / "tshirt_sequences.npz"
TINY = SantestebanSettings(fit=RegressorSettings(components=4, hidden=(6,), alpha=1e-3, max_iter=60, examples=0),
                           wrinkles=RegressorSettings(components=6, hidden=(12,), alpha=1.0, max_iter=40, examples=0),
                           anchor_copies=1, pack_frames=60)


@pytest.fixture(scope="module")
def pack():
    return load_sequence_pack(PACK)


@pytest.fixture(scope="module")
def trained(body, database, pack):
    arrays, report = train(database, body, DRAPES, pack, TINY, progress=False)
    return arrays, report


def test_training_is_deterministic_and_reports_its_data(body, database, pack, trained):
    arrays, report = trained
    again, _ = train(database, body, DRAPES, pack, TINY, progress=False)
    for a, b in ((arrays.fit, again.fit), (arrays.wrinkles, again.wrinkles)):
        for x, y in zip(a.weights + a.biases, b.weights + b.biases):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_array_equal(a.basis, b.basis)
    assert report["anchors"] == database.n_anchors and report["shapes"] == len(database.training_betas)
    assert report["pack_frames"] == 60 and report["pack_clips"] > 3
    n_pose = 3 * len(database.parents)
    # R_G sees the phenotypes only, R_L the pose's dofs and the phenotypes: those that vary over the training
    # shapes (one held fixed there carries no information)
    varying = (n_pose + np.flatnonzero(np.asarray(database.training_betas).std(axis=0) >= 0.01)).tolist()
    assert 0 < len(varying) < 6 and arrays.fit.dofs.tolist() == varying
    assert arrays.wrinkles.dofs.min() < n_pose and arrays.wrinkles.dofs[-len(varying):].tolist() == varying


def test_unposed_anchor_drapes_skin_back_to_the_drapes(body, database):
    """Unposing with each shape's skeleton is undone by skinning with it: the drape comes back (beta0's anchors
    are also the database's example drapes)."""
    unposed = unposed_anchor_drapes(database, body, DRAPES)
    assert unposed.shape == (database.n_anchors, len(database.training_betas), database.n_vertices, 3)
    anchor, shape = 5, 9
    drape = read_drape_pack(DRAPES)["drapes"][f"anchor_{anchor:04d}_{shape:02d}"][0]
    transforms = np.empty((len(database.parents), 3, 4))
    forward_kinematics(canonical_poses(database.anchor_poses[anchor:anchor + 1])[0], np.zeros(3),
                       body.shape(database.training_betas[shape]).heads, database.parents, transforms)
    back = np.empty_like(drape)
    linear_blend_skinning(unposed[anchor, shape], database.skin_indices, database.skin_weights.astype(np.float64),
                          transforms, back)
    np.testing.assert_allclose(back, drape, atol=1e-6)


def test_model_is_rest_plus_both_regressors_skinned_then_pushed(body, database, trained):
    """Per frame: T + R_G(beta) + R_L(beta, theta), skinned with beta's skeleton (the batched training-side
    predict gives the same), and with no vertex closer to its bound body vertex than the margin."""
    arrays, _ = trained
    db = replace(database, santesteban=arrays)
    model = SantestebanModel(db, body, margin=-1.0)  # a margin no vertex is under: no push
    beta = np.array([0.7, 0.6, 0.3, 0.8, 0.5, 0.5])
    model.set_shape(beta)
    pose = canonical_poses(database.anchor_poses[7:8])
    x = inputs(pose, beta[None])
    unposed = database.rest + predict(arrays.fit, x)[0] + predict(arrays.wrinkles, x)[0]
    transforms = np.empty((len(database.parents), 3, 4))
    forward_kinematics(pose[0], np.zeros(3), body.shape(beta).heads, database.parents, transforms)
    want = np.empty_like(unposed)
    linear_blend_skinning(unposed, database.skin_indices, database.skin_weights.astype(np.float64), transforms, want)
    np.testing.assert_allclose(model.synthesize(pose[0], np.zeros(3)), want, atol=2e-5)
    assert model.pushed == 0
    pushed = SantestebanModel(db, body)
    pushed.set_shape(beta)
    out = pushed.synthesize(pose[0], np.zeros(3)).astype(np.float64)
    moved = np.linalg.norm(out - want, axis=1) > 1e-6
    assert pushed.pushed == moved.sum() > 0
    assert np.isfinite(out).all()


def test_push_out_of_body_moves_along_the_normal_to_the_margin():
    """Analytic: a body vertex at the origin with normal +z under the identity transform; garment points below
    the margin end exactly at it, above it they stay."""
    transforms = np.zeros((1, 3, 4))
    transforms[0, :, :3] = np.eye(3)
    body_rest, body_normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    skin_i, skin_w = np.zeros((1, 4), dtype=np.int32), np.array([[1.0, 0.0, 0.0, 0.0]])
    garment = np.array([[0.1, 0.2, -0.03], [0.0, 0.0, 0.001], [0.3, 0.0, 0.02]])
    count = push_out_of_body(garment, np.zeros(3, dtype=np.int64), body_rest, body_normals, skin_i, skin_w,
                             transforms, 0.005)
    assert count == 2
    np.testing.assert_allclose(garment, [[0.1, 0.2, 0.005], [0.0, 0.0, 0.005], [0.3, 0.0, 0.02]], atol=1e-15)


def test_database_round_trip_select_permute_and_corruption(body, tmp_path, database, trained):
    arrays, _ = trained
    path = write_database(tmp_path / "santesteban.h5", replace(database, santesteban=arrays))
    back = read_database(path).santesteban
    for a, b in ((arrays.fit, back.fit), (arrays.wrinkles, back.wrinkles)):
        np.testing.assert_array_equal(a.dofs, b.dofs)
        np.testing.assert_array_equal(as_stored(a).basis, b.basis)
    order = np.random.default_rng(0).permutation(database.n_vertices)
    permuted = permute_vertices(read_database(path), order).santesteban
    np.testing.assert_array_equal(permuted.wrinkles.mean, back.wrinkles.mean[order])
    ids = np.arange(0, database.n_vertices, 3)
    selected = select_database(read_database(path), EngineConfig(vertices=tuple(int(i) for i in ids)))
    assert selected.santesteban.fit.mean.shape == (len(ids), 3)
    with h5py.File(path, "r+") as h5:
        dofs = h5["garment_model/santesteban/fit/dofs"]
        values = dofs[...]
        values[0] = 3 * len(database.parents) + 6  # one past the inputs
        del h5["garment_model/santesteban/fit/dofs"]
        h5["garment_model/santesteban/fit/dofs"] = values
    with pytest.raises(DatabaseError, match="garment_model/santesteban/fit/dofs"):
        read_database(path)


def test_command_trains_into_the_database_and_no_learning_library_at_run_time(tmp_path):
    path = tmp_path / "tshirt.h5"
    path.write_bytes(DATABASE.read_bytes())
    report = run_training_command("agentdress_ros.offline.santesteban", "--database", path, "--drapes", DRAPES,
                                  "--pack", PACK, "--pack-frames", 40)
    assert report["pack_frames"] == 40
    assert_no_learning_library_after(
        "import numpy as np\n"
        "from agentdress_ros.body import AnnyBody\n"
        "from agentdress_ros.engine import read_database\n"
        "from agentdress_ros.engine.santesteban import SantestebanModel\n"
        f"model = SantestebanModel(read_database({str(path)!r}), AnnyBody())\n"
        "model.set_shape([0.6, 0.6, 0.4, 0.6, 0.5, 0.5])\n"
        "assert np.isfinite(model.synthesize(np.full((31, 3), 0.2), np.zeros(3))).all()\n")


def test_parameters_select_the_model_per_garment_and_refuse_what_cannot_run():
    from agentdress_ros.ros.params import ParameterError, check_garment_config, validate

    assert validate("garment_models", ["tshirt:santesteban"]) == {"tshirt": "santesteban"}
    with pytest.raises(ParameterError, match="garment_models: tshirt: 'physics' must be one of agentdress, "
                                             "santesteban"):
        validate("garment_models", ["tshirt:physics"])
    with pytest.raises(ParameterError, match="needs a database in garment_databases"):
        check_garment_config(["tshirt"], {}, ("tshirt",), {"tshirt": "santesteban"})
    check_garment_config(["tshirt"], {"tshirt": "x.h5"}, ("tshirt",), {"tshirt": "santesteban"})


def test_a_database_without_the_group_names_the_file(tmp_path, body, database):
    from agentdress_ros.models.garment_models import GarmentDatabaseError, make_garment_model

    path = write_database(tmp_path / "plain.h5", replace(database, santesteban=None))
    with pytest.raises(GarmentDatabaseError, match=f"{path}.*garment_model/santesteban.*agentdress lab santesteban"):
        make_garment_model("tshirt", path, body=body, model="santesteban")
