"""The crowd driver without DDS: never a test clip, different motions and shapes, walkers facing their way."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agentdress_ros.ros.crowd_demo import (STANDING_CLIPS, TEST_CLIPS, WALKING_CLIPS, CrowdPlayer, agent_names,
                                           training_clips, viewer_pose)

from .conftest import shared_path


def test_the_held_out_clips_are_never_played():
    assert not (set(WALKING_CLIPS) | set(STANDING_CLIPS)) & TEST_CLIPS
    folder = shared_path("mocap", "cmu")
    assert not {p.stem for p in training_clips(folder, names=tuple(TEST_CLIPS) + WALKING_CLIPS)} & TEST_CLIPS


@pytest.fixture(scope="module")
def player():
    return CrowdPlayer(12, rate_hz=30.0, mocap=shared_path("mocap", "cmu"))


def test_agents_differ_in_motion_and_shape_and_stay_finite(player):
    assert agent_names(3) == ["agent_000", "agent_001", "agent_002"]
    sources = {t.name for t in player.tracks}
    assert any(s.startswith("cmu:") for s in sources) and any(s.startswith("motion:") for s in sources)
    assert len(sources) >= 8
    betas = np.array([t.beta for t in player.tracks])
    assert len(np.unique(betas.round(6), axis=0)) == len(betas) and ((betas >= 0) & (betas <= 1)).all()
    for t in (0.0, 1.7, 33.3):
        rotvecs, roots = player.frames(t)
        assert rotvecs.shape == (12, 31, 3) and roots.shape == (12, 3) and np.isfinite(rotvecs).all()
        assert np.isfinite(roots).all() and (np.abs(roots[:, :2]) < 25.0).all()


def test_walkers_face_the_way_they_walk(player):
    walkers = [i for i, t in enumerate(player.tracks) if t.walking]
    assert walkers
    r0, p0 = player.frames(2.0)
    _, p1 = player.frames(2.1)
    for i in walkers:
        step = p1[i, :2] - p0[i, :2]
        assert np.linalg.norm(step) == pytest.approx(0.12, rel=0.05)  # 1.2 m/s
        facing = Rotation.from_rotvec(r0[i, 0]).apply((0.0, -1.0, 0.0))[:2]  # the body faces -Y at rest
        cos = step @ facing / (np.linalg.norm(step) * np.linalg.norm(facing))
        assert cos > math.cos(math.radians(20))


def test_the_viewer_walks_across_and_looks_ahead():
    p0, q0 = viewer_pose(0.0)
    p1, _ = viewer_pose(1.0)
    assert p1[0] - p0[0] == pytest.approx(1.4) and p0[2] == pytest.approx(1.6) and q0 == (0.0, 0.0, 0.0, 1.0)
    _, q_back = viewer_pose(30.0)  # 42 m along a 40 m span: on the way back, facing -x
    assert q_back[2] == pytest.approx(1.0)
