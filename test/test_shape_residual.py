"""The shape residual (offline.shape_residual, EngineConfig.shape_residual): drapes at random shapes along the
training clips (`agentdress settle --start shaped`), the residual of synthesis they define, its MLP, storage and the
engine's per-frame use."""
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from agentdress_ros.offline.regressor import RegressorSettings, predict
from agentdress_ros.offline.sequences import load_sequence_pack, rest_frame_offsets
from agentdress_ros.offline.shape_residual import engine_config, residual_data, train
from agentdress_ros.engine import DatabaseError, Engine, EngineConfig, read_database, write_database
from agentdress_ros.engine.database import Regressor, write_model
from agentdress_ros.engine.engine import permute_vertices, select_database
from agentdress_ros.engine.pose_models import canonical_poses

from .conftest import assert_no_learning_library_after, run_training_command

ROOT = Path(__file__).resolve().parents[1]
DATABASE = ROOT / "data" / "trousers_default.h5"
PACK = ROOT / "data" / "trousers_sequences.npz"
TINY = RegressorSettings(components=4, hidden=(8,), alpha=1.0, max_iter=40, examples=0)
TINY_DRAPE = {"ramp_frames": 3, "max_frames": 4, "min_frames": 2}
NODE = {"pose_model": "regressor", "fold": False}


@pytest.fixture(scope="module")
def trousers_database():
    return read_database(DATABASE)


@pytest.fixture(scope="module")
def shaped(tmp_path_factory):
    """A tiny shaped pack: 3 poses draped from rest (a 3-frame ramp, 4 frames), then each at a random shape."""
    from agentdress_ros.offline.settled import settle_pack

    folder = tmp_path_factory.mktemp("shaped")
    work = folder / "rest.npz.work"
    settle_pack(DATABASE, PACK, folder / "rest.npz", 3, workers=0, progress=False, drape=TINY_DRAPE, start="rest")
    report = settle_pack(DATABASE, PACK, folder / "shaped.npz", 3, workers=0, progress=False, drape=TINY_DRAPE,
                         start="shaped", work=work, seed=4)
    return folder / "shaped.npz", work, report


def test_shaped_drapes_start_from_the_drapes_from_rest_at_random_shapes(body, trousers_database, shaped):
    """Each pose's drape from rest is draped again at a shape drawn in the training range widened by 0.05 (the
    held-out set's outside shapes lie 0.05 beyond it), warm-started from it like the held-out set's other shapes; a
    pose's shape does not depend on how many drapes from rest are finished; the pack stores each drape unposed with
    its own shape's bones."""
    from agentdress_ros.offline.jobs import DrapeStore
    from agentdress_ros.offline.settled import SHAPED_MARGIN, rest_start_jobs, shaped_jobs
    from agentdress_ros.evaluate.testset import HeldOutConfig
    from agentdress_ros.garment import make_garment

    path, work, report = shaped
    assert report["start"] == "shaped" and report["drapes"] == 3
    pack = load_sequence_pack(path)
    low, high = np.asarray(trousers_database.beta_range).T
    trained = high - low > 1e-9
    betas = pack["betas"]
    assert betas.shape == (3, 6) and len(np.unique(betas[:, trained][:, 0])) == 3
    assert (betas[:, trained] >= np.clip(low - SHAPED_MARGIN, 0, 1)[trained]).all()
    assert (betas[:, trained] <= np.clip(high + SHAPED_MARGIN, 0, 1)[trained]).all()
    beta0 = np.asarray(trousers_database.beta0)
    np.testing.assert_array_equal(betas[:, ~trained], np.repeat(beta0[None, ~trained], 3, 0))
    source = load_sequence_pack(PACK)
    rest_jobs = rest_start_jobs(source, trousers_database, np.arange(8))
    jobs = shaped_jobs(trousers_database, rest_jobs, seed=4)
    assert [j.beta.tolist() for j in shaped_jobs(trousers_database, rest_jobs[:3], seed=4)] == [j.beta.tolist()
                                                                                       for j in jobs[:3]]
    assert jobs[2].warm_key == rest_jobs[2].key and jobs[2].key == f"shaped_{rest_jobs[2].index:04d}_01"
    assert jobs[2].settings == {**trousers_database.provenance["config"]["drape"], **HeldOutConfig().warm_drape}
    store = DrapeStore(work / "drapes")
    garment = make_garment(trousers_database.garment, body, trousers_database.n_vertices)
    for n in range(3):  # the source pack's row of each drape: its clip and frame
        index = np.flatnonzero((source["clip"] == pack["clip"][n]) & (source["frame"] == pack["frame"][n]))[0]
        drape = store.load(f"shaped_{index:04d}_01")
        shape = body.shape(betas[n])
        unposed = rest_frame_offsets(body, shape, trousers_database.skin_indices, trousers_database.skin_weights,
                                     garment.rest_vertices(body, shape), [drape], [pack["rotvecs"][n]],
                                     np.zeros((1, 3)))[0].reshape(-1, 3)
        assert np.abs(unposed - pack["offsets"][n]).max() < 1e-4  # float16 PCA of 3 drapes


