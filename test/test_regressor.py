"""The `regressor` pose model: training (scikit-learn, offline), numpy inference, the anchor fold, storage."""
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from agentdress_ros.offline.regressor import (RegressorSettings, TrainingData, add_network_arguments, clip_folds,
                                            coefficients_of, example_data, fit, model_inputs, network_settings,
                                            pack_data, pose_dofs, predict, region_parts, store_regressor,
                                            train_database_regressor, validate_example_copies, vertex_error)
from agentdress_ros.offline.sequences import load_sequence_pack
from agentdress_ros.engine import DatabaseError, Engine, EngineConfig, read_database, write_database
from agentdress_ros.engine.config import EngineKnobs
from agentdress_ros.engine.database import as_stored
from agentdress_ros.engine.engine import permute_vertices, select_database
from agentdress_ros.engine.pose_models import INPUT_CLIP, RegressorDecoder

ROOT = Path(__file__).resolve().parents[1]
DATABASE = ROOT / "data" / "tshirt_default.h5"
PACK = ROOT / "data" / "tshirt_sequences.npz"
TINY = RegressorSettings(components=6, hidden=(12,), alpha=1.0, examples=0, max_iter=40, seed=3)


@pytest.fixture(scope="module")
def frames(database):
    """Every 8th frame of three clips of the shipped T-shirt pack."""
    data = pack_data(load_sequence_pack(PACK), database)
    keep = np.flatnonzero(np.isin(data.groups, np.unique(data.groups)[:3]))[::8]
    return data.rows(keep)


@pytest.fixture(scope="module")
def trained(database, frames):
    regressor, (mlp,) = fit(frames, pose_dofs(database, "all"), TINY)
    return regressor, mlp


def test_numpy_inference_equals_the_sklearn_model(body, database, frames, trained):
    regressor, mlp = trained
    x = (frames.poses.reshape(len(frames.poses), -1)[:, regressor.dofs] - regressor.input_mean) / regressor.input_scale
    x = np.clip(x, -INPUT_CLIP, INPUT_CLIP)
    expected = (mlp.predict(x) * regressor.coefficient_scale) @ regressor.basis.reshape(len(regressor.basis), -1)
    expected = expected.reshape(frames.positions.shape) + regressor.mean
    np.testing.assert_allclose(predict(regressor, frames.poses), expected, atol=2e-5)
    # the engine's per-frame path (internal vertex order, float64 buffers) gives the same rest-frame garment
    engine = Engine(replace(database, regressor=regressor), body, EngineConfig(pose_model="regressor",
                                                                                  dtype="float64"))
    assert engine.pose_model.decoder.blocks is None  # one MLP of the whole garment: one dense product
    for pose, want in zip(frames.poses[:3], expected[:3]):
        out = np.empty_like(want)
        out[engine.order] = engine.pose_model.evaluate(pose, np.zeros(3), None).T
        np.testing.assert_allclose(out, want, atol=2e-5)


@pytest.mark.parametrize("hidden", [(12,), (12, 8)])
def test_an_ensemble_is_stored_as_one_mlp_whose_output_is_the_members_mean(database, frames, hidden):
    settings = replace(TINY, hidden=hidden, ensemble=3)
    regressor, mlps = fit(frames, pose_dofs(database, "all"), settings)
    assert len(mlps) == 3 and [m.random_state for m in mlps] == [3, 4, 5]
    assert [w.shape[1] for w in regressor.weights[:-1]] == [3 * h for h in hidden]
    x = np.clip((frames.poses.reshape(len(frames.poses), -1)[:, regressor.dofs] - regressor.input_mean)
                / regressor.input_scale, -INPUT_CLIP, INPUT_CLIP)
    mean_output = np.mean([m.predict(x) for m in mlps], axis=0)
    expected = (mean_output * regressor.coefficient_scale) @ regressor.basis.reshape(len(regressor.basis), -1)
    np.testing.assert_allclose(predict(regressor, frames.poses), expected.reshape(frames.positions.shape)
                               + regressor.mean, atol=2e-5)


