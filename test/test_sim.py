"""Ground-truth drapes (agentdress_ros.sim) with the real newton VBD solver on a small T-shirt.

The drape tests need `newton` (pip install newton==1.8.0, the project's `build` extra) and are skipped without it;
the first run also pays warp's one-time kernel compile (~30 s, cached in ~/.cache/warp).
"""
import importlib.util
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agentdress_ros.sim import DrapeSettings, membrane_lame, triangle_stretch

NEWTON = importlib.util.find_spec("newton") is not None
needs_newton = pytest.mark.skipif(
    not NEWTON, reason="newton is not installed: pip install newton==1.8.0 (the project's `build` extra)"
)


def test_lame_parameters_match_plane_stress_hooke_law():
    """(mu, lambda) from (Y, nu) give plane-stress Hooke: Y/(1-nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1-nu)/2]]."""
    settings = DrapeSettings()
    Y, nu = settings.stretch_stiffness, settings.poisson_ratio
    assert (Y, nu) == (30.0, 0.3)
    mu, lam = settings.lame
    assert mu == pytest.approx(Y / (2 * (1 + nu)))
    assert lam == pytest.approx(Y * nu / (1 - nu**2))
    assert (mu, lam) == pytest.approx((11.538461538, 9.890109890))
    # Isotropic law sigma = 2 mu eps + lambda tr(eps) I in Voigt form (eps_xx, eps_yy, 2 eps_xy).
    lame_matrix = np.array([[2 * mu + lam, lam, 0.0], [lam, 2 * mu + lam, 0.0], [0.0, 0.0, mu]])
    hooke = Y / (1 - nu**2) * np.array([[1.0, nu, 0.0], [nu, 1.0, 0.0], [0.0, 0.0, (1 - nu) / 2]])
    np.testing.assert_allclose(lame_matrix, hooke, rtol=1e-12)
    # Uniaxial stress recovers Young's modulus and Poisson ratio: strain = C^-1 (1, 0, 0).
    strain = np.linalg.solve(lame_matrix, [1.0, 0.0, 0.0])
    assert 1.0 / strain[0] == pytest.approx(Y)
    assert -strain[1] / strain[0] == pytest.approx(nu)
    with pytest.raises(ValueError):
        membrane_lame(30.0, 1.0)


def test_triangle_stretch_of_known_deformations():
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2]])
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(triangle_stretch(rest @ rotation.T + 5.0, rest, faces), [[1.0, 1.0]], atol=1e-12)
    stretched = rest * np.array([1.1, 0.9, 1.0])
    np.testing.assert_allclose(triangle_stretch(stretched, rest, faces), [[1.1, 0.9]], atol=1e-12)


@pytest.fixture(scope="module")
def scene(body):
    """A ~1200-vertex T-shirt on the reference body in the rest pose: (rest, warm start, body vertices, faces)."""
    from agentdress_ros.garment import make_garment
    from agentdress_ros.garment.dressing import Dressing

    garment = make_garment("tshirt", body, n_vertices=1200)
    dressing = Dressing(body, [garment], dtype=np.float64)
    dressing.pose(np.zeros((body.n_bones, 3)))
    return (garment.faces, dressing.garment_rest[0].copy(), dressing.garment_vertices[0].copy(),
            dressing.body_vertices.copy(), dressing.body_faces)


@pytest.fixture(scope="module")
def draped(scene, warp_kernels):
    from agentdress_ros.sim import drape

    faces, rest, warm, body_vertices, body_faces = scene
    return drape(warm, faces, body_vertices, body_faces, DrapeSettings(), rest_vertices=rest)


@needs_newton
def test_drape_converges_outside_the_body(draped):
    settings = DrapeSettings()
    assert draped.converged, f"no convergence in {draped.frames} frames (p99 speed {draped.percentile_speed} m/s)"
    assert draped.frames < settings.max_frames
    assert draped.percentile_speed < settings.speed_threshold
    assert draped.inside_count == 0
    assert draped.min_clearance > 0.0
    assert np.isfinite(draped.vertices).all()


@needs_newton
def test_drape_strain_is_bounded(draped):
    # measured: mean stretch 1.6 %, most stretched triangle 7.0 %, most compressed 7.3 %; bounds about twice that
    assert draped.strain_mean < 0.03
    assert draped.strain_max < 0.15
    assert draped.compression_max < 0.15


