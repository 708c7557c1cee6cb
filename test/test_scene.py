"""The crowd scene without DDS: tiers and hysteresis, the viewing cone, the budget scheduler's decisions (injected
costs, no wall-clock margins), and a scene of agents on the shipped databases: shared data with a small state per
agent, correct per-agent clouds, idle skip, culling, cross-fades between tiers, add and remove off the frame path."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from agentdress_ros.scene import (AgentSpec, Candidate, GarmentSpec, LodPolicy, Scene, SceneConfig, Viewer,
                                  parse_tier, parse_tiers, schedule)
from agentdress_ros.engine.config import EngineKnobs
from agentdress_ros.scene.lod import DEFAULT_TIERS, quaternion_forward

DATA = Path(__file__).resolve().parents[1] / "data"
EXAMPLES = EngineKnobs.of(pose_model="examples")
GARMENTS = (GarmentSpec("tshirt", database=str(DATA / "tshirt_default.h5"), engine=EXAMPLES),
            GarmentSpec("trousers", database=str(DATA / "trousers_default.h5"), engine=EXAMPLES))
BETA0 = (0.5, 2.0 / 3.0, 0.5, 0.5, 0.5, 0.5)
LOOK_X = (0.0, 0.0, 0.0, 1.0)  # identity orientation: looking along +x


# ---- tiers -----------------------------------------------------------------------------------------------------
def test_tier_lines_parse_and_print_back():
    tiers = DEFAULT_TIERS
    assert [t.name for t in tiers] == ["near", "mid", "far", "distant"]
    assert tiers[1].engine.as_dict() == {"neighbors": 2, "penetration": False, "pose_model": "examples",
                                         "projection": 0}
    assert tiers[1].kind == "synthesis"
    assert tiers[2].kind == "skinned" and math.isinf(tiers[3].max_distance) and tiers[3].every == 6
    assert parse_tiers([t.text() for t in tiers]) == tiers


@pytest.mark.parametrize("lines, words", [
    (["a 3 synthesis", "b 2 skinned", "c inf skinned"], "increase"),
    (["a 3 synthesis", "b 8 skinned"], "inf"),
    (["a 3 synthesis", "a inf skinned"], "repeat"),
    (["a inf skinned neighbors=2"], "synthesis tiers only"),
    (["a inf synthesis colour=red"], "unknown key"),
    (["a inf synthesis neighbors=0"], ">= 1"),
    (["a inf synthesis projection=-1"], ">= 0"),
    (["a inf synthesis pose_model=magic"], "one of"),
    (["a inf skinned pose_model=examples"], "synthesis tiers only"),
    (["a inf fancy"], "kind"),
    (["a -1 synthesis"], "> 0"),
    (["a"], "needs"),
])
def test_bad_tier_lines_are_rejected_with_the_reason(lines, words):
    with pytest.raises(ValueError, match=words):
        parse_tiers(lines)


def test_tier_hysteresis_holds_a_tier_near_its_boundary():
    lod = LodPolicy(tiers=parse_tiers(["near 3 synthesis", "mid 8 synthesis", "far inf skinned"]), hysteresis=0.5)
    assert lod.tier(2.0, None) == 0 and lod.tier(5.0, None) == 1
    assert lod.tier(3.3, 0) == 0  # just outside: stays near
    assert lod.tier(3.6, 0) == 1
    assert lod.tier(2.7, 1) == 1  # just inside: stays mid
    assert lod.tier(2.4, 1) == 0
    assert lod.tier(2.0, 2) == 0  # a jump lands where it belongs
    assert lod.tier(30.0, 0) == 2
    assert lod.tier(8.2, 2) == 2 and lod.tier(7.4, 2) == 1


def test_viewing_cone_with_margin_and_agent_radius():
    lod = LodPolicy(fov_deg=90.0, margin_deg=10.0, agent_radius=1.0)
    viewer = Viewer.from_pose((0.0, 0.0, 0.0), LOOK_X)
    assert lod.visible(viewer, (10.0, 0.0, 0.0))
    assert not lod.visible(viewer, (-10.0, 0.0, 0.0))
    # 50 degrees off axis: outside 45 degrees but inside the margin
    assert lod.visible(viewer, (10.0 * math.cos(math.radians(50)), 10.0 * math.sin(math.radians(50)), 0.0))
    assert not lod.visible(viewer, (10.0 * math.cos(math.radians(70)), 10.0 * math.sin(math.radians(70)), 0.0))
    assert lod.visible(viewer, (-0.5, 0.0, 0.0))  # within its own radius: always
    assert not LodPolicy(cull=True).visible(viewer, (-10.0, 0.0, 0.0))
    assert LodPolicy(cull=False).visible(viewer, (-10.0, 0.0, 0.0))


def test_viewer_pose_orientation_and_fixed_offset():
    yaw90 = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))
    assert np.allclose(quaternion_forward(*yaw90), (0.0, 1.0, 0.0), atol=1e-12)
    viewer = Viewer.from_pose((1.0, 0.0, 0.0), LOOK_X, offset=(10.0, 0.0, 1.0, math.pi / 2))
    assert np.allclose(viewer.position, (10.0, 1.0, 1.0)) and np.allclose(viewer.forward, (0.0, 1.0, 0.0))
    with pytest.raises(ValueError):
        quaternion_forward(0.0, 0.0, 0.0, 0.0)


# ---- the budget scheduler ---------------------------------------------------------------------------------------
COSTS = [1.0, 0.6, 0.2, 0.2]  # ms per level: near, mid, far (skinned), distant (skinned)


def _candidates(distances, tiers, skipped=()):
    return [Candidate(f"a{i}", d, t, COSTS, int(f"a{i}" in skipped)) for i, (d, t) in enumerate(zip(distances, tiers))]


def test_scheduler_keeps_every_agent_at_its_tier_inside_the_budget():
    decisions = schedule(_candidates([1, 5, 12], [0, 1, 2]), budget_ms=8.0)
    assert [(d.level, d.degraded) for d in decisions] == [(0, False), (1, False), (2, False)]


def test_scheduler_lowers_the_farthest_first_and_never_the_near_ones():
    distances = [1.0, 2.0, 4.0, 6.0, 7.0, 9.0]
    tiers = [0, 0, 1, 1, 1, 2]
    decisions = {d.key: d for d in schedule(_candidates(distances, tiers), budget_ms=3.6)}
    assert decisions["a0"].level == 0 and decisions["a1"].level == 0  # near: untouched
    # 4.0 ms asked: the farthest (a5) goes first, and since its lowest level costs what its tier does it waits this
    # tick (3.8 ms); then a4 drops from mid to far (3.4 ms): within the budget, so the nearer mid agents are kept
    assert decisions["a5"].level is None and decisions["a5"].degraded
    assert decisions["a4"].level == 2 and decisions["a4"].degraded
    assert all(decisions[k].level == 1 and not decisions[k].degraded for k in ("a2", "a3"))
    total = sum(d.estimate for d in decisions.values())
    assert total <= 3.6 + 1e-9
    # The farthest is touched before any nearer one: lowering is monotone in distance.
    lowered = [d.key for d in decisions.values() if d.degraded]
    assert lowered and max(distances[int(k[1:])] for k in decisions if k not in lowered and tiers[int(k[1:])] > 0) \
        <= min(distances[int(k[1:])] for k in lowered)


def test_scheduler_skips_far_agents_on_alternate_ticks_when_lowering_is_not_enough():
    distances = [1.0] + [20.0 + i for i in range(6)]
    tiers = [0] + [3] * 6
    budget = 1.0 + 3 * 0.2 + 1e-9  # the near agent and three far ones
    first = schedule(_candidates(distances, tiers), budget)
    skipped = {d.key for d in first if d.level is None}
    assert len(skipped) == 3 and "a0" not in skipped
    assert skipped == {"a4", "a5", "a6"}  # the farthest
    second = schedule(_candidates(distances, tiers, skipped), budget)
    assert {d.key for d in second if d.level is None} == {"a1", "a2", "a3"}  # the others' turn
    assert all(d.degraded for d in first if d.level is None)


def test_scheduler_lets_no_agent_wait_longer_than_max_wait():
    candidates = _candidates([1.0, 20.0, 30.0], [0, 3, 3])
    candidates[2].waited = 9
    decisions = {d.key: d for d in schedule(candidates, budget_ms=1.0, max_wait=9)}
    assert decisions["a1"].level is None  # no room: skipped
    assert decisions["a2"].level == 3 and decisions["a2"].degraded is False  # waited long enough: dressed


def test_scheduler_never_drops_near_agents_even_over_budget():
    decisions = schedule(_candidates([1.0, 1.5, 2.0], [0, 0, 0]), budget_ms=0.5)
    assert all(d.level == 0 and not d.degraded for d in decisions)
    assert all(d.level == 1 for d in schedule(_candidates([5.0, 6.0], [1, 1]), budget_ms=0.0))  # 0: no budget


def test_scheduler_defers_far_near_agents_a_tick_when_they_alone_overfill_it():
    """Near agents are never lowered; when their poses arrive together, the farthest wait a tick or two (never
    the nearest, never more than near_wait ticks in a row) so their cost spreads over the ticks between poses."""
    candidates = _candidates([1.0, 1.5, 2.0, 2.5], [0, 0, 0, 0])  # 1 ms each at level 0
    decisions = {d.key: d for d in schedule(candidates, budget_ms=2.0, near_wait=2)}
    assert [decisions[k].level for k in ("a0", "a1", "a2", "a3")] == [0, 0, None, None]
    assert all(d.level in (0, None) for d in decisions.values())  # deferred, never lowered
    for c in candidates:  # the deferred ones waited: they go first next time, the others may wait
        c.waited = 1 if decisions[c.key].level is None else 0
    second = {d.key: d for d in schedule(candidates, budget_ms=2.0, near_wait=2)}
    assert second["a1"].level is None  # not deferred last tick: its turn
    assert [second[k].level for k in ("a0", "a1", "a2", "a3")].count(None) == 2
    for c in candidates:
        c.waited = 2
    assert all(d.level == 0 for d in schedule(candidates, budget_ms=2.0, near_wait=2))  # waited enough


# ---- a scene on the shipped databases ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def walk():
    from agentdress_ros.motion.procedural import make_motion

    return make_motion("walk", 1.0)


@pytest.fixture()
def scene(body):
    scene = Scene(body, SceneConfig(budget_ms=0.0, fade_frames=4))
    yield scene
    scene.stop()


def _add(scene, name, beta=BETA0, **spec):
    agent = scene.build_agent(AgentSpec(name, GARMENTS, tuple(beta), **spec))
    scene.install(agent)
    return agent


class Published:
    def __init__(self):
        self.frames = {}

    def __call__(self, agent, frames, stamp_ns):
        self.frames[agent.name] = {g: None if v is None else v.copy() for g, v in frames.items()}


def test_agents_share_garment_data_and_hold_a_small_state(scene, body, walk):
    a = _add(scene, "a")
    b = _add(scene, "b", (0.2, 0.5, 0.5, 0.8, 0.3, 0.5))
    assert len(scene.library) == 2  # one loaded model per garment, whatever the number of agents
    for name in ("tshirt", "trousers"):
        ga, gb = a.garments[name].base, b.garments[name].base
        assert ga.db is gb.db and ga.pose_model.canonical is gb.pose_model.canonical
        assert ga._buffers[0] is not gb._buffers[0] and ga.pose_model.out is not gb.pose_model.out
    own = a.memory_bytes(scene.library.models())
    assert 0 < own < 5e6, own


def _single_agent(body, beta, publish_body=False, subdivision=0):
    """The single agent's models of GARMENTS on `beta` (the body too with publish_body), dressed for display."""
    from agentdress_ros.display.models import dress_for_display
    from agentdress_ros.models.garment_models import make_body_model, make_garment_model

    models = {g.name: make_garment_model(g.name, g.database, None, body, beta, g.engine.config()) for g in GARMENTS}
    if publish_body:
        models["body"] = make_body_model(body, beta)
    return dress_for_display(models, body, {}, subdivision, beta)