def test_the_target_is_what_the_engine_must_add_to_reach_the_drape(body, trousers_database, shaped):
    """A pack whose drapes are the engine's own synthesis displaced by a known rest-frame field e gives e back as
    the residual (the frame the kernel adds the blended shape delta in)."""
    from agentdress_ros.garment import make_garment

    pack = dict(load_sequence_pack(shaped[0]))
    engine = Engine(trousers_database, body, EngineConfig(**NODE))
    garment = make_garment(trousers_database.garment, body, trousers_database.n_vertices)
    field = np.random.default_rng(0).normal(0.0, 0.01, (3, trousers_database.n_vertices, 3))
    offsets = []
    for n, (pose, beta) in enumerate(zip(canonical_poses(pack["rotvecs"]), pack["betas"])):
        engine.set_shape(beta)
        engine.reset()
        synthesis = np.array(engine.synthesize(pose), dtype=np.float64)
        shape = body.shape(beta)
        unposed = rest_frame_offsets(body, shape, trousers_database.skin_indices, trousers_database.skin_weights,
                                     garment.rest_vertices(body, shape), [synthesis], [pose], np.zeros((1, 3)))[0]
        offsets.append(unposed.reshape(-1, 3) + field[n])
    pack["offsets"] = np.asarray(offsets)
    data = residual_data(trousers_database, body, pack, NODE, progress=False)
    np.testing.assert_allclose(data.positions, field, atol=2e-5)
    assert data.poses.shape == (3, 3 * len(trousers_database.bone_names) + 6)
    np.testing.assert_array_equal(data.poses[:, -6:], pack["betas"])


def test_engine_adds_the_residual_in_the_rest_frame(body, trousers_database):
    """A residual that is one constant displacement c: at the rest pose the garment moves by c, with the whole body
    turned by R it moves by R c; float32 buffers and forks included."""
    from scipy.spatial.transform import Rotation

    n_inputs = 3 * len(trousers_database.bone_names) + 6
    c = np.array([0.01, -0.02, 0.03])
    constant = Regressor(dofs=np.arange(n_inputs - 6, n_inputs, dtype=np.int32), input_mean=np.zeros(6, np.float32),
                         input_scale=np.ones(6, np.float32), weights=(np.zeros((6, 1), np.float32),),
                         biases=(np.zeros(1, np.float32),), coefficient_mean=np.zeros(1, np.float32),
                         coefficient_scale=np.ones(1, np.float32),
                         mean=np.tile(c, (trousers_database.n_vertices, 1)).astype(np.float32),
                         basis=np.zeros((1, trousers_database.n_vertices, 3), np.float32))
    db = replace(trousers_database, shape_residual=constant)
    beta = [0.7, 0.6, 0.4, 0.6, 0.3, 0.5]
    config = {**NODE, "penetration": False}
    plain, corrected = Engine(db, body, EngineConfig(**config)), Engine(db, body, EngineConfig(**config,
                                                                                              shape_residual=True))
    twin = corrected.fork()
    turn = Rotation.from_rotvec([0.0, 0.0, 0.8])
    for engine in (plain, corrected, twin):
        engine.set_shape(beta)
    for pose, moved in ((np.zeros((len(trousers_database.bone_names), 3)), c), (None, turn.apply(c))):
        if pose is None:
            pose = np.zeros((len(trousers_database.bone_names), 3))
            pose[0] = turn.as_rotvec()
        base = np.array(plain.synthesize(pose), dtype=np.float64)
        for engine in (corrected, twin):
            np.testing.assert_allclose(np.array(engine.synthesize(pose), dtype=np.float64) - base,
                                       np.tile(moved, (trousers_database.n_vertices, 1)), atol=2e-6)
    with pytest.raises(ValueError, match="shape_residual needs a database with shape_model/residual"):
        Engine(trousers_database, body, EngineConfig(shape_residual=True))
    with pytest.raises(ValueError, match="needs shape_model=True"):
        EngineConfig(shape_residual=True, shape_model=False)