@needs_newton
def test_gravity_pulls_the_cloth_down_but_it_stays_on_the_body(scene, draped):
    from agentdress_ros.garment.binding import signed_clearance

    faces, rest, warm, body_vertices, body_faces = scene
    drop = warm[:, 2].mean() - draped.vertices[:, 2].mean()
    assert 0.025 < drop < 0.05, drop  # 3.7 cm measured
    assert draped.displacement_mean == pytest.approx(np.linalg.norm(draped.vertices - warm, axis=1).mean())
    # It hangs on the shoulders: most of the shirt is still within a few cm of the skin, none fell off.
    clearance = signed_clearance(draped.vertices, body_vertices, body_faces)
    assert np.median(clearance) < 0.02  # 1.1 cm measured
    assert clearance.max() < 0.08  # 5.1 cm measured


@needs_newton
def test_replayed_substeps_give_the_eager_drape_bit_for_bit(scene, warp_kernels):
    """The 1,200-vertex shirt carried by the body over a 4-frame ramp (the body rising 3 cm: moving frames), then 8
    still frames, in contact with the shoulders throughout: the substeps replayed from warp graphs (the default) and
    the same drape run eagerly, launch by launch, give the same vertices bit for bit - and so does a second replayed
    drape (determinism)."""
    from agentdress_ros.sim import drape

    faces, rest, warm, body_vertices, body_faces = scene
    path = np.stack([body_vertices + [0.0, 0.0, 0.03 * (k / 4 - 1)] for k in range(4)])
    short = DrapeSettings(max_frames=8, min_frames=8)
    replayed, again, eager = (drape(warm, faces, body_vertices, body_faces, settings, rest_vertices=rest,
                                    body_path=path)
                              for settings in (short, short, replace(short, graph=False)))
    assert replayed.ramp_frames == 4 and replayed.frames == eager.frames == 12
    assert np.array_equal(replayed.vertices, eager.vertices) and np.array_equal(again.vertices, replayed.vertices)
    assert np.abs(replayed.vertices - warm).max() > 0.01  # the cloth moved with the body
    # and the three collision pipelines shared one narrow-phase kernel, built once (sim.settings)
    from newton._src.geometry import narrow_phase

    assert narrow_phase.create_narrow_phase_kernel_gjk_mpr.cache_info().hits >= 2


@pytest.fixture(scope="module")
def trousers(body):
    """A ~600-vertex pair of trousers on the reference body at rest: (garment, rest, warm start, body, faces)."""
    from agentdress_ros.garment import make_garment
    from agentdress_ros.garment.dressing import Dressing

    garment = make_garment("trousers", body, n_vertices=600)
    dressing = Dressing(body, [garment], dtype=np.float64)
    dressing.pose(np.zeros((body.n_bones, 3)))
    return (garment, dressing.garment_rest[0].copy(), dressing.garment_vertices[0].copy(),
            dressing.body_vertices.copy(), dressing.body_faces)


@needs_newton
def test_a_pinned_waistband_holds_trousers_up(trousers):
    """Friction 0.3 cannot hold loose trousers on the hips; the waistband (pinned at its skinned place) does."""
    from agentdress_ros.sim import drape

    garment, rest, warm, body_vertices, body_faces = trousers
    assert 10 <= len(garment.pinned) < garment.n_vertices // 5
    # the band is the top of the trousers
    assert warm[garment.pinned, 2].min() > np.percentile(warm[:, 2], 80)
    settings = DrapeSettings(max_frames=120)
    held = drape(warm, garment.faces, body_vertices, body_faces, settings, rest_vertices=rest, pinned=garment.pinned)
    # the loose pair slides on for its whole budget: 10.1 cm in 40 frames, 11.3 cm in 120 (measured 2026-12-07)
    loose = drape(warm, garment.faces, body_vertices, body_faces, replace(settings, max_frames=40), rest_vertices=rest)
    np.testing.assert_allclose(held.vertices[garment.pinned], warm[garment.pinned], atol=1e-6)  # float32 state
    drop_held = warm[:, 2].mean() - held.vertices[:, 2].mean()
    drop_loose = warm[:, 2].mean() - loose.vertices[:, 2].mean()
    assert held.converged and held.inside_count == 0
    # measured: held 1.4 cm (converged at frame 73), loose 10.1 cm
    assert drop_held < 0.025 and drop_loose > drop_held + 0.05, (drop_held, drop_loose)