def test_each_agent_gets_its_own_correct_clouds(scene, body, walk):
    shapes = {"a": BETA0, "b": (0.2, 0.5, 0.5, 0.8, 0.3, 0.5)}
    for name, beta in shapes.items():
        _add(scene, name, beta)
    published = Published()
    rot, root = walk.rotvecs, walk.root_translation
    scene.agents["a"].pose.set(rot[3], root[3])
    scene.agents["b"].pose.set(rot[17], root[17] + (2.0, 0.0, 0.0))
    scene.tick(published)
    assert set(published.frames) == {"a", "b"}
    for name, frame in ((("a", 3)), ("b", 17)):
        single = _single_agent(body, shapes[name])
        offset = (2.0, 0.0, 0.0) if name == "b" else (0.0, 0.0, 0.0)
        for garment, model in single.items():  # the trousers first: the T-shirt is layered out of them
            expected = model.synthesize(rot[frame], root[frame] + offset)
            assert np.allclose(published.frames[name][garment], expected, atol=1e-5)
    assert not np.allclose(published.frames["a"]["tshirt"], published.frames["b"]["tshirt"], atol=1e-2)


def test_an_agent_is_dressed_for_display_exactly_as_the_single_agent(scene, body, walk):
    """Layered, refined, its edges kept off its drawn body: the near tier's frames are the single agent's, bit for
    bit, through a shape refit too (the display bindings are made again for the new shape)."""
    beta = (0.2, 0.5, 0.5, 0.8, 0.3, 0.5)
    agent = _add(scene, "a", beta, publish_body=True, subdivision=1)
    single = _single_agent(body, beta, publish_body=True, subdivision=1)
    assert list(agent.garments) == list(single) == ["trousers", "tshirt", "body"]
    for name, model in single.items():
        assert agent.garments[name].n_vertices == model.n_vertices > (1000 if name != "body" else 0)
        np.testing.assert_array_equal(agent.garments[name].faces, model.faces)
        assert agent.garments[name].skin_binding() is None or name == "body"
    far = agent.garments["tshirt"]  # the shipped farther tiers draw without display stages (display=none)
    assert [far.topology_at(level) for level in range(4)] == ["display", "coarse", "coarse", "coarse"]
    assert len(far.faces_at(2)) == len(far.coarse_faces) < len(far.faces_at(0))
    for frame in (0, 5, 10, 15):
        rotvecs, root = walk.rotvecs[frame], walk.root_translation[frame]
        dressed = {n: np.array(g.dress(0, rotvecs, root)) for n, g in agent.garments.items()}
        for name, model in single.items():
            np.testing.assert_array_equal(dressed[name], model.synthesize(rotvecs, root))
    refit = (0.7, 0.3, 0.5, 0.4, 0.6, 0.5)
    scene.request_shape("a", refit)
    deadline = time.monotonic() + 60.0
    while not (scene.idle() and agent.beta == refit) and time.monotonic() < deadline:
        time.sleep(0.05)
    single = _single_agent(body, refit, publish_body=True, subdivision=1)
    for name in agent.garments:
        agent.garments[name].reset()
    for frame in (20, 25):
        rotvecs, root = walk.rotvecs[frame], walk.root_translation[frame]
        for name, model in single.items():
            np.testing.assert_array_equal(np.array(agent.garments[name].dress(0, rotvecs, root)),
                                          model.synthesize(rotvecs, root))


