"""Runtime engine: analytic truths of the synthesis (Eq. 4, 7-10) on a small synthetic database."""
import numpy as np
import pytest

from agentdress_ros.body.kinematics import linear_blend_skinning
from agentdress_ros.engine.config import EngineConfig
from agentdress_ros.engine.database import DatabaseError, shape_features, write_database
from agentdress_ros.engine.engine import Engine, load_engine, region_blocks
from agentdress_ros.engine.kernels import block_push, region_neighbours
from agentdress_ros.engine.pose_models import POSE_MODELS, PoseModel
from agentdress_ros.engine.synthetic import make_synthetic_database

EXACT = EngineConfig(penetration=False, decay=False)


@pytest.fixture(scope="module")
def db(body):
    return make_synthetic_database(1200, 12, n_examples=6, n_sequence=5, seed=3, body=body)


@pytest.fixture(scope="module")
def exact_engine(db, body):
    return Engine(db, body, EXACT)


def skinned(body, shape, rest, db, pose, root=None):
    """Plain LBS (float64) of `rest` (V, 3) with shape's transforms at pose."""
    transforms, _ = body.pose(shape, np.asarray(pose, dtype=np.float64), root)
    out = np.empty((len(rest), 3))
    return linear_blend_skinning(np.asarray(rest, dtype=np.float64), db.skin_indices,
                                 db.skin_weights.astype(np.float64), transforms, out)


def shape_model(db, s, beta):
    """f(beta, theta_s) (V, 3) of anchor s, straight from the database arrays (Eq. 5-6)."""
    phi = shape_features(beta, db.beta0, db.beta_scale)[0] @ db.ridge[s]
    return db.pca_mean[s] + np.tensordot(phi, db.pca_components[s], axes=1)


@pytest.mark.parametrize("s, k", [(0, 0), (4, 2), (7, 8), (11, 16)])
def test_taylor_blend_at_an_anchor_reproduces_its_drape(db, body, exact_engine, s, k):
    # at theta = theta_s and a training shape: pose_model(theta_s) + f(beta, theta_s) - f(beta0, theta_s), exactly
    beta = db.training_betas[k]
    exact_engine.set_shape(beta)
    out = exact_engine.synthesize(db.anchor_poses[s]).astype(np.float64)
    expected = skinned(body, exact_engine.reference, db.rest, db, db.anchor_poses[s])
    expected += shape_model(db, s, beta) - shape_model(db, s, db.beta0)
    assert np.abs(out - expected).max() < 2e-5
    assert exact_engine.weights[:, 0].min() > 1 - 1e-6  # the anchor itself carries all weight


def test_reference_shape_is_plain_lbs_at_any_pose(db, body, exact_engine):
    exact_engine.set_shape(db.beta0)
    pose = np.random.default_rng(0).normal(scale=0.4, size=(body.n_bones, 3))
    out = exact_engine.synthesize(pose, np.array([0.3, -0.2, 0.1]))
    expected = skinned(body, exact_engine.reference, db.rest, db, pose, np.array([0.3, -0.2, 0.1]))
    assert np.abs(out - expected).max() < 2e-5


def test_identity_pose_at_reference_shape_returns_the_rest_garment(db, exact_engine):
    exact_engine.set_shape(db.beta0)
    out = exact_engine.synthesize(np.zeros((len(db.bone_names), 3)))
    assert np.abs(out - db.rest).max() < 1e-5


def test_ablation_at_an_anchor_at_beta0_returns_the_anchor_drape(db, body):
    # Sec. 4.6: sum_s w^s LBS_{theta_s -> theta}(f(beta0, theta_s)); at theta_s that is f(beta0, theta_s)
    engine = Engine(db, body, EngineConfig(penetration=False, decay=False, taylor="zeroth"))
    out = engine.synthesize(db.anchor_poses[5])
    assert np.abs(out - shape_model(db, 5, db.beta0)).max() < 2e-5