def test_bad_inputs_are_rejected_before_simulating():
    from agentdress_ros.sim import drape

    vertices = np.zeros((3, 3))
    with pytest.raises(ValueError):
        drape(vertices, np.array([[0, 1, 5]]), vertices, np.array([[0, 1, 2]]))
    with pytest.raises(ValueError):
        drape(np.full((3, 3), np.nan), np.array([[0, 1, 2]]), vertices, np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match="pinned"):
        drape(vertices, np.array([[0, 1, 2]]), vertices, np.array([[0, 1, 2]]), pinned=[3])


@needs_newton
@pytest.mark.parametrize("substeps", [16, 17, 40])
def test_a_frame_of_any_substep_count_falls_as_implicit_euler_does(substeps):
    """A flat sheet far from its collider falls freely. Implicit Euler from rest moves it g dt^2 n (n + 1) / 2 in n
    steps of dt = T / n, so a frame of T with n substeps drops it g T^2 (n + 1) / (2 n): the same frame at any
    count, odd ones included (whose newest state sits in the other buffer)."""
    from agentdress_ros.sim.cloth import ClothSim

    grid = np.stack(np.meshgrid(np.linspace(0.0, 0.2, 5), np.linspace(0.0, 0.2, 5)), axis=-1).reshape(-1, 2)
    sheet = np.column_stack([grid, np.full(len(grid), 0.02)])  # near 0, where float32 steps are fine
    faces = np.array([[r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c + 1] for r in range(4) for c in range(4)]
                     + [[r * 5 + c, (r + 1) * 5 + c + 1, (r + 1) * 5 + c] for r in range(4) for c in range(4)])
    box = np.array([[5, 5, 0], [6, 5, 0], [5, 6, 0], [5, 5, 1.0]])  # a tet 5 m away: no contact
    box_faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    settings = DrapeSettings(velocity_retention=1.0, graph=False)
    sim = ClothSim(sheet, faces, box, box_faces, settings)
    dropped = sheet[:, 2] - sim.frame(substeps=substeps)[:, 2]
    expected = -settings.gravity * sim.frame_dt ** 2 * (substeps + 1) / (2 * substeps)
    np.testing.assert_allclose(dropped, expected, rtol=1e-2)  # float32 steps; a wrong buffer is 11 % off at 17
    second = sheet[:, 2] - sim.frame()[:, 2]  # then a frame at the default count continues from the newest state
    assert np.all(second > dropped)


def test_fast_frames_get_the_substeps_that_keep_the_body_within_one_step():
    from agentdress_ros.sim.sequence import SequenceSettings

    body = np.zeros((4, 3))
    moved = body.copy()
    moved[2] = (0.0, 0.06, 0.08)  # one vertex moves 10 cm in the frame
    assert SequenceSettings().substeps(body, moved) == DrapeSettings().substeps  # off by default
    assert SequenceSettings(max_body_step=0.004).substeps(body, moved) == 25
    assert SequenceSettings(max_body_step=0.004).substeps(body, body + 0.001) == DrapeSettings().substeps
    assert "max_body_step" not in SequenceSettings().key() and "max_body_step" in SequenceSettings(max_body_step=0.03).key()
    # knobs added later leave the key of sequences simulated before them alone (their chunks resume)
    assert "warm_ramp_frames" not in SequenceSettings().key()


@pytest.fixture(scope="module")
def arms_down(body):
    """A 400-vertex T-shirt and an arms-down pose from a training clip (08_04, slow walk) at beta0:
    (garment, pose (B, 3), rest garment (V, 3), skinned garment (V, 3), posed body (N, 3), body faces (G, 3))."""
    from agentdress_ros.offline.anchors import canonical_poses
    from agentdress_ros.garment import make_garment
    from agentdress_ros.motion.retarget import load_cmu_motion
    from agentdress_ros.body import visible_body
    from agentdress_ros.sim.posing import posed_surfaces

    from .conftest import shared_path

    garment = make_garment("tshirt", body, n_vertices=400)
    shape = body.shape()
    motion = load_cmu_motion(shared_path("mocap", "cmu", "08_04.bvh"), shape.heads, shape.tails)
    pose = canonical_poses(motion.rotvecs[232:233])[0]
    bodies, skinned = posed_surfaces(body, garment, shape, pose[None])
    return garment, pose, garment.rest_vertices(body, shape), skinned[0], bodies[0], visible_body(body)[1]