def test_a_batch_of_agents_pose_models_answers_as_each_one_alone(scene, walk):
    """engine.pose_models.predict_batch over two agents' pose models (forks on shared examples): each answer is
    that model's own evaluate from the same state; a batch whose lengths disagree is refused."""
    from agentdress_ros.engine.pose_models import canonical_poses, predict_batch

    agents = [_add(scene, "a"), _add(scene, "b", (0.2, 0.5, 0.5, 0.8, 0.3, 0.5))]
    models = [agent.garments["tshirt"].base.pose_model for agent in agents]
    thetas = list(canonical_poses(walk.rotvecs[[3, 9]]))
    roots = [walk.root_translation[3], walk.root_translation[9]]
    for model in models:
        model.reset()
    batch = [np.array(out) for out in predict_batch(models, thetas, roots)]
    for model, theta, root, out in zip(models, thetas, roots, batch):
        model.reset()
        np.testing.assert_array_equal(out, model.evaluate(theta, root, None))
    assert not np.array_equal(batch[0], batch[1])
    with pytest.raises(ValueError, match="2 models for 1 poses"):
        predict_batch(models, thetas[:1], roots[:1])


def test_an_agent_runs_the_garment_model_its_spec_names(scene, body, walk):
    """garment_models in a crowd: a garment whose spec names Santesteban et al.'s system dresses, at every tier,
    exactly as the single agent's model of that name (the same maker, the same shape)."""
    from agentdress_ros.models.garment_models import make_garment_model

    beta = (0.2, 0.5, 0.5, 0.8, 0.3, 0.5)
    spec = GarmentSpec("tshirt", database=str(DATA / "tshirt_default.h5"), model="santesteban")
    agent = scene.build_agent(AgentSpec("s", (spec,), beta))
    scene.install(agent)
    single = make_garment_model("tshirt", DATA / "tshirt_default.h5", None, body, beta, model="santesteban")
    assert agent.garments["tshirt"].kind == single.kind == "santesteban"
    for level, frame in enumerate((2, 9, 14, 20)):  # one frame per tier
        dressed = agent.garments["tshirt"].dress(level, walk.rotvecs[frame], walk.root_translation[frame])
        expected = single.synthesize(walk.rotvecs[frame], walk.root_translation[frame])
        np.testing.assert_array_equal(dressed, np.asarray(expected, dtype=np.float32))