def test_plain_and_augmented_agree_at_an_anchor(db, body):
    beta = db.training_betas[3]
    outs = []
    for taylor in ("augmented", "plain"):
        engine = Engine(db, body, EngineConfig(penetration=False, decay=False, taylor=taylor))
        engine.set_shape(beta)
        outs.append(engine.synthesize(db.anchor_poses[2]).copy())
    assert np.abs(outs[0] - outs[1]).max() < 2e-5


def test_weights_sum_to_one_nearest_first():
    rng = np.random.default_rng(1)
    poses, q = rng.normal(size=(20, 9)), rng.uniform(size=(7, 9))
    selected, weights = np.zeros((7, 5), dtype=np.int32), np.zeros((7, 5))
    state = np.zeros((7, 20))
    region_neighbours(rng.normal(size=12), poses, np.arange(3, 12), q, np.full(7, 1e-9), 3.0, 0.5, state, False,
                      selected, weights)
    assert np.allclose(weights.sum(axis=1), 1.0)
    assert (np.diff(weights, axis=1) <= 1e-12).all()  # nearest first, heaviest first
    for g in range(7):
        assert set(selected[g]) == set(np.argsort(state[g], kind="stable")[:5])


def test_decay_blends_distances_with_the_previous_frame():
    poses, q = np.array([[0.0], [1.0]]), np.ones((7, 1))
    selected, weights, state = np.zeros((7, 1), dtype=np.int32), np.zeros((7, 1)), np.zeros((7, 2))
    args = (np.arange(1), q, np.full(7, 1e-9), 3.0, 0.25)
    region_neighbours(np.array([0.0]), poses, *args, state, False, selected, weights)
    region_neighbours(np.array([1.0]), poses, *args, state, True, selected, weights)
    assert np.allclose(state[:, 0], 0.75) and np.allclose(state[:, 1], 0.25)  # D = eta D' + (1 - eta) D


def test_penetration_push_is_the_blended_eq10_depth():
    starts, regions = np.array([0, 2]), np.array([[0, -1, -1, -1]], dtype=np.int32)
    region_w = np.zeros((4, 2))
    region_w[0] = 1.0
    selected, weights = np.array([[0, 1]] * 7, dtype=np.int32), np.array([[0.5, 0.5]] * 7)
    clearances = np.array([[0.005, 0.005], [0.003, 0.0]])  # d0 per anchor and vertex
    push = np.zeros(2)
    block_push(0.0, starts, regions, region_w, selected, weights, clearances, np.array([0.001, 0.004]), push)
    assert np.allclose(push, [0.5 * 0.004 + 0.5 * 0.002, 0.5 * 0.001 + 0.0])


def test_penetration_handling_lifts_a_garment_pushed_into_the_body(db, body):
    from dataclasses import replace

    from agentdress_ros.garment.binding import vertex_normals

    reference = body.shape(db.beta0)
    normals = vertex_normals(reference.vertices, body.body_faces)
    engine = Engine(db, body, EXACT)
    sunk = db.rest - 0.02 * normals[engine.bound_body_vertex[np.argsort(engine.order)]]
    sunk_db = replace(db, rest=sunk.astype(np.float32))
    pose = db.anchor_poses[1]
    off = Engine(sunk_db, body, EXACT).synthesize(pose).copy()
    engine = Engine(sunk_db, body, EngineConfig(decay=False))
    on = engine.synthesize(pose).copy()
    moved = np.linalg.norm(on - off, axis=1)
    # the shirt sat ~1.5 cm off the skin; sunk 2 cm, it is pushed back to its d0 = min(h0, 5 mm) clearance
    assert 0.004 < moved.mean() < 0.03
    after = engine._clearance + engine._push  # h + sum_s w^s max(0, d0^s - h) >= the blended d0 >= min d0
    assert (after >= engine._state.clearances.min(axis=0) - 1e-6).all()