@needs_newton
def test_animated_collider_carries_the_cloth_out_of_where_skinning_puts_it_inside(body, arms_down):
    """Skinning to an arms-down pose folds the shirt into the armpit (vertices inside the body); carrying the body
    from rest into the pose under the cloth leaves those vertices outside it."""
    from agentdress_ros.garment.inside import inside_report
    from agentdress_ros.sim import drape
    from agentdress_ros.sim.posing import posed_surfaces, ramp_poses

    garment, pose, rest, skinned, posed_body, faces = arms_down
    started_inside = inside_report(skinned, posed_body, faces)["inside"]
    assert started_inside.sum() >= 3
    path, _ = posed_surfaces(body, garment, body.shape(), ramp_poses(pose, 12))
    result = drape(rest, garment.faces, posed_body, faces, DrapeSettings(max_frames=60), rest_vertices=rest,
                   body_path=path)
    assert result.ramp_frames == 12 and np.isfinite(result.vertices).all()
    ended = inside_report(result.vertices, posed_body, faces)
    # most vertices that skinning puts inside end outside; what stays is caught where the arm passes into the torso
    assert ended["inside"][started_inside].sum() <= started_inside.sum() // 2, ended["inside_count"]
    assert ended["truly_inside_count"] == 0


def test_ramp_between_blends_shape_and_pose_and_stops_short_of_the_target():
    from agentdress_ros.sim.posing import ramp_between

    beta_from, beta_to = np.zeros(6), np.linspace(0.1, 0.6, 6)
    pose_from, pose_to = np.zeros((3, 3)), np.full((3, 3), 0.3)
    betas, poses = ramp_between(beta_from, pose_from, beta_to, pose_to, 4)
    assert betas.shape == (4, 6) and poses.shape == (4, 3, 3)
    np.testing.assert_allclose(betas[0], beta_from)
    np.testing.assert_allclose(poses[0], pose_from)
    np.testing.assert_allclose(betas[2], 0.5 * beta_to)
    np.testing.assert_allclose(poses[3], 0.75 * pose_to)


@needs_newton
def test_a_warm_start_can_carry_a_finished_drape_onto_another_shape(body, arms_down):
    """warm_ramp_frames: the body changes from the source drape's shape into the job's with the settled drape on it
    (instead of the source's offset pasted onto the new shape's skinned garment and lifted out of the body)."""
    from agentdress_ros.offline.jobs import DrapeJob, _body_and_garment, posed_scene, run_drape_job
    from agentdress_ros.garment.inside import inside_report

    garment, pose, *_ = arms_down
    beta0 = body.shape().beta
    heavy = beta0.copy()
    heavy[3] = 0.9  # weight: a larger body inside the same shirt
    short = {"max_frames": 30, "min_frames": 8}
    source = run_drape_job(DrapeJob("anchor", 0, 0, pose, beta0, "tshirt", 400, {**short, "ramp_frames": 8}))
    job = DrapeJob("anchor", 0, 1, pose, heavy, "tshirt", 400, {**short, "warm_ramp_frames": 6},
                   warm_key=source["key"], warm_pose=pose, warm_beta=beta0)
    carried = run_drape_job(job, source["vertices"])
    assert carried["stats"]["ramp_frames"] == 6 and carried["stats"]["pushed_out"] == 0
    assert np.isfinite(carried["vertices"]).all()
    job_body, job_garment = _body_and_garment("tshirt", 400)
    _, _, heavy_body, heavy_faces = posed_scene(job_body, job_garment, heavy, pose)
    assert inside_report(carried["vertices"], heavy_body, heavy_faces)["truly_inside_count"] == 0
    # the transferred start of the same job (no warm ramp) is another, equally converged-or-not drape of it
    pasted = run_drape_job(DrapeJob("anchor", 0, 1, pose, heavy, "tshirt", 400, short, warm_key=source["key"],
                                    warm_pose=pose, warm_beta=beta0), source["vertices"])
    assert pasted["stats"]["ramp_frames"] == 0
    assert np.linalg.norm(pasted["vertices"] - carried["vertices"], axis=1).mean() < 0.015  # 0.42 cm measured