def test_an_agents_body_is_masked_by_its_garments_as_the_single_agents(scene, body, walk):
    """publish_body in a crowd: the body without the faces its garments cover, its band under their edges sunk,
    exactly the single agent's (display.models.dress_for_display), at every tier."""
    from agentdress_ros.display.models import dress_for_display
    from agentdress_ros.models.garment_models import make_body_model, make_garment_model

    beta = (0.2, 0.5, 0.5, 0.8, 0.3, 0.5)
    agent = _add(scene, "a", beta, publish_body=True)
    models = {g.name: make_garment_model(g.name, g.database, None, body, beta, g.engine.config()) for g in GARMENTS}
    single = dress_for_display({**models, "body": make_body_model(body, beta)}, body, {}, 0, beta)["body"]
    masked = agent.garments["body"]
    assert len(single.faces) < len(make_body_model(body).faces)
    np.testing.assert_array_equal(masked.faces, single.faces)
    for level, frame in enumerate((4, 8, 12, 16)):
        rotvecs, root = walk.rotvecs[frame], walk.root_translation[frame]
        np.testing.assert_array_equal(masked.dress(level, rotvecs, root), single.synthesize(rotvecs, root))


def test_a_body_streamed_as_bones_is_posed_without_vertices(scene, walk):
    """bones_only (set by the crowd node while nobody takes the body's points, only its bones): the body's frame is
    None, its bone transforms are those of the full frame, and the garments are the same as with the body's
    vertices."""
    agent = _add(scene, "a", publish_body=True)
    frames, transforms = [], []
    for bones_only in (False, True):
        agent.garments["body"].bones_only = bones_only
        agent.pose.set(walk.rotvecs[6], walk.root_translation[6])
        published = Published()
        assert scene.tick(published).dressed == ["a"]
        frames.append(published.frames["a"])
        transforms.append(agent.garments["body"].base.transforms.copy())
    assert frames[0]["body"].shape == (13380, 3) and frames[1]["body"] is None
    assert np.array_equal(transforms[0], transforms[1])
    for garment in ("tshirt", "trousers"):
        assert np.allclose(frames[0][garment], frames[1][garment], atol=1e-6)