def test_body_projection_puts_every_vertex_outside_its_nearest_candidate(db, body):
    """A garment sunk 2 cm into the body: with projection, each output vertex lies at least the margin in front of
    the nearest of its K candidate body vertices (skinned in numpy here; nearest to the unprojected vertex), moved
    along the posed normal of that vertex's largest incident face only; a fork may turn it off (the plain output)
    but not change K."""
    from dataclasses import replace

    from agentdress_ros.garment.binding import vertex_normals

    reference = body.shape(db.beta0)
    normals = vertex_normals(reference.vertices, body.body_faces)
    order = np.argsort(Engine(db, body, EXACT).order)
    sunk_db = replace(db, rest=(db.rest - 0.02 * normals[Engine(db, body, EXACT).bound_body_vertex[order]]
                                ).astype(np.float32))
    config = EngineConfig(penetration=False, decay=False, projection=8, dtype="float64")
    engine = Engine(sunk_db, body, config)
    pose = db.anchor_poses[2]
    on = engine.synthesize(pose).copy()
    off = engine.fork(projection=0).synthesize(pose).copy()
    np.testing.assert_allclose(off, Engine(sunk_db, body, replace(config, projection=0)).synthesize(pose))
    transforms, _ = body.pose(reference, np.asarray(pose, dtype=np.float64))
    points = body.posed_vertices(reference, transforms)  # every hm08 vertex
    faces = body.body_faces
    face_normals = np.cross(points[faces[:, 1]] - points[faces[:, 0]], points[faces[:, 2]] - points[faces[:, 0]])
    rest_area = np.linalg.norm(np.cross(reference.vertices[faces[:, 1]] - reference.vertices[faces[:, 0]],
                                        reference.vertices[faces[:, 2]] - reference.vertices[faces[:, 0]]), axis=1)
    nearest = np.array([c[np.linalg.norm(off[v] - points[c], axis=1).argmin()]
                        for v, c in enumerate(engine.projection_candidates(v) for v in range(len(off)))])
    largest = [np.flatnonzero((faces == u).any(axis=1)) for u in nearest]
    rotated = np.array([face_normals[f[rest_area[f].argmax()]] for f in largest])  # that face's posed normal
    rotated /= np.linalg.norm(rotated, axis=1, keepdims=True)
    depth = ((on - points[nearest]) * rotated).sum(axis=1)
    assert depth.min() >= config.penetration_margin - 1e-6
    moved = np.linalg.norm(on - off, axis=1) > 1e-9
    assert 0.2 < moved.mean() < 1.0  # sunk 2 cm: most vertices come out
    np.testing.assert_allclose(depth[moved], config.penetration_margin, atol=1e-6)  # ...to the margin exactly
    along = np.cross(on[moved] - off[moved], rotated[moved])  # along their nearest's normal
    assert np.abs(along).max() < 1e-6
    with pytest.raises(ValueError, match="candidates"):
        engine.fork(projection=4)


