"""Runtime engine at the extremes: shapes beyond the training range, wrapped and huge angles, exact anchor hits,
far anchors, 180-degree jumps, subnormal and non-finite inputs; property-based with hypothesis."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agentdress_ros.body.kinematics import linear_blend_skinning
from agentdress_ros.engine.config import EngineConfig
from agentdress_ros.engine.database import shape_features
from agentdress_ros.engine.engine import Engine
from agentdress_ros.engine.kernels import prepare_pose, region_neighbours
from agentdress_ros.engine.synthetic import make_synthetic_database

PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def db(body):
    return make_synthetic_database(1000, 10, n_examples=4, n_sequence=3, seed=7, body=body)


@pytest.fixture(scope="module")
def engine(db, body):
    return Engine(db, body, EngineConfig())


@pytest.fixture(scope="module")
def projected(db, body):
    """The node's refinement on top: the body projection (its posed face normals, its thinned candidates)."""
    return Engine(db, body, EngineConfig(projection=8))


@pytest.fixture(scope="module")
def exact(db, body):
    return Engine(db, body, EngineConfig(penetration=False, decay=False))


def lbs(body, shape, db, pose):
    transforms, _ = body.pose(shape, np.asarray(pose, dtype=np.float64))
    out = np.empty((db.n_vertices, 3))
    return linear_blend_skinning(db.rest.astype(np.float64), db.skin_indices, db.skin_weights.astype(np.float64),
                                 transforms, out)


def deviation_bound(engine) -> float:
    """How far the output may lie from the beta0 LBS garment: the largest shape delta, the largest garment-to-body
    distance (the most a push can undo) and the skeleton change between beta and beta0, plus slack."""
    state = engine._state
    delta = np.linalg.norm(state.deltas, axis=1).max()
    gap = np.linalg.norm(engine.db.rest - state.body_points, axis=1).max()
    bones = np.linalg.norm(state.heads - engine._heads0, axis=1).max()
    return float(2 * (delta + gap + bones) + 0.01)


def test_beta_beyond_the_training_range_is_clamped_and_reported(db, engine):
    beyond = db.beta_range[:, 1] + 0.3
    report = engine.set_shape(beyond)
    assert report.clamped and report.clamped_names
    assert np.all(report.effective <= db.beta_range[:, 1])
    assert np.isfinite(engine.synthesize(np.zeros((len(db.bone_names), 3)))).all()
    at_edge = engine.set_shape(db.beta_range[:, 0])
    assert not at_edge.clamped
    with pytest.raises(ValueError, match="weight"):
        engine.set_shape([0.5, 0.5, 0.5, np.nan, 0.5, 0.5])
    with pytest.raises(ValueError, match="6 values"):
        engine.set_shape([0.5] * 5)
    engine.set_shape(db.beta0)