def test_idle_agents_cost_nothing(scene, walk):
    agent = _add(scene, "a")
    agent.pose.set(walk.rotvecs[0], walk.root_translation[0])
    assert scene.tick().dressed == ["a"]
    report = scene.tick()
    assert report.dressed == [] and report.idle == 1
    agent.pose.set(walk.rotvecs[1], walk.root_translation[1])
    assert scene.tick().dressed == ["a"]


def test_an_agent_out_of_view_is_not_dressed_and_comes_back_on_the_frame_it_returns(scene, walk):
    agent = _add(scene, "a")
    agent.pose.set(walk.rotvecs[0], (5.0, 0.0, 0.0))
    scene.set_viewer(Viewer.from_pose((0.0, 0.0, 1.6), LOOK_X))
    assert scene.tick().dressed == ["a"]
    scene.set_viewer(Viewer.from_pose((0.0, 0.0, 1.6), (0.0, 0.0, 1.0, 0.0)))  # turned around: looking along -x
    for i in range(3):
        agent.pose.set(walk.rotvecs[i + 1], (5.0, 0.0, 0.0))
        report = scene.tick()
        assert report.dressed == [] and report.culled == 1
    scene.set_viewer(Viewer.from_pose((0.0, 0.0, 1.6), LOOK_X))
    assert scene.tick().dressed == ["a"]  # back in view: dressed at once, even without a new pose
    assert scene.status()["tiers"]["mid"]["agents"] == 1