def test_body_projection_searches_what_each_example_pose_brings_near(db, body):
    """Each output row's candidates hold its K nearest body vertices at rest and, at every pose-model example pose,
    the body vertex nearest to its example drape vertex there (a pose brings body parts near that rest does not)."""
    from scipy.spatial import cKDTree

    engine = Engine(db, body, EngineConfig(projection=4, projection_examples=1, projection_spacing=0.0))
    reference, surface = body.shape(db.beta0), body.body_vertex_ids
    expected = [set(surface[n]) for n in cKDTree(reference.vertices[surface]).query(np.asarray(db.rest, float), k=4)[1]]
    for pose, drape in zip(db.example_poses, db.example_drapes):
        transforms, _ = body.pose(reference, np.asarray(pose, dtype=np.float64))
        posed = body.posed_vertices(reference, transforms)[surface]
        for v, n in enumerate(cKDTree(posed).query(np.asarray(drape, float))[1]):
            expected[v].add(surface[n])
    for v in range(db.n_vertices):
        candidates = engine.projection_candidates(v)  # output rows: the database's order
        assert len(candidates) == len(set(candidates))  # each searched once
        assert set(candidates) == expected[v]
    assert any(len(e) > 4 for e in expected)  # the example poses add candidates
    wider = Engine(db, body, EngineConfig(projection=4, projection_examples=3, projection_spacing=0.0))
    found = [set(wider.projection_candidates(v)) for v in range(db.n_vertices)]
    assert all(found[v] >= expected[v] for v in range(db.n_vertices))  # the nearest at each pose and two more
    assert sum(map(len, found)) > sum(map(len, expected))
    rest_only = Engine(db, body, EngineConfig(projection=4, projection_examples=0, projection_spacing=0.0))
    assert all(len(rest_only.projection_candidates(v)) == 4 for v in range(db.n_vertices))
    spaced = Engine(db, body, EngineConfig(projection=4, projection_examples=3, projection_spacing=0.03))
    nearest = cKDTree(reference.vertices[surface]).query(np.asarray(db.rest, float))[1]
    for v in range(db.n_vertices):
        kept = spaced.projection_candidates(v)
        assert set(kept) <= found[v] and surface[nearest[v]] in kept  # a subset, the nearest at rest first
        apart = np.linalg.norm(reference.vertices[kept][:, None] - reference.vertices[kept][None], axis=2)
        assert apart[np.triu_indices(len(kept), 1)].min(initial=1.0) >= 0.03
    assert sum(len(spaced.projection_candidates(v)) for v in range(db.n_vertices)) < sum(map(len, found)) / 2


def test_examples_pose_model_reproduces_an_example_at_its_pose(db, body):
    engine = Engine(db, body, EngineConfig(pose_model="examples", penetration=False, decay=False))
    out = engine.pose_model_output(db.example_poses[2])
    assert np.abs(out - db.example_drapes[2]).max() < 2e-5
    assert np.isfinite(engine.synthesize(db.example_poses[2] * 1.1)).all()


def test_sequence_pose_model_looks_up_the_frame(db, body):
    engine = Engine(db, body, EngineConfig(pose_model="sequence", penetration=False, decay=False))
    for t in (0, 3):
        out = engine.synthesize(db.sequence_poses[t], frame=t)
        assert np.abs(out - db.sequence_drapes[t]).max() < 2e-5
    assert np.abs(engine.synthesize(db.sequence_poses[4]) - db.sequence_drapes[4]).max() < 2e-5  # nearest frame


def test_pose_model_registry_and_protocol(exact_engine):
    assert {"lbs", "examples", "sequence"} <= set(POSE_MODELS)
    assert isinstance(exact_engine.pose_model, PoseModel)
    with pytest.raises(ValueError, match="unknown pose model"):
        Engine(exact_engine.db, exact_engine.body, EngineConfig(pose_model="nope"))


def test_level_of_detail_outputs_the_same_vertices(db, body):
    ids = np.arange(0, db.n_vertices, 3)
    pose = np.random.default_rng(2).normal(scale=0.3, size=(len(db.bone_names), 3))
    outs = []
    for vertices in (None, ids):
        engine = Engine(db, body, EngineConfig(decay=False, vertices=vertices))
        engine.set_shape(db.training_betas[6])
        outs.append(engine.synthesize(pose).copy())
    assert outs[1].shape == (len(ids), 3)
    assert np.abs(outs[0][ids] - outs[1]).max() < 1e-5
    assert Engine(db, body, EngineConfig(vertices=ids)).faces.max() < len(ids)