def test_training_is_deterministic_and_stored_in_the_database(body, tmp_path, trousers_database, shaped):
    pack = load_sequence_pack(shaped[0])
    first, info = train(trousers_database, body, pack, NODE, TINY, folds=3, progress=False)
    again, _ = train(trousers_database, body, pack, NODE, TINY, folds=3, progress=False)
    for a, b in zip(first.weights + first.biases, again.weights + again.biases):
        np.testing.assert_array_equal(a, b)
    assert info["engine"] == NODE and info["drapes"] == 3 and len(info["fold_errors_m"]) == 3
    assert info["training_error_m"] < info["residual_before_m"]
    data = residual_data(trousers_database, body, pack, NODE, progress=False)
    assert info["training_error_m"] == pytest.approx(
        np.linalg.norm(predict(first, data.poses) - data.positions, axis=2).mean())
    path = write_database(tmp_path / "residual.h5", replace(trousers_database, shape_residual=first))
    back = read_database(path).shape_residual
    np.testing.assert_array_equal(back.dofs, first.dofs)
    assert back.info["engine"] == NODE
    order = np.random.default_rng(0).permutation(trousers_database.n_vertices)
    np.testing.assert_array_equal(permute_vertices(read_database(path), order).shape_residual.mean,
                                  back.mean[order])
    ids = tuple(int(i) for i in np.arange(0, trousers_database.n_vertices, 4))
    assert select_database(read_database(path), EngineConfig(vertices=ids)).shape_residual.basis.shape[1] == len(ids)
    with h5py.File(path, "r+") as h5:  # a new regressor pose model drops the residual of its predecessor's synthesis
        write_model(h5, "regressor", trousers_database.regressor)
    assert read_database(path).shape_residual is None
    path = write_database(tmp_path / "residual.h5", replace(trousers_database, shape_residual=first))
    with h5py.File(path, "r+") as h5:
        values = h5["shape_model/residual/dofs"][...]
        values[0] = 3 * len(trousers_database.bone_names) + 6  # one past the inputs
        del h5["shape_model/residual/dofs"]
        h5["shape_model/residual/dofs"] = values
    with pytest.raises(DatabaseError, match="shape_model/residual/dofs"):
        read_database(path)


def test_command_trains_into_the_database_and_no_learning_library_at_run_time(tmp_path, shaped):
    assert engine_config(["pose_model=regressor", "fold=false", "neighbors=3"]) == {
        "pose_model": "regressor", "fold": False, "neighbors": 3}
    path = tmp_path / "trousers.h5"
    path.write_bytes(DATABASE.read_bytes())
    report = run_training_command("agentdress_ros.offline.shape_residual", "--database", path, "--shaped", shaped[0],
                                  "--engine", "pose_model=regressor", "fold=false", "--components", 4, "--hidden", 8,
                                  "--max-iter", 30, "--ensemble", 1, "--folds", 3)
    assert report["drapes"] == 3 and report["bytes_after"] > report["bytes_before"]
    assert_no_learning_library_after(
        "import numpy as np\n"
        "from agentdress_ros.body import AnnyBody\n"
        "from agentdress_ros.engine import Engine, EngineConfig, read_database\n"
        f"engine = Engine(read_database({str(path)!r}), AnnyBody(), EngineConfig(pose_model='regressor', "
        "fold=False, shape_residual=True))\n"
        "engine.set_shape([0.6, 0.6, 0.4, 0.6, 0.5, 0.5])\n"
        "assert np.isfinite(engine.synthesize(np.full((engine.n_bones, 3), 0.2))).all()\n")


def test_the_evaluation_measures_the_residual_where_the_database_has_one(body, trousers_database):
    """A database with a residual gets a trade-table row in the configuration it was trained against, and a row
    at beta0 (where its drapes never were)."""
    from agentdress_ros.evaluate.evaluate import beta0_report, trade_rows

    rows = trade_rows(trousers_database.n_anchors, trousers_database.n_components, regressor=True,
                      shape_residual={**NODE, "shape_residual": True})
    assert rows[-1].config == {**NODE, "shape_residual": True} and "pose_model=regressor" in rows[-1].name
    assert not [r for r in trade_rows(trousers_database.n_anchors, trousers_database.n_components, regressor=True)
                if r.group == "shape residual"]
    n_inputs = 3 * len(trousers_database.bone_names) + 6
    zero = Regressor(dofs=np.arange(n_inputs - 6, n_inputs, dtype=np.int32), input_mean=np.zeros(6, np.float32),
                     input_scale=np.ones(6, np.float32), weights=(np.zeros((6, 1), np.float32),),
                     biases=(np.zeros(1, np.float32),), coefficient_mean=np.zeros(1, np.float32),
                     coefficient_scale=np.ones(1, np.float32),
                     mean=np.zeros((trousers_database.n_vertices, 3), np.float32),
                     basis=np.zeros((1, trousers_database.n_vertices, 3), np.float32), info={"engine": NODE})
    poses = canonical_poses(load_sequence_pack(PACK)["rotvecs"][:2])
    engine = Engine(trousers_database, body, EngineConfig(**NODE))
    drapes = []
    for pose in poses:
        engine.reset()  # as the report does: no decay history between static poses
        drapes.append(np.array(engine.synthesize(pose), dtype=np.float64))
    report = {r["name"]: r for r in beta0_report(replace(trousers_database, shape_residual=zero), body, poses, drapes)}
    assert report["synthesis with the shape residual"]["error_mean_cm"] < 1e-6  # a zero residual, its own synthesis