def test_a_tier_change_cross_fades_instead_of_popping(scene, walk):
    agent = _add(scene, "a")
    published = Published()
    pose = walk.rotvecs[5]
    scene.set_viewer(Viewer.from_pose((-2.0, 0.0, 0.9), LOOK_X))
    agent.pose.set(pose, (0.0, 0.0, 0.0))
    scene.tick(published)
    near = published.frames["a"]["tshirt"]
    assert agent.level == 0
    scene.set_viewer(Viewer.from_pose((-12.0, 0.0, 0.9), LOOK_X))  # 12 m: the skinned tier
    frames = []
    for _ in range(6):
        scene.tick(published)
        frames.append(published.frames["a"]["tshirt"])
    far = agent.garments["tshirt"].base.skin(pose, np.zeros(3)).copy()  # the far tier draws no display stages
    step = np.abs(far - near).max()
    assert step > 0.01  # the levels differ visibly...
    jumps = [np.abs(b - a).max() for a, b in zip([near] + frames, frames)]
    assert max(jumps) < 0.3 * step + 1e-6  # ...but no frame jumps by more than a fifth-ish of it
    assert np.allclose(frames[-1], far, atol=1e-5)  # and it lands on the far level
    assert scene.status()["tiers"]["far"]["agents"] == 1


def test_budget_holds_with_artificially_expensive_agents(body, walk):
    """Costs injected as estimates (smoothing 0 keeps them) and a stopped clock: the scheduler's decisions are
    checked, not wall time (a preempted tick would rightly spend its budget on waiting)."""
    scene = Scene(body, SceneConfig(budget_ms=3.5, cost_smoothing=0.0, fade_frames=0), clock=lambda: 0.0)
    try:
        distances = [1.5, 2.0, 5.0, 6.0, 25.0, 30.0, 35.0, 40.0]
        for i, x in enumerate(distances):
            agent = _add(scene, f"a{i}")
            agent.cost_ms = {0: 1.0, 1: 0.8, 2: 0.5, 3: 0.5}
        scene.set_viewer(Viewer.from_pose((0.0, 0.0, 0.9), LOOK_X))
        dressed_count = {f"a{i}": 0 for i in range(len(distances))}
        for t in range(18):  # two rounds of the distant tier's every=6, two max_waits
            for i, x in enumerate(distances):
                scene.agents[f"a{i}"].pose.set(walk.rotvecs[t], (x, 0.0, 0.0))
            report = scene.tick()
            assert {"a0", "a1"} <= set(report.dressed)  # the near ones every tick
            assert report.estimate_ms <= 3.5 + 1e-9
            for name in report.dressed:
                dressed_count[name] += 1
        tiers = scene.status()["tiers"]
        assert tiers["near"]["degraded_frames"] == 0
        assert tiers["distant"]["degraded_frames"] + tiers["mid"]["degraded_frames"] > 0
        assert all(count >= 2 for count in dressed_count.values()), dressed_count  # nobody starves
    finally:
        scene.stop()