@pytest.fixture(scope="module")
def swing_sequences(body, arms_down, tmp_path_factory):
    """A 7-frame motion (arms swinging down while the root moves 30 cm) simulated twice in chunks of 3 frames:
    once uninterrupted, once stopped after the first chunk and resumed. -> (folder, garment, motion)."""
    from agentdress_ros.motion.skeleton import Motion
    from agentdress_ros.sim.sequence import SequenceSettings, simulate_sequence

    garment, pose, *_ = arms_down
    t = np.linspace(0.0, 1.0, 7)[:, None, None]
    motion = Motion(rotvecs=t * pose[None], root_translation=np.c_[np.zeros(7), -0.3 * t[:, 0], np.zeros(7)],
                    fps=30.0, name="swing")
    settings = SequenceSettings(chunk_frames=3, ramp_frames=4, settle_frames=10,
                                drape=DrapeSettings(substeps=4, iterations=2))
    folder = tmp_path_factory.mktemp("sequences")
    beta = body.shape().beta
    runs = {"whole": simulate_sequence(motion, garment, beta, folder / garment.name / "whole", settings, body=body,
                                       progress=False),
            "first": simulate_sequence(motion, garment, beta, folder / garment.name / "resumed", settings,
                                       body=body, max_chunks=1, progress=False),
            "rest": simulate_sequence(motion, garment, beta, folder / garment.name / "resumed", settings, body=body,
                                      progress=False)}
    return folder, garment, motion, runs


@needs_newton
def test_a_resumed_sequence_gives_the_frames_of_an_uninterrupted_run(swing_sequences):
    from agentdress_ros.sim.sequence import load_sequence

    folder, garment, motion, runs = swing_sequences
    assert runs["whole"]["chunks"] == 3 and runs["whole"]["frames"] == 7
    assert runs["first"]["chunks"] == 1 and runs["rest"]["chunks"] == 2
    a, b = load_sequence(folder / garment.name / "whole"), load_sequence(folder / garment.name / "resumed")
    assert np.array_equal(a["positions"], b["positions"])
    assert np.isfinite(a["positions"]).all() and a["positions"].shape == (7, garment.n_vertices, 3)
    np.testing.assert_allclose(a["root_velocity"][:, 1], -0.3 * 30.0 / 6.0, rtol=1e-5)
    # the cloth moved with the body (root translation of 30 cm)
    assert abs(a["positions"][-1, :, 1].mean() - a["positions"][0, :, 1].mean() + 0.3) < 0.03  # 28.2 cm measured
    # 25 cm or more in 6 frames at 30 fps: some frame moves some vertex at 1.25 m/s or faster (3.2 m/s measured for
    # the cloth, 2.8 m/s for the body)
    assert runs["whole"]["max_cloth_speed"] > 1.25 and runs["whole"]["max_body_speed"] > 1.25


@needs_newton
def test_a_sequence_is_not_continued_on_another_motion_of_the_same_name(body, swing_sequences):
    """The chunks carry a digest of the motion: a clip processed otherwise (a repaired capture flip) under the same
    name and settings is refused, not continued from frames of the old motion."""
    from agentdress_ros.motion.skeleton import Motion
    from agentdress_ros.sim.sequence import SequenceSettings, simulate_sequence

    folder, garment, motion, _ = swing_sequences
    other = Motion(rotvecs=motion.rotvecs * 1.01, root_translation=motion.root_translation, fps=30.0, name="swing")
    settings = SequenceSettings(chunk_frames=3, ramp_frames=4, settle_frames=10,
                                drape=DrapeSettings(substeps=4, iterations=2))
    with pytest.raises(ValueError, match="other settings"):
        simulate_sequence(other, garment, body.shape().beta, folder / garment.name / "whole", settings, body=body,
                          progress=False)