def test_region_parts_cover_the_garment_with_blend_weights_summing_to_one(database):
    parts = region_parts(database)
    total = np.zeros(database.n_vertices)
    for part in parts:
        total[part.vertices] += part.blend
        assert (part.blend > 0).all() and len(part.vertices) >= 20
    np.testing.assert_allclose(total, 1.0, atol=1e-12)
    # the T-shirt's two forearm regions hold 5-6 vertices each: too few for a model, their vertices blend the rest
    assert len(parts) == len(database.region_names) - 2
    torso = np.asarray(database.region_dof)[database.region_names.index("torso")]
    np.testing.assert_array_equal(parts[0].dofs, np.flatnonzero(torso > 0))
    # a region left out whose vertex belongs to no other joins its nearest covered vertex's parts
    regions = np.array(database.regions)
    lonely = int(np.flatnonzero(regions[:, 1] > 0)[0])
    regions[lonely] = 0.0
    regions[lonely, 2] = 1.0  # only in the left forearm, which keeps too few vertices
    total = np.zeros(database.n_vertices)
    for part in region_parts(replace(database, regions=regions)):
        total[part.vertices] += part.blend
    assert total[lonely] == pytest.approx(1.0)


def test_a_parts_regressor_is_its_parts_blended_and_the_engine_skips_the_zeros(body, database, frames):
    """One Regressor equal to sum_p blend_p member_p, each member fitted on its region's vertices and dofs; the
    engine's decoder finds the blocks again from the zeros and gives the same garment, and forks keep their own
    buffers."""
    settings = replace(TINY, parts=True, ensemble=2)
    parts = model_inputs(database, settings)
    regressor, _ = fit(frames, parts, settings)
    assert regressor.info["settings"]["parts"] and len(regressor.info["parts"]) == len(parts)
    poses = frames.poses[:4]
    expected = np.zeros((len(poses), database.n_vertices, 3))
    for part in parts:
        member, _ = fit(TrainingData(frames.poses, frames.positions[:, part.vertices], frames.groups), part.dofs,
                        replace(settings, parts=False))
        expected[:, part.vertices] += part.blend[None, :, None] * predict(member, poses)
    np.testing.assert_allclose(predict(regressor, poses), expected, atol=1e-6)  # float32 arrays, blended
    decoder = RegressorDecoder(regressor)
    assert len(decoder.blocks.rows) == len(parts)
    for pose, want in zip(poses, expected):
        np.testing.assert_allclose(decoder.decode(pose).T, want, atol=1e-6)
    twin = decoder.fork()
    mine = decoder.decode(poses[1])
    np.testing.assert_allclose(twin.decode(poses[0]).T, expected[0], atol=1e-6)
    np.testing.assert_allclose(mine.T, expected[1], atol=1e-6)  # the twin's frame left this one's buffers alone
    # the coefficients that restore a garment are found by least squares, the parts' bases overlapping
    coefficients = coefficients_of(regressor, expected)
    restored = coefficients @ regressor.basis.reshape(len(regressor.basis), -1) + regressor.mean.reshape(-1)
    np.testing.assert_allclose(restored.reshape(expected.shape), expected, atol=1e-6)
    # through the database file (float16 weights) and the engine: the same to well under a millimetre
    engine = Engine(replace(database, regressor=as_stored(regressor)), body,
                    EngineConfig(pose_model="regressor", shape_model=False, dtype="float32"))
    out = np.empty((database.n_vertices, 3))
    out[engine.order] = engine.pose_model.evaluate(poses[1], np.zeros(3), None).T
    assert np.abs(out - expected[1]).max() < 2e-4


def test_inputs_that_training_held_still_are_dropped_and_far_inputs_clipped(database, frames, trained):
    """A dof (nearly) constant in the training frames is not an input; a pose far outside the training range gives
    the prediction at INPUT_CLIP standard deviations, not an extrapolation (a retarget to another body moves dofs
    held still at beta0)."""
    still = np.array(frames.poses)
    still[:, 5] = 0.3 + 1e-4 * np.sin(np.arange(len(still)))[:, None]  # bone 5 held (all but) still
    regressor, _ = fit(TrainingData(still, frames.positions, frames.groups), pose_dofs(database, "all"), TINY)
    assert not np.isin(np.arange(15, 18), regressor.dofs).any()
    assert np.isin(pose_dofs(database, "all"), regressor.dofs).sum() == len(regressor.dofs) > 0
    regressor = trained[0]
    dof = int(regressor.dofs[0])
    pose = np.array(frames.poses[:1])
    edge, beyond = pose.copy(), pose.copy()
    flat_edge, flat_beyond = edge.reshape(1, -1), beyond.reshape(1, -1)
    flat_edge[0, dof] = regressor.input_mean[0] + 1.01 * INPUT_CLIP * regressor.input_scale[0]
    flat_beyond[0, dof] = regressor.input_mean[0] + 30 * regressor.input_scale[0]
    np.testing.assert_array_equal(predict(regressor, beyond), predict(regressor, edge))