def test_angles_near_pi_and_wrapped_give_the_same_garment(db, exact):
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(len(db.bone_names), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    pose = axes * (np.pi - 1e-3)
    pose[0] = 0.0
    a = exact.synthesize(pose).copy()
    b = exact.synthesize(pose - axes * 2 * np.pi * np.r_[0, np.ones(len(pose) - 1)][:, None]).copy()  # angle -pi-..
    c = exact.synthesize(pose + axes * 4 * np.pi * np.r_[0, np.ones(len(pose) - 1)][:, None]).copy()
    assert np.isfinite(a).all()
    assert np.abs(a - b).max() < 1e-4 and np.abs(a - c).max() < 1e-4


def test_canonical_pose_is_the_same_rotation():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    rotvecs = rng.normal(size=(20, 3)) * rng.uniform(0, 40, size=(20, 1))
    theta, root = np.empty_like(rotvecs), np.empty(3)
    assert prepare_pose(rotvecs, np.zeros(3), 1e4, theta, root) == -1
    assert (np.linalg.norm(theta, axis=1) <= np.pi + 1e-9).all()
    assert np.allclose(Rotation.from_rotvec(theta).as_matrix(), Rotation.from_rotvec(rotvecs).as_matrix(), atol=1e-9)


def test_pose_exactly_at_an_anchor_has_finite_unit_weights(db, engine):
    engine.reset()
    out = engine.synthesize(db.anchor_poses[3])
    assert np.isfinite(out).all()
    assert np.allclose(engine.weights.sum(axis=1), 1.0, atol=1e-6)
    assert (engine.selected[:, 0] == 3).all()


def test_all_anchors_far_away_weights_do_not_underflow():
    rng = np.random.default_rng(2)
    poses = rng.uniform(-3, 3, size=(50, 6))
    selected, weights = np.zeros((7, 5), dtype=np.int32), np.zeros((7, 5))
    for scale in (1e-300, 1.0, 1e150, 1e300):  # tiny to huge sensitivities: D from ~0 to overflow-sized
        state = np.zeros((7, 50))
        q = np.full((7, 6), scale)
        region_neighbours(np.full(6, 3.1), poses, np.arange(6), q, 1e-6 * q.sum(axis=1), 3.0, 0.5, state, False,
                          selected, weights)
        assert np.isfinite(weights).all() and np.allclose(weights.sum(axis=1), 1.0)
        assert (weights[:, 0] >= weights[:, -1]).all()


def test_a_180_degree_jump_in_one_frame_stays_finite_and_bounded(db, body, engine):
    engine.reset()
    pose = np.zeros((len(db.bone_names), 3))
    bound = deviation_bound(engine)
    for angle in (0.0, np.pi, 0.0, -np.pi, np.pi / 2):
        pose[10] = [0.0, 0.0, angle]  # an upper arm swings half a turn between frames
        pose[0] = [angle, 0.0, 0.0]  # and the whole body flips
        out = engine.synthesize(pose)
        assert np.isfinite(out).all()
        assert np.linalg.norm(out - lbs(body, engine.reference, db, pose), axis=1).max() < bound


@pytest.mark.parametrize("which", ["engine", "projected"])
def test_subnormal_huge_and_non_finite_inputs(db, request, which):
    engine = request.getfixturevalue(which)
    n = len(db.bone_names)
    assert np.isfinite(engine.synthesize(np.full((n, 3), 5e-324))).all()
    assert np.isfinite(engine.synthesize(np.full((n, 3), 1e300))).all()
    assert np.isfinite(engine.synthesize(np.full((n, 3), -1e300), np.array([1e300, -1e300, 1e30]))).all()
    assert np.isfinite(engine.synthesize(np.full((n, 3), 1e30, dtype=np.float32))).all()
    bad = np.zeros((n, 3))
    bad[db.bone_names.index("LeftForeArm"), 1] = np.nan
    with pytest.raises(ValueError, match="LeftForeArm"):
        engine.synthesize(bad)
    bad[:] = 0.0
    bad[db.bone_names.index("Head"), 2] = np.inf
    with pytest.raises(ValueError, match="Head"):
        engine.synthesize(bad)
    with pytest.raises(ValueError, match="root translation"):
        engine.synthesize(np.zeros((n, 3)), np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        engine.synthesize(np.zeros((n - 1, 3)))
    assert engine.bad_frames == 0


@PROPERTY
@given(pose=st.lists(st.floats(-7.0, 7.0), min_size=93, max_size=93),
       beta=st.lists(st.floats(-0.5, 1.5), min_size=6, max_size=6))
def test_output_is_finite_and_near_the_skinned_garment(db, body, engine, pose, beta):
    engine.set_shape(beta)
    pose = np.reshape(pose, (-1, 3))
    out = engine.synthesize(pose)
    assert np.isfinite(out).all()
    reference = lbs(body, engine.reference, db, pose)
    assert np.linalg.norm(out - reference, axis=1).max() < deviation_bound(engine)


@PROPERTY
@given(s=st.integers(0, 9), k=st.integers(0, 16))
def test_exact_reproduction_at_anchor_pose_and_training_shape(db, body, exact, s, k):
    beta = db.training_betas[k]
    exact.set_shape(beta)
    out = exact.synthesize(db.anchor_poses[s]).astype(np.float64)

    def f(b):
        phi = shape_features(b, db.beta0, db.beta_scale)[0] @ db.ridge[s]
        return db.pca_mean[s] + np.tensordot(phi, db.pca_components[s], axes=1)

    expected = lbs(body, exact.reference, db, db.anchor_poses[s]) + f(beta) - f(db.beta0)
    assert np.abs(out - expected).max() < 2e-5


@PROPERTY
@given(pose=st.lists(st.floats(-7.0, 7.0), min_size=93, max_size=93),
       beta=st.lists(st.floats(-0.5, 1.5), min_size=6, max_size=6))
def test_the_body_projection_stays_finite_and_bounded(db, body, projected, pose, beta):
    """Any pose, any shape: the projection moves a vertex at most out of the body, so the output stays finite, no
    frame is rejected, and it lies within the same bound of the skinned garment plus the body's half-thickness."""
    projected.set_shape(beta)
    pose = np.reshape(pose, (-1, 3))
    out = projected.synthesize(pose)
    assert np.isfinite(out).all() and projected.bad_frames == 0
    reference = lbs(body, projected.reference, db, pose)
    assert np.linalg.norm(out - reference, axis=1).max() < deviation_bound(projected) + 0.3