def test_knobs_anchors_components_neighbors_float64(db, body):
    pose = np.random.default_rng(4).normal(scale=0.3, size=(len(db.bone_names), 3))
    engine = Engine(db, body, EngineConfig(anchors=4, components=2, neighbors=2))
    assert engine.db.n_anchors == 4 and engine.db.n_components == 2 and engine.selected.shape == (7, 2)
    assert np.isfinite(engine.synthesize(pose)).all()
    a = Engine(db, body, EngineConfig(dtype="float32"))
    b = Engine(db, body, EngineConfig(dtype="float64"))
    for engine in (a, b):
        engine.set_shape(db.training_betas[10])
    out32, out64 = a.synthesize(pose), b.synthesize(pose)
    assert out32.dtype == np.float32 and out64.dtype == np.float64
    assert np.abs(out32 - out64).max() < 1e-4


def test_region_blocks_keep_each_vertex_weights(db):
    order, starts, regions, weights = region_blocks(db.regions)
    assert sorted(order) == list(range(db.n_vertices)) and starts[-1] == db.n_vertices
    dense = np.zeros((db.n_vertices, 7))
    for b in range(len(regions)):
        for j, g in enumerate(regions[b]):
            if g >= 0:
                dense[order[starts[b]:starts[b + 1]], g] = weights[j, starts[b]:starts[b + 1]]
    assert np.allclose(dense.sum(axis=1), 1.0)
    top = np.argsort(-db.regions, axis=1)[:, :4]
    keep = np.take_along_axis(db.regions, top, axis=1)
    assert np.allclose(np.take_along_axis(dense, top, axis=1), keep / keep.sum(axis=1, keepdims=True), atol=1e-6)


def test_set_shape_swaps_state_and_reports(db, body, exact_engine):
    before = exact_engine._state
    report = exact_engine.set_shape(db.training_betas[1])
    assert exact_engine._state is not before and not report.clamped and report.clamped_names == ()
    np.testing.assert_array_equal(report.requested, db.training_betas[1])
    assert np.allclose(report.effective, db.training_betas[1])


def test_load_engine_from_file(db, body, tmp_path):
    path = write_database(tmp_path / "tiny.h5", db)
    engine = load_engine(path, EXACT, body=body)
    assert engine.n_vertices == db.n_vertices
    assert np.abs(engine.synthesize(db.anchor_poses[0]) - Engine(db, body, EXACT).synthesize(db.anchor_poses[0])
                  ).max() < 1e-6
    with pytest.raises(DatabaseError, match="not found"):
        load_engine(tmp_path / "missing.h5", body=body)


def test_anchor_subset_restricts_the_examples_and_the_pose_model_keeps_its_own_k(db, body):
    """N anchors keep only those anchors' beta0 drapes as pose-model examples (matched by pose, as a build stores
    them), and the pose model's K (pose_neighbors) does not follow the anchors' K."""
    from dataclasses import replace

    extra = len(db.example_poses)
    anchor_drapes = np.stack([shape_model(db, s, db.beta0) for s in range(db.n_anchors)]).astype(np.float32)
    built = replace(db, example_poses=np.concatenate([db.anchor_poses, db.example_poses]),
                    example_drapes=np.concatenate([anchor_drapes, db.example_drapes]))
    engine = Engine(built, body, EngineConfig(pose_model="examples", anchors=[1, 3], neighbors=1, pose_neighbors=2))
    np.testing.assert_array_equal(engine.db.example_poses, db.anchor_poses[[1, 3]])
    assert engine.db.n_anchors == 2 and len(engine.pose_model.canonical) == 2
    assert engine.selected.shape == (7, 1) and engine.pose_model.selected.shape == (7, 2)
    full = Engine(built, body, EngineConfig(pose_model="examples", neighbors=2, pose_neighbors=4))
    assert len(full.pose_model.canonical) == db.n_anchors + extra
    assert full.selected.shape == (7, 2) and full.pose_model.selected.shape == (7, 4)
    with pytest.raises(ValueError, match="pose_neighbors"):
        EngineConfig(pose_neighbors=0)
    # a database without anchor drapes among its examples cannot run the examples pose model on an anchor subset
    with pytest.raises(ValueError, match="has none"):
        Engine(db, body, EngineConfig(pose_model="examples", anchors=2))