def test_training_is_deterministic_given_its_seed(database, frames, trained):
    again, _ = fit(frames, pose_dofs(database, "all"), TINY)
    for a, b in zip(trained[0].weights + trained[0].biases, again.weights + again.biases):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(trained[0].basis, again.basis)


def test_fold_makes_synthesis_exact_at_an_anchor(body, database, trained):
    """At an anchor's pose and beta0, synthesis returns the anchor's beta0 drape whatever the pose model's error;
    at another shape the result does not depend on the (folded) pose model at all."""
    db = replace(database, regressor=trained[0])
    second, _ = fit(_frames_of(database, 1), pose_dofs(database, "sensitive"), replace(TINY, seed=4))
    config = dict(pose_model="regressor", dtype="float64", penetration=False, decay=False)
    anchor = 3
    drape = db.example_drapes[np.flatnonzero(np.abs(db.example_poses - db.anchor_poses[anchor]).max(axis=(1, 2))
                                              <= 1e-6)[0]]
    pose = db.anchor_poses[anchor].astype(np.float64)
    folded = Engine(db, body, EngineConfig(**config))
    unfolded = Engine(db, body, EngineConfig(**config, fold=False))
    error = np.linalg.norm(folded.synthesize(pose) - drape, axis=1)
    error_unfolded = np.linalg.norm(unfolded.synthesize(pose) - drape, axis=1)
    assert error.max() < 1e-4 < error_unfolded.mean()
    other = Engine(replace(database, regressor=second), body, EngineConfig(**config))
    beta = np.asarray(db.beta0) + np.array([0.2, 0, 0.1, -0.1, 0, 0])
    folded.set_shape(beta)
    other.set_shape(beta)
    np.testing.assert_allclose(folded.synthesize(pose), other.synthesize(pose), atol=1e-4)


def test_a_fork_takes_another_pose_model_only_without_the_fold(body, database, trained):
    """A level of detail may run a cheaper pose model: a fork of a regressor engine without the fold, set to
    `examples`, is the examples engine at any shape; with the fold the fork is refused (the shape state holds the
    regressor's residuals), and the scene then keeps the agent's pose model at every tier."""
    from agentdress_ros.scene import AgentSpec, GarmentSpec, Scene, SceneConfig

    db = replace(database, regressor=trained[0])
    config = dict(dtype="float64", penetration=False, decay=False)
    parent = Engine(db, body, EngineConfig(pose_model="regressor", fold=False, **config))
    examples = Engine(db, body, EngineConfig(pose_model="examples", **config))
    beta = np.asarray(db.beta0) + np.array([0.2, 0, 0.1, -0.1, 0, 0])
    parent.set_shape(beta)
    examples.set_shape(beta)
    fork = parent.fork(pose_model="examples")
    second = parent.fork(pose_model="examples")
    assert second.pose_model.canonical is fork.pose_model.canonical  # loaded once, shared
    pose = db.anchor_poses[5] * 0.7
    np.testing.assert_allclose(fork.synthesize(pose), examples.synthesize(pose), atol=1e-9)
    assert np.abs(parent.synthesize(pose) - examples.synthesize(pose)).max() > 1e-3
    folded = Engine(db, body, EngineConfig(pose_model="regressor", **config))
    with pytest.raises(ValueError, match="fold"):
        folded.fork(pose_model="examples")

    scene = Scene(body, SceneConfig(lod_enabled=False, budget_ms=0.0))
    try:
        spec = GarmentSpec("tshirt", database=str(DATABASE), engine=EngineKnobs.of(fold=True, pose_model="regressor"))
        agent = scene.build_agent(AgentSpec("folds", (spec,), tuple(db.beta0)))
        levels = agent.garments["tshirt"]._levels
        assert levels[1][0] == "synthesis" and levels[1][1].pose_model.name == "regressor"
        spec = GarmentSpec("tshirt", database=str(DATABASE), engine=EngineKnobs.of(fold=False, pose_model="regressor"))
        agent = scene.build_agent(AgentSpec("unfolded", (spec,), tuple(db.beta0)))
        assert agent.garments["tshirt"]._levels[1][1].pose_model.name == "examples"
    finally:
        scene.stop()