def test_the_budget_keeps_free_the_recent_misses_of_its_estimates(body, walk):
    """Each dressing tick records how far it ran past its plan; the budget then leaves the MARGIN_QUANTILE of the
    recent misses free (at most half of it), so a tick's high quantile, not only its mean, stays inside."""
    from agentdress_ros.scene.scene import MARGIN_QUANTILE, MARGIN_WINDOW

    scene = Scene(body, SceneConfig(budget_ms=8.0, cost_smoothing=0.0, fade_frames=0))
    try:
        for _ in range(MARGIN_WINDOW):  # a burst every third tick (poses arrive at a third of the tick rate)
            scene.ticks += 1
            scene._note_miss(2.0 if scene.ticks % 3 == 0 else -0.1)
        assert 100.0 * (2.0 / 3.0) < MARGIN_QUANTILE and scene.margin_ms == pytest.approx(2.0)
        assert scene._dressing_budget(time.perf_counter()) <= 8.0 - 2.0
        for _ in range(MARGIN_WINDOW):
            scene.ticks += 1
            scene._note_miss(100.0)
        assert scene.margin_ms == 4.0  # never more than half the budget
        # a real tick: an agent whose estimate says 0.1 ms but spins 3 ms records a miss of about 3 ms
        agent = _add(scene, "slow", extra_cost_ms=3.0)
        scene.set_viewer(Viewer.from_pose((0.0, 0.0, 0.9), LOOK_X))
        agent.pose.set(walk.rotvecs[0], (2.0, 0.0, 0.0))
        scene.tick()  # measures the level's real cost
        agent.cost_ms = {level: 0.1 for level in range(4)}
        agent.pose.set(walk.rotvecs[1], (2.0, 0.0, 0.0))
        assert scene.tick().dressed == ["slow"]
        assert scene._misses[-1] >= 2.5
    finally:
        scene.stop()


def test_only_agents_the_next_tick_may_dress_need_their_input(scene, walk):
    near, distant, behind = (_add(scene, name) for name in ("near", "distant", "behind"))
    assert all(scene.needs_input(a) for a in (near, distant, behind))  # never placed yet
    scene.set_viewer(Viewer.from_pose((0.0, 0.0, 0.9), LOOK_X))
    for agent, x in ((near, 2.0), (distant, 40.0), (behind, -5.0)):
        agent.pose.set(walk.rotvecs[0], (x, 0.0, 0.0))
    due = []
    for _ in range(6):
        scene.tick()
        assert scene.needs_input(near) and not scene.needs_input(behind)  # culled: its poses can wait
        due.append(scene.needs_input(distant))
    assert due.count(True) == 1  # the distant tier dresses every sixth tick
    scene.set_viewer(None)
    assert scene.needs_input(behind)  # without a viewer every agent may be dressed