def test_garment_and_body_are_fitted_to_the_same_shape_beyond_the_training_range(body):
    """Age and proportions were trained at beta0 alone (zero-width range): only the shape models are held there;
    the body and the garment's fit (the surface binding the residual basis adds back) follow the requested shape,
    so the garment's clearance from the skin stays as at beta0 (the engine held the whole garment at beta0 before:
    median 27 cm off on this young, long-limbed body)."""
    from pathlib import Path

    from agentdress_ros.garment.binding import signed_clearance
    from agentdress_ros.models.garment_models import make_garment_model

    path = Path(__file__).resolve().parents[1] / "data" / "tshirt_default.h5"
    if not path.is_file():
        pytest.skip(f"no shipped database {path}")
    engine = load_engine(path, EngineConfig(pose_model="examples"), body=body)
    pose = engine.db.anchor_poses[0]
    young = np.array(engine.db.beta0)
    young[[1, 5]] = 0.2, 0.9  # age, proportions: outside their training range [2/3, 2/3], [0.5, 0.5]

    def clearance(beta):
        report = engine.set_shape(beta)
        engine.reset()
        garment = np.asarray(engine.synthesize(pose), dtype=np.float64)
        shape = body.shape(beta)
        skin = body.posed_vertices(shape, body.pose(shape, pose)[0])
        return signed_clearance(garment, skin, body.body_faces), report

    at_beta0, _ = clearance(engine.db.beta0)
    moved, report = clearance(young)
    assert report.clamped_names == () and report.held_names == ("age", "proportions")
    np.testing.assert_array_equal(report.effective, young)
    np.testing.assert_array_equal(report.model_beta[[1, 5]], engine.db.beta0[[1, 5]])
    change = np.abs(moved - at_beta0)
    assert np.median(change) < 5e-3 and np.percentile(change, 95) < 25e-3, (np.median(change), change.max())

    model = make_garment_model("tshirt", path, body=body, beta=young)
    assert model.shape_limits == {"clamped": [], "held": ["age", "proportions"]}
    model.set_shape(np.full(6, 1.5))  # outside [0, 1]: clamped for body and garment alike
    assert model.shape_limits["clamped"] == list(engine.db.beta_names)


@pytest.mark.parametrize("pose_model", ["examples", "lbs"])
def test_a_refit_clone_leaves_the_live_engines_frames_and_continues_its_history(db, body, pose_model):
    """The node refits a clone on a worker thread and drapes it at rest for the display bindings while the live
    engine keeps dressing frames: nothing the clone computes may reach the live frame or its decay history (a
    shared buffer published a frame mixing rest-pose and posed vertices); swapped in, the clone continues the decay
    as the live engine would have."""
    config = EngineConfig(pose_model=pose_model, decay=True)
    live, untouched = Engine(db, body, config), Engine(db, body, config)
    rng = np.random.default_rng(5)
    poses = [rng.normal(scale=0.3, size=(body.n_bones, 3)) for _ in range(4)]
    for pose in poses[:2]:
        frame = live.synthesize(pose)
        untouched.synthesize(pose)
    published = frame.copy()
    clone = live.clone()
    clone.set_shape(np.clip(np.asarray(db.beta0) + 0.3, 0.0, 1.0))
    for _ in range(2):
        clone.synthesize(np.zeros((body.n_bones, 3)))
    clone.reset()
    np.testing.assert_array_equal(frame, published)  # the view last returned by the live engine is untouched
    np.testing.assert_array_equal(live.synthesize(poses[2]), untouched.synthesize(poses[2]))
    same_shape = live.clone()
    np.testing.assert_array_equal(same_shape.synthesize(poses[3]), untouched.synthesize(poses[3]))