def test_database_round_trip_select_and_permute(body, tmp_path, database, trained):
    regressor = trained[0]
    path = write_database(tmp_path / "db.h5", replace(database, recurrent=None, regressor=regressor))
    back = read_database(path).regressor
    stored = as_stored(regressor)  # weights and basis kept as float16
    for a, b in zip((stored.dofs, stored.mean, stored.basis, *stored.weights, *stored.biases),
                    (back.dofs, back.mean, back.basis, *back.weights, *back.biases)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert back.activation == regressor.activation and back.info == regressor.info
    db = read_database(path)
    ids = np.arange(0, db.n_vertices, 7)
    sub = select_database(db, EngineConfig(vertices=ids))
    np.testing.assert_array_equal(sub.regressor.basis, back.basis[:, ids])
    order = np.random.default_rng(0).permutation(db.n_vertices)
    np.testing.assert_array_equal(permute_vertices(db, order).regressor.mean, regressor.mean[order])
    np.testing.assert_array_equal(permute_vertices(db, order).regressor.basis, back.basis[:, order])
    # a level of detail outputs the full engine's vertices (pose model alone, no blend across vertices)
    pose = db.anchor_poses[1].astype(np.float64) * 0.7
    config = dict(pose_model="regressor", shape_model=False, dtype="float64")
    full = Engine(db, body, EngineConfig(**config)).synthesize(pose)
    part = Engine(db, body, EngineConfig(**config, vertices=ids)).synthesize(pose)
    np.testing.assert_allclose(part, full[ids], atol=1e-9)


@pytest.mark.parametrize("mutate, field", [
    (lambda g: g["layer_00/weights"].__setitem__((0, 0), np.nan), "pose_model/regressor/layer_00/weights"),
    (lambda g: _swap(g, "basis", np.zeros((2, 5, 3), np.float32)), "pose_model/regressor/basis"),
    (lambda g: _swap(g, "dofs", np.r_[g["dofs"][:1], g["dofs"][:-1]]), "pose_model/regressor/dofs"),
    (lambda g: _swap(g, "dofs", np.array([3, 4, 5], np.int32)), "pose_model/regressor/input_mean"),
    (lambda g: _swap(g, "input_scale", -np.ones(g["input_scale"].shape, np.float32)),
     "pose_model/regressor/input_scale"),
    (lambda g: g.attrs.__setitem__("activation", "sigmoid"), "pose_model/regressor/activation"),
    (lambda g: g.attrs.__setitem__("layers", 3), "pose_model/regressor/layer_02/weights"),
    (lambda g: g.attrs.__setitem__("info", "{not json"), "pose_model/regressor/info"),
])
def test_corrupt_regressor_group_names_file_and_field(tmp_path, database, trained, mutate, field):
    path = write_database(tmp_path / "db.h5", replace(database, recurrent=None, regressor=trained[0]))
    with h5py.File(path, "r+") as h5:
        mutate(h5["pose_model/regressor"])
    with pytest.raises(DatabaseError) as error:
        read_database(path)
    assert str(path) in str(error.value) and field in str(error.value), str(error.value)


def test_training_refuses_test_clips_and_holds_out_whole_clips(database):
    pack = load_sequence_pack(PACK)
    pack["clips"] = np.array(["02_01"] + [str(c) for c in pack["clips"][1:]])
    with pytest.raises(ValueError, match="02_01"):
        pack_data(pack, database)
    folds = clip_folds(["a", "b", "c", "d", "e"], 3)
    assert sorted(sum(folds, [])) == ["a", "b", "c", "d", "e"] and len(folds) == 3


def test_the_network_options_read_back_as_settings():
    import argparse

    parser = argparse.ArgumentParser()
    add_network_arguments(parser)
    assert network_settings(parser.parse_args([])) == RegressorSettings()
    changed = network_settings(parser.parse_args(["--alpha", "1", "--examples", "2", "--hidden", "64", "32"]))
    assert changed == replace(RegressorSettings(), alpha=1.0, examples=2, hidden=(64, 32))


def test_frames_that_lost_the_garment_are_left_out(database):
    """max_offset leaves out exactly the frames with a vertex further than it from its skinned place."""
    pack = load_sequence_pack(PACK)
    largest = np.linalg.norm(pack["offsets"], axis=2).max(axis=1)
    cut = float(np.percentile(largest, 90))
    kept = pack_data(pack, database, max_offset=cut)
    assert len(kept.poses) == int((largest <= cut).sum()) < len(largest)
    assert np.abs(kept.positions - np.asarray(pack["rest"], np.float64)).max() <= cut + 1e-6
    assert len(pack_data(pack, database).poses) == len(largest)


def test_copies_of_the_static_drapes_are_validated_on_drapes_held_out_of_training(database, frames):
    """Each count of copies is scored on halves of the beta0 drapes that its fits never saw: with no copies the
    score is the frames-only model's error on those drapes, and adding the other half moves the model towards them."""
    examples = example_data(database)
    dofs = pose_dofs(database, "all")
    rows = validate_example_copies(frames, examples, dofs, TINY, [0, 20], folds=2)
    assert [r["copies"] for r in rows] == [0, 20] and all(len(r["fold_errors_m"]) == 2 for r in rows)
    frames_only, _ = fit(frames, dofs, TINY)
    half = np.array_split(np.random.default_rng(TINY.seed).permutation(len(examples.poses)), 2)[0]
    assert rows[0]["fold_errors_m"][0] == pytest.approx(
        vertex_error(predict(frames_only, examples.poses[half]), examples.positions[half]))
    assert rows[1]["validation_error_m"] < rows[0]["validation_error_m"]


def test_settled_drapes_come_from_the_training_frames_and_join_the_regressor_data(tmp_path, database):
    """`agentdress settle`: frames of the sequence pack settle into static drapes with the body held still, starting
    where the dynamic simulation left the cloth (nothing lifted out); their pack reads like a sequence pack and
    `agentdress regressor --settled` trains on copies of them under their source clips. A rerun drapes nothing."""
    from agentdress_ros.offline.jobs import DrapeStore
    from agentdress_ros.offline.regressor import training_frames, training_key
    from agentdress_ros.offline.settled import settle_pack

    out = tmp_path / "settled.npz"
    report = settle_pack(DATABASE, PACK, out, 2, workers=0, progress=False, drape={"max_frames": 12, "min_frames": 4})
    assert report["drapes"] == 2 and report["clips"] == 2 and report["rest_frame_error_mean_m"] < 1e-4
    source, settled = load_sequence_pack(PACK), load_sequence_pack(out)
    picked = [0, len(source["rotvecs"]) - 1]  # two frames spread over the pack: its first and last
    np.testing.assert_array_equal(settled["rotvecs"], source["rotvecs"][picked])
    assert [str(settled["clips"][c]) for c in settled["clip"]] == [str(source["clips"][c]) for c in source["clip"][picked]]
    assert not settled["cloth_speed"].any() and not settled["root_velocity"].any()
    store = DrapeStore(tmp_path / "settled.npz.work" / "drapes")
    stats = [store.stats(f"settled_{f:04d}_00") for f in picked]
    assert all(s["ramp_frames"] == 1 and s["pushed_out"] == 0 and 0 < s["displacement_mean"] < 0.05 for s in stats)
    # the stored offsets are the drapes unposed with beta0's bones (up to the pack's float16 coefficients)
    data = pack_data(settled, database)
    assert np.abs(data.positions - (settled["rest"] + settled["offsets"])).max() < 1e-6
    moved = np.linalg.norm(settled["offsets"] - source["offsets"][picked], axis=2).mean(axis=1)
    np.testing.assert_allclose(moved, [s["displacement_mean"] for s in stats], rtol=0.5)  # unposing keeps lengths
    mtime = out.stat().st_mtime_ns
    again = settle_pack(DATABASE, PACK, out, 2, workers=0, progress=False, drape={"max_frames": 12, "min_frames": 4})
    assert again["cpu_seconds"] == report["cpu_seconds"] and out.stat().st_mtime_ns >= mtime
    # --partial packs what another run's folder holds so far, draping nothing: here all of it
    partial = settle_pack(DATABASE, PACK, tmp_path / "so_far.npz", 3, workers=0, progress=False, partial=True,
                          work=tmp_path / "settled.npz.work")
    assert partial["drapes"] == 2 and partial["cpu_seconds"] == report["cpu_seconds"]
    so_far = load_sequence_pack(tmp_path / "so_far.npz")  # each drape beside its own pose, not the frames asked for
    np.testing.assert_array_equal(so_far["rotvecs"], settled["rotvecs"])
    np.testing.assert_array_equal(so_far["frame"], settled["frame"])
    settings = replace(TINY, settled_copies=3)
    frames, _ = training_frames(PACK, database, settings, out)
    plain, _ = training_frames(PACK, database, TINY, out)  # no copies asked: the settled pack is not read
    assert len(frames.poses) == len(plain.poses) + 3 * 2
    np.testing.assert_array_equal(frames.groups[-2:], data.groups)
    assert training_key(PACK, database, settings, out) != training_key(PACK, database, TINY, out)
    assert training_key(PACK, database, TINY, out) == training_key(PACK, database, TINY)
    static = replace(settings, dynamic=False)  # the static drapes only: no dynamic frame, the pack not read
    only, dropped = training_frames(tmp_path / "absent.npz", database, static, out)
    assert len(only.poses) == 3 * 2 and dropped == 0  # neither tiny drape strays
    assert training_key(tmp_path / "absent.npz", database, static, out) not in (
        training_key(PACK, database, settings, out), training_key(PACK, database, TINY))
    with pytest.raises(ValueError, match="static drapes only"):
        training_frames(PACK, database, replace(TINY, dynamic=False))


def test_drapes_from_rest_are_draped_like_the_anchors_in_a_spread_order(tmp_path, database):
    """`agentdress settle --start rest`: the pack frames' poses draped the way the anchors and the held-out set are
    (the garment at rest on the body at rest, carried into the pose by the animated collider, the database's drape
    settings), in an order whose every prefix is spread over the frames."""
    from agentdress_ros.offline.jobs import DrapeStore
    from agentdress_ros.offline.settled import rest_start_jobs, settle_pack, spread_order

    assert spread_order(8).tolist() == [0, 4, 2, 6, 1, 5, 3, 7]
    assert sorted(spread_order(13).tolist()) == list(range(13)) and spread_order(1).tolist() == [0]
    source = load_sequence_pack(PACK)
    jobs = rest_start_jobs(source, database, [5])
    assert jobs[0].settings == database.provenance["config"]["drape"] and not jobs[0].warm_key
    assert jobs[0].settings["ramp_frames"] == 30
    out = tmp_path / "rest.npz"
    tiny = {"ramp_frames": 3, "max_frames": 4, "min_frames": 2}
    report = settle_pack(DATABASE, PACK, out, 3, workers=0, progress=False, drape=tiny, start="rest")
    picked = [0, len(source["rotvecs"]) - 1, (len(source["rotvecs"]) - 1) // 2]  # spread frames, in spread order
    assert report["start"] == "rest" and report["drapes"] == 3 and "moved_from_rest_mean_m" in report
    rest = load_sequence_pack(out)
    np.testing.assert_array_equal(rest["rotvecs"], source["rotvecs"][picked])
    np.testing.assert_array_equal(rest["frame"], source["frame"][picked])
    stats = [DrapeStore(tmp_path / "rest.npz.work" / "drapes").stats(f"rest_{f:04d}_00") for f in picked]
    assert all(s["ramp_frames"] == 3 and s["pushed_out"] == 0 for s in stats)
    # more drapes later: 2n - 1 frames beside a pack of n settle the n - 1 halfway between, none of the n again,
    # and the regressor trains on both packs
    from agentdress_ros.offline.regressor import training_frames, training_key

    between = settle_pack(DATABASE, PACK, tmp_path / "between.npz", 5, workers=0, progress=False, drape=tiny,
                          start="rest", skip=out)
    halfway = load_sequence_pack(tmp_path / "between.npz")
    last = len(source["rotvecs"]) - 1
    assert between["drapes"] == 2
    assert sorted(halfway["frame"].tolist()) == sorted(source["frame"][[round(last / 4), round(3 * last / 4)]].tolist())
    settings = replace(TINY, settled_copies=1, dynamic=False)
    both, _ = training_frames(PACK, database, settings, [out, tmp_path / "between.npz"])
    assert len(both.poses) == 5
    assert training_key(PACK, database, settings, [out]) == training_key(PACK, database, settings, out)
    assert training_key(PACK, database, settings, [out, tmp_path / "between.npz"]) != training_key(
        PACK, database, settings, out)
    with pytest.raises(ValueError, match="start must be"):
        settle_pack(DATABASE, PACK, out, 3, workers=0, progress=False, start="moving")


def test_novel_frames_go_where_the_training_poses_are_sparsest(tmp_path, database, body):
    """--select novel: greedy farthest-point sampling in the regressor's standardised pose inputs. The first pick is
    the pack frame farthest from the covered poses and their mirror images (checked by brute force), each pick is
    no nearer than the next, a pose already covered is never picked, and the settled pack holds the picks."""
    from agentdress_ros.offline.mirror import bone_twins, mirrored_poses
    from agentdress_ros.offline.regressor import standardized_inputs
    from agentdress_ros.offline.settled import novel_frames, settle_pack
    from agentdress_ros.engine.pose_models import canonical_poses

    pack = load_sequence_pack(PACK)
    covered = np.asarray(database.example_poses)
    picks, distances = novel_frames(pack, database, body, covered, 4)
    assert len(set(picks.tolist())) == 4 and np.all(np.diff(distances) <= 0)
    inputs = lambda poses: standardized_inputs(database.regressor, canonical_poses(poses))
    known = np.concatenate([inputs(covered), inputs(mirrored_poses(canonical_poses(covered),
                                                                   bone_twins(body.bone_names)))])
    candidates = inputs(pack["rotvecs"])
    nearest = np.linalg.norm(candidates[:, None] - known[None], axis=2).min(axis=1)
    assert picks[0] == nearest.argmax() and distances[0] == pytest.approx(nearest.max())
    again, _ = novel_frames(pack, database, body, np.concatenate([covered, pack["rotvecs"][picks]]), 4)
    assert not set(again.tolist()) & set(picks.tolist())
    assert len(novel_frames(pack, database, body, pack["rotvecs"], 3)[0]) == 0  # everything covered: nothing new
    tiny = {"ramp_frames": 3, "max_frames": 4, "min_frames": 2}
    report = settle_pack(DATABASE, PACK, tmp_path / "novel.npz", 2, workers=0, progress=False, drape=tiny,
                         start="rest", select="novel")
    settled = load_sequence_pack(tmp_path / "novel.npz")
    assert report["select"] == "novel" and report["drapes"] == 2
    np.testing.assert_array_equal(settled["frame"], pack["frame"][picks[:2]])
    with pytest.raises(ValueError, match="select must be"):
        settle_pack(DATABASE, PACK, tmp_path / "x.npz", 2, workers=0, progress=False, select="random")


def test_drapes_from_rest_of_another_garment_at_the_packs_poses(tmp_path):
    """A garment without a sequence pack of its own (the long sleeve) is draped from rest at the poses of another
    garment's pack: the pack written is the database's garment (its vertices, faces and rest), and the drapes come
    back from its rest-frame offsets. Settling from the pack's own cloth needs the pack's garment: refused by name."""
    from agentdress_ros.offline.jobs import DrapeStore
    from agentdress_ros.offline.settled import settle_pack
    from agentdress_ros.engine import read_database

    sleeve_path = ROOT / "data" / "longsleeve_default.h5"
    sleeve = read_database(sleeve_path)
    assert sleeve.n_vertices != load_sequence_pack(PACK)["garment_vertices"]
    out = tmp_path / "sleeve_rest.npz"
    tiny = {"ramp_frames": 3, "max_frames": 4, "min_frames": 2}
    report = settle_pack(sleeve_path, PACK, out, 2, workers=0, progress=False, drape=tiny, start="rest",
                         components=2)
    packed = load_sequence_pack(out)
    assert report["drapes"] == 2 and str(packed["garment"]) == sleeve.garment
    assert packed["rest"].shape == (sleeve.n_vertices, 3)
    np.testing.assert_array_equal(packed["faces"], sleeve.faces)
    np.testing.assert_allclose(packed["rest"], sleeve.rest, atol=1e-6)
    assert report["rest_frame_error_mean_m"] < 1e-4  # 2 drapes, 2 components: exact up to the float16 storage
    assert DrapeStore(tmp_path / "sleeve_rest.npz.work" / "drapes").load("rest_0000_00").shape == (sleeve.n_vertices, 3)
    with pytest.raises(ValueError, match="longsleeve_default.h5"):
        settle_pack(sleeve_path, PACK, tmp_path / "dynamic.npz", 2, workers=0, progress=False)


def test_validation_on_held_out_clips_static_drapes_weighs_their_copies(database, frames):
    """--validate-settled: each fold trains on the other clips' frames and static drapes (count copies) and scores
    the held-out clips' static drapes; 0 copies is the model without them."""
    from agentdress_ros.offline.regressor import validate_settled_copies

    dofs = pose_dofs(database, "sensitive")
    clips = np.unique(frames.groups)
    settled = frames.rows(np.arange(0, len(frames.poses), 5))  # stand-ins: a few frames per clip, shifted by 2 cm
    settled = TrainingData(settled.poses, settled.positions + np.array([0.0, 0.0, 0.02]), settled.groups)
    rows = validate_settled_copies(frames, settled, None, dofs, TINY, [0, 4], folds=3)
    assert [r["copies"] for r in rows] == [0, 4] and all(len(r["fold_errors_m"]) == len(clips) for r in rows)
    held = settled.groups == sorted(clips)[0]
    alone, _ = fit(frames.rows(frames.groups != sorted(clips)[0]), dofs, TINY)
    assert rows[0]["fold_errors_m"][0] == pytest.approx(
        vertex_error(predict(alone, settled.poses[held]), settled.positions[held]))
    assert rows[1]["validation_error_m"] < rows[0]["validation_error_m"]  # the copies carry the shift
    only = validate_settled_copies(None, settled, None, dofs, TINY, [4], folds=3)  # static drapes only
    assert not only[0]["dynamic"] and rows[0]["dynamic"] and len(only[0]["fold_errors_m"]) == len(clips)


def test_command_writes_the_group_once_and_no_learning_library_at_run_time(tmp_path, database):
    """Training into a database is idempotent; a frame with the stored regressor imports no sklearn/torch/jax."""
    path = write_database(tmp_path / "db.h5", database)
    pack = tmp_path / "pack.npz"
    with np.load(PACK) as data:
        arrays = {name: data[name] for name in data.files}
    keep = np.isin(arrays["clip"], [0, 1, 2]) & (np.arange(len(arrays["clip"])) % 6 == 0)
    for name in ("coefficients", "rotvecs", "root_translation", "root_velocity", "cloth_speed", "body_speed", "clip",
                 "frame"):
        arrays[name] = arrays[name][keep]
    np.savez(pack, **arrays)
    first = train_database_regressor(path, pack, TINY, folds=2, progress=False)
    assert "skipped" not in first and read_database(path).regressor is not None
    assert first["validation_error_m"] > 0 and len(first["folds"]) == 2
    again = train_database_regressor(path, pack, TINY, folds=2, progress=False)
    assert "skipped" in again and again["key"] == first["key"]
    size = Path(path).stat().st_size
    for _ in range(3):  # rewriting the group keeps the file valid, and no bigger: the old bytes are not kept
        store_regressor(path, read_database(path).regressor)
    assert Path(path).stat().st_size <= size
    script = (f"import sys, numpy as np; from agentdress_ros.engine import load_engine, EngineConfig; "
              f"e = load_engine({str(path)!r}, EngineConfig(pose_model='regressor')); "
              f"out = e.synthesize(np.zeros((31, 3))); assert np.isfinite(out).all(); "
              f"print([m for m in ('sklearn', 'torch', 'jax') if m in sys.modules])")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.strip().splitlines()[-1].replace("'", '"')) == []


def _swap(group, name, value):
    del group[name]
    group.create_dataset(name, data=value)


def _frames_of(database, clip_index):
    data = pack_data(load_sequence_pack(PACK), database)
    keep = np.flatnonzero(data.groups == np.unique(data.groups)[clip_index])[::4]
    return data.rows(keep)



@pytest.mark.parametrize("garment", ["tshirt", "trousers"])
def test_shipped_regressor_synthesis_reproduces_the_anchor_drapes(body, garment):
    """The shipped databases' regressor, folded, in the node's float32 pipeline: every anchor's beta0 drape within
    1 mm on average (penetration handling on; anchors whose poses agree on a region's dofs share its weight there,
    so a few vertices may differ by centimetres, as with the examples pose model: test_shipped_data)."""
    db = read_database(ROOT / "data" / f"{garment}_default.h5")
    assert db.regressor is not None and db.regressor.info["clips"]
    engine = Engine(db, body, EngineConfig(pose_model="regressor"))
    errors = []
    for s in range(db.n_anchors):
        engine.reset()
        drape = db.example_drapes[np.flatnonzero(np.abs(db.example_poses - db.anchor_poses[s]).max(axis=(1, 2))
                                                 <= 1e-6)[0]]
        errors.append(np.linalg.norm(engine.synthesize(db.anchor_poses[s]) - drape, axis=1).mean())
    assert max(errors) < 1e-3, errors