def test_agents_are_added_and_refitted_off_the_frame_path_and_removed(scene, walk):
    scene.request_agent(AgentSpec("late", GARMENTS, BETA0))
    deadline = time.monotonic() + 60.0
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert "late" not in scene.agents  # installed by the next tick, on the frame thread
    scene.tick()
    agent = scene.agents["late"]
    before = agent.garments["tshirt"].base.shape_report.effective.copy()
    scene.request_shape("late", (0.3, 0.5, 0.5, 0.7, 0.5, 0.5))
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    after = agent.garments["tshirt"].base.shape_report.effective
    assert not np.allclose(before, after) and agent.dirty
    assert scene.status()["refits"] == 1
    scene.request_shape("late", (0.3, 0.5, 0.5, 0.7, 0.5, 0.5))  # a repeated shape is no refit
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert scene.status()["refits"] == 1
    mid = agent.garments["tshirt"]._levels[1][1]
    assert mid._state is agent.garments["tshirt"].base._state  # every tier follows the one shape state
    assert scene.tick().dressed == ["late"]
    assert scene.remove_agent("late") and "late" not in scene.agents
    assert scene.tick().dressed == []
    errors = []
    scene.on_error = errors.append
    scene.request_agent(AgentSpec("broken", (GarmentSpec("tshirt", database="/nonexistent.h5"),)))
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert errors and "broken" in errors[0] and "nonexistent" in errors[0]
    # skinned_fallback: the garment's skinned template instead, reported; the agent lives and refits
    errors.clear()
    scene.request_agent(AgentSpec("fallback", (GarmentSpec("tshirt", database="/nonexistent.h5"),),
                                  skinned_fallback=True))
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert scene.tick().dressed == ["fallback"]
    assert scene.agents["fallback"].garments["tshirt"].kind == "skinned"
    assert len(errors) == 1 and "nonexistent" in errors[0] and "skinned_fallback" in errors[0]
    scene.request_shape("fallback", (0.3, 0.5, 0.5, 0.7, 0.5, 0.5))
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(errors) == 1 and scene.agents["fallback"].shape_generation == 1


def test_parse_tier_names_the_line():
    with pytest.raises(ValueError, match="'x 3'"):
        parse_tier("x 3")


def test_agents_of_one_shape_share_its_state_until_one_changes(scene):
    a, b = _add(scene, "a"), _add(scene, "b")
    ta, tb = a.garments["tshirt"].base, b.garments["tshirt"].base
    assert ta._state is tb._state  # fitted once for both
    scene.request_shape("b", (0.3, 0.5, 0.5, 0.7, 0.5, 0.5))
    deadline = time.monotonic() + 60.0
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert ta._state is not tb._state and np.allclose(ta.shape_report.effective, BETA0)
    state = tb._state
    scene.request_shape("b", (0.3, 0.5, 0.5, 0.7, 0.5, 0.5))  # the same shape again: nothing to do
    while not scene.idle() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert tb._state is state


def test_tiers_and_visibility_of_many_agents_match_one_at_a_time():
    rng = np.random.default_rng(5)
    lod = LodPolicy(tiers=parse_tiers(["near 3 synthesis", "mid 8 synthesis", "far 20 skinned",
                                       "distant inf skinned every=3"]))
    distances = np.concatenate([rng.uniform(0.0, 40.0, 400), [3.0, 3.5, 8.0, 8.5, 20.0, 2.5, 7.5]])
    current = rng.integers(-1, 4, len(distances))
    together = lod.tiers_of(distances, current)
    alone = [lod.tier(d, None if c < 0 else int(c)) for d, c in zip(distances, current)]
    assert together.tolist() == alone
    viewer = Viewer.from_pose((0.5, -1.0, 1.6), (0.0, 0.0, np.sin(0.3), np.cos(0.3)))
    centres = rng.uniform(-30.0, 30.0, (400, 3))
    centres[:5] = viewer.position + rng.uniform(-0.5, 0.5, (5, 3))  # within the agent radius: always visible
    seen = lod.visible_of(viewer, centres)
    assert seen[:5].all() and 0 < seen.sum() < len(seen)
    # analytic: the cone's half-angle is 55 + 10 degrees, widened by asin(radius / distance)
    d = centres - viewer.position
    r = np.linalg.norm(d, axis=1)
    angle = np.degrees(np.arccos(np.clip(d @ viewer.forward / r, -1, 1)))
    expected = (r <= 1.0) | (angle <= 65.0 + np.degrees(np.arcsin(np.minimum(1.0, 1.0 / r))))
    assert seen.tolist() == expected.tolist()
