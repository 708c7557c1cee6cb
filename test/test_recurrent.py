"""The `recurrent` pose model: a GRU over the regressor's inputs (offline.recurrent with JAX, offline), its numpy
inference with a state per model, storage."""
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from agentdress_ros.offline.recurrent import RecurrentSettings, sequences, train
from agentdress_ros.offline.regressor import predict
from agentdress_ros.offline.sequences import load_sequence_pack
from agentdress_ros.engine import DatabaseError, Engine, EngineConfig, read_database, write_database
from agentdress_ros.engine.pose_models import JUMP_RAD, canonical_poses

from .conftest import assert_no_learning_library_after, run_training_command

ROOT = Path(__file__).resolve().parents[1]
DATABASE = ROOT / "data" / "tshirt_default.h5"
PACK = ROOT / "data" / "tshirt_sequences.npz"
TINY = RecurrentSettings(hidden=8, window=20, burn_in=5, batch=8, steps=25, seed=2)


@pytest.fixture(scope="module")
def runs(database):
    return sequences(load_sequence_pack(PACK), database, 0.5)[:3]


@pytest.fixture(scope="module")
def trained(database, runs):
    return train(database, runs, TINY, progress=False)


def _engine(db, body, **config):
    return Engine(db, body, EngineConfig(pose_model="recurrent", shape_model=False, dtype="float64", **config))


def test_sequences_are_runs_of_consecutive_frames_without_a_lost_garment(database, runs):
    pack = load_sequence_pack(PACK)
    every = sequences(pack, database, 0.5)
    assert sum(len(p) for p, _ in every) == int((np.linalg.norm(pack["offsets"], axis=2).max(axis=1) <= 0.5).sum())
    assert all(len(p) == len(g) and g.shape[1:] == (database.n_vertices, 3) for p, g in every)


def test_training_is_deterministic_and_starts_from_the_static_regressor(database, runs, trained):
    recurrent, report = trained
    again, _ = train(database, runs, TINY, progress=False)
    for name in ("input_weights", "state_weights", "bias", "output_weights", "output_bias"):
        np.testing.assert_array_equal(getattr(recurrent, name), getattr(again, name))
    assert recurrent.hidden == 8 and report["windows"] > 0
    assert report["recurrent_rms"] < report["static_rms"]  # it learned something on its own training windows


def test_a_zero_output_layer_is_the_static_regressor_exactly(body, database, trained):
    silent = replace(trained[0], output_weights=np.zeros_like(trained[0].output_weights),
                     output_bias=np.zeros_like(trained[0].output_bias))
    engine = _engine(replace(database, recurrent=silent), body)
    poses = canonical_poses(database.example_poses[:4])
    for pose, want in zip(poses, predict(database.regressor, poses)):
        out = np.empty_like(want)
        out[engine.order] = engine.pose_model.evaluate(pose, np.zeros(3), None).T
        np.testing.assert_allclose(out, want, atol=1e-9)


def test_state_restarts_on_reset_and_on_a_pose_jump_and_forks_keep_their_own(body, database, runs, trained):
    engine = _engine(replace(database, recurrent=trained[0]), body)
    poses = runs[0][0][:12]
    first = [engine.pose_model.evaluate(p, np.zeros(3), None).copy() for p in poses]
    assert np.abs(first[-1] - first[0]).max() > 0  # the state and the pose moved it
    engine.reset()
    again = [engine.pose_model.evaluate(p, np.zeros(3), None).copy() for p in poses]
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    # a jump larger than JUMP_RAD restarts the state: the jumped-to pose reads as a fresh start
    jumped = poses[0] + np.where(np.arange(poses[0].size).reshape(poses[0].shape) == 30, 1.5 * JUMP_RAD, 0.0)
    fresh = _engine(replace(database, recurrent=trained[0]), body)
    want = fresh.pose_model.evaluate(jumped, np.zeros(3), None).copy()
    np.testing.assert_array_equal(engine.pose_model.evaluate(jumped, np.zeros(3), None), want)
    fork = engine.fork()
    fork_out = [fork.pose_model.evaluate(p, np.zeros(3), None).copy() for p in poses]
    np.testing.assert_array_equal(np.asarray(fork_out), np.asarray(first))  # its own state, from zero
    # a clone (the node's shape refit) continues the state where it was taken, and leaves the original's alone
    engine.reset()
    for p in poses[:6]:
        engine.pose_model.evaluate(p, np.zeros(3), None)
    clone = engine.clone()
    for k in range(6, len(poses)):
        np.testing.assert_array_equal(clone.pose_model.evaluate(poses[k], np.zeros(3), None), first[k])
    np.testing.assert_array_equal(engine.pose_model.evaluate(poses[6], np.zeros(3), None), first[6])


def test_database_round_trip_and_a_wrong_shape_named(tmp_path, database, trained):
    path = write_database(tmp_path / "recurrent.h5", replace(database, recurrent=trained[0]))
    back = read_database(path).recurrent
    np.testing.assert_array_equal(back.state_weights, trained[0].state_weights)
    assert back.info["windows"] == trained[1]["windows"]
    with h5py.File(path, "r+") as h5:
        del h5["pose_model/recurrent/output_bias"]
        h5["pose_model/recurrent/output_bias"] = np.zeros(3, dtype=np.float32)
    with pytest.raises(DatabaseError, match="pose_model/recurrent/output_bias.*expected"):
        read_database(path)


def test_command_trains_into_the_database_and_no_learning_library_at_run_time(tmp_path):
    path = tmp_path / "tshirt.h5"
    path.write_bytes(DATABASE.read_bytes())
    report = run_training_command("agentdress_ros.offline.recurrent", "--database", path, "--pack", PACK, "--steps", 20,
                                  "--hidden", 8)
    assert report["settings"]["steps"] == 20
    assert_no_learning_library_after(
        "import numpy as np\n"
        "from agentdress_ros.body import AnnyBody\n"
        "from agentdress_ros.engine import Engine, EngineConfig, read_database\n"
        f"engine = Engine(read_database({str(path)!r}), AnnyBody(), EngineConfig(pose_model='recurrent'))\n"
        "for k in range(3):\n"
        "    out = engine.synthesize(np.full((31, 3), 0.1 * k))\n"
        "assert np.isfinite(out).all()\n")