@needs_newton
def test_stepping_variants_continue_from_the_reference_checkpoint(body, swing_sequences):
    """`agentdress bench sequence`: every variant continues from the reference's first chunk, so the reference's
    own continuation is the uninterrupted run, frame for frame, and a coarser stepping is measured against it."""
    from agentdress_ros.evaluate.bench_sequence import compare_stepping
    from agentdress_ros.sim.sequence import SequenceSettings, load_sequence

    folder, garment, motion, _ = swing_sequences
    settings = SequenceSettings(chunk_frames=3, ramp_frames=4, settle_frames=10,
                                drape=DrapeSettings(substeps=4, iterations=2))
    result = compare_stepping(motion, garment, body.shape().beta, body, settings,
                              [{"graph": False}, {"substeps": 2}], chunks=2, progress=False)
    reference, same, coarser = result["rows"]
    assert reference["settings"] == "reference" and reference["frames"] == 4 and reference["ratio_to_baseline"] == 1
    assert same["distance_mm"]["max_vertex"] == 0.0  # moving frames never replay a graph: the same stepping
    assert 15.0 < coarser["distance_mm"]["mean"] < 60.0  # half the substeps: 29.6 mm from the reference (measured)
    assert np.isfinite([row["distance_mm"]["max_vertex"] for row in result["rows"]]).all()
    whole = load_sequence(folder / garment.name / "whole")["positions"]
    assert np.array_equal(result["baseline_positions"], whole[3:])


@needs_newton
def test_sequence_pack_restores_the_cloth_from_rest_frame_pca(body, swing_sequences, tmp_path):
    """The pack holds rest-frame offsets (unposed with beta0's bones) as float16 PCA coefficients: skinning them
    back reproduces every simulated frame to well under a millimetre."""
    from agentdress_ros.body.kinematics import linear_blend_skinning
    from agentdress_ros.offline.sequences import load_sequence_pack, pack_sequences
    from agentdress_ros.sim.sequence import load_sequence

    folder, garment, motion, _ = swing_sequences
    report = pack_sequences(folder, garment.name, garment.n_vertices, tmp_path / "pack.npz", components=13)
    assert report["frames"] == 14 and report["clips"] == 2 and report["components"] == 13
    pack = load_sequence_pack(tmp_path / "pack.npz")
    truth = load_sequence(folder / garment.name / "whole")
    shape = body.shape()
    for f in range(7):
        transforms, _ = body.pose(shape, truth["rotvecs"][f].astype(float), truth["root_translation"][f].astype(float))
        rest = pack["rest"].astype(float) + pack["offsets"][f]
        posed = linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, transforms, np.empty_like(rest))
        assert np.abs(posed - truth["positions"][f]).max() < 5e-4


@needs_newton
def test_a_clip_packed_part_way_is_kept_and_simulated_again(body, swing_sequences, tmp_path):
    import shutil

    from agentdress_ros.offline.sequences import clips_to_simulate, load_sequence_pack, pack_sequences

    folder, garment, motion, _ = swing_sequences
    root = tmp_path / "runs"
    shutil.copytree(folder / garment.name / "whole", root / garment.name / "whole")
    part = root / garment.name / "part"
    part.mkdir()
    shutil.copy(folder / garment.name / "whole" / "sequence.json", part)
    shutil.copy(folder / garment.name / "whole" / "chunk_0000.npz", part)  # stopped after its first chunk
    report = pack_sequences(root, garment.name, garment.n_vertices, tmp_path / "pack.npz", components=8)
    assert report["frames"] == 7 + 3 and report["clips_part_way"] == ["part"]
    pack = load_sequence_pack(tmp_path / "pack.npz")
    assert pack["clip_complete"].tolist() == [False, True] and pack["clips"].tolist() == ["part", "whole"]
    clips = [Path("mocap/whole.bvh"), Path("mocap/part.bvh"), Path("mocap/new.bvh")]
    assert clips_to_simulate(clips, tmp_path / "pack.npz", tmp_path / "elsewhere") == clips[1:]
    assert clips_to_simulate(clips, tmp_path / "pack.npz", root / garment.name) == clips  # folders under way
    # the clip simulated again (whole this time) keeps its place; the other comes from the pack as it was
    again = tmp_path / "again"
    shutil.copytree(folder / garment.name / "whole", again / garment.name / "part")
    report = pack_sequences(again, garment.name, garment.n_vertices, tmp_path / "pack.npz", components=8)
    repacked = load_sequence_pack(tmp_path / "pack.npz")
    assert report["frames"] == 7 + 7 and repacked["clips"].tolist() == ["part", "whole"]
    assert repacked["clip_complete"].tolist() == [True, True]
    np.testing.assert_allclose(repacked["offsets"][repacked["clip"] == 1], pack["offsets"][pack["clip"] == 1],
                               atol=1e-3)
