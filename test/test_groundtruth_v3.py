"""Ground truth v3 (several drapes per held-out case) and its scoring against physics' own spread, checked on
hand-made drapes where the answer is known in closed form, and on the real plan of the shipped T-shirt."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agentdress_ros.evaluate.groundtruth_v3 import RAMPS, drape_key, summary, v3_drapes, V3Case
from agentdress_ros.evaluate.score_v3 import (case_metrics, leave_one_out, nearest, ratio_interval,
                                              surface_distance, summarise)

ROOT = Path(__file__).resolve().parents[1]


def grid(n: int = 21, size: float = 1.0):
    """A flat square (n x n vertices, side `size` m) in the z = 0 plane: ((V, 3), (F, 3))."""
    x, y = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[:-1, 1:].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel()
    return vertices, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def shifted(vertices, dx=0.0, dz=0.0):
    return vertices + np.array([dx, 0.0, dz])


def test_noise_ceiling_is_each_drape_against_the_mean_of_the_others():
    base, _ = grid(5)
    drapes = np.stack([shifted(base, dz=z) for z in (0.0, 0.01, 0.02)])  # 0, 1, 2 cm
    # drape 0 vs mean(1, 2) = 1.5 cm, drape 1 vs mean(0, 2) = 0, drape 2 vs mean(0, 1) = 1.5 cm
    assert leave_one_out(None, drapes) == pytest.approx(1.0)
    # the mean drape (1 cm) against the same three references: 0.5, 0, 0.5 cm
    assert leave_one_out(drapes.mean(axis=0), drapes) == pytest.approx(1.0 / 3.0)
    # each drape's nearest other drape is 1 cm away; a candidate at 0.4 cm is 0.4 cm from its nearest
    assert nearest(None, drapes) == pytest.approx(1.0)
    assert nearest(shifted(base, dz=0.004), drapes) == pytest.approx(0.4)


def test_surface_distance_ignores_sliding_along_the_surface():
    vertices, faces = grid(41)
    # lifted 1 cm off its plane: 1 cm both ways, as the vertex distance says
    assert surface_distance(vertices, shifted(vertices, dz=0.01), faces) == pytest.approx(1.0, rel=1e-6)
    # slid 1 cm within its plane: every vertex moved 1 cm, yet the surfaces coincide except on a 1 cm strip at the
    # two edges the slide uncovers (whose centres lie up to 1 cm from the other surface): 1 in 100 of the area
    slid = shifted(vertices, dx=0.01)
    assert case_metrics(slid, vertices[None].repeat(2, 0), faces)["to_mean_cm"] == pytest.approx(1.0)
    assert surface_distance(vertices, slid, faces) < 0.02


def test_ratio_to_ceiling_and_intervals():
    base, faces = grid(5)
    cases = []
    for k in range(12):
        drapes = np.stack([shifted(base, dz=z) for z in (0.0, 0.01, 0.02)]) + 0.001 * k
        cases.append((drapes.mean(axis=0), drapes))
    ceiling = [case_metrics(None, d, faces) for _, d in cases]
    model = [case_metrics(m, d, faces) for m, d in cases]
    report = summarise(model, ceiling)
    assert report["ratio_to_ceiling"]["mean"] == pytest.approx(1.0 / 3.0)
    low, high = report["ratio_to_ceiling"]["ci"]
    assert low == pytest.approx(1.0 / 3.0) and high == pytest.approx(1.0 / 3.0)  # the same ratio in every case
    low, high = ratio_interval([1.0, 2.0, 3.0, 4.0], [1.0, 1.0, 1.0, 1.0])
    assert 1.0 <= low < 2.5 < high <= 4.0


def _pack_of(tmp_path, entries):
    from agentdress_ros.offline.jobs import write_drape_pack

    keys = [k for k, _ in entries]
    stats = [s for _, s in entries]
    vertices = [np.full((4, 3), i, dtype=np.float32) for i in range(len(keys))]
    path = tmp_path / "v3.npz"
    write_drape_pack(path, keys, vertices, stats, json.dumps({"poses": ["a@1", "b@2"]}), {"commit": "abc"})
    from agentdress_ros.offline.jobs import read_drape_pack

    return path, read_drape_pack(path)


def test_a_case_is_kept_only_when_every_ramp_converged_extended_or_not(tmp_path):
    ok = {"frames": 200, "converged": True, "seconds": 40.0}
    failed = {"frames": 360, "converged": False, "seconds": 70.0}
    entries = [(drape_key(r, 0), ok) for r in RAMPS]  # case 0: all converged at once
    entries += [(drape_key(30, 1), failed), (drape_key(30, 1, extended=True), ok)]  # case 1: extended, converged
    entries += [(drape_key(45, 1), failed), (drape_key(45, 1, extended=True), failed)]  # never converged
    entries += [(drape_key(60, 1), ok)]
    path, pack = _pack_of(tmp_path, entries)
    report = summary(pack, [V3Case(0, "a@1", 0, "inside"), V3Case(1, "b@2", 1, "inside")])
    assert report["kept"] == [0] and report["not_converged"] == [1] and report["missing"] == []
    assert report["cases"][1]["drapes"][30] == {"frames": 200, "converged": True, "extended": True, "seconds": 40.0}
    assert report["cases"][1]["drapes"][45]["converged"] is False
    drapes, kept, _ = v3_drapes(path)
    assert kept == [0] and drapes.shape == (1, len(RAMPS), 4, 3)
    with pytest.raises(ValueError, match="another plan"):
        v3_drapes(path, expected_key=json.dumps({"poses": ["c@3"]}))


def test_the_v3_plan_covers_every_test_clip_and_shape():
    from agentdress_ros.body import AnnyBody
    from agentdress_ros.engine import read_database
    from agentdress_ros.evaluate.groundtruth_v3 import v3_plan

    db = read_database(ROOT / "data" / "tshirt_default.h5")
    cases, poses, betas, key = v3_plan(db, AnnyBody())
    assert len(cases) == 40 and poses.shape[0] == 40 and betas.shape == (40, 6)
    assert {c.shape_index for c in cases} == {0, 1, 2}
    assert {c.shape_label for c in cases} == {"inside", "outside"}
    clips = {c.pose_label.split("@")[0] for c in cases}
    mocap = (ROOT.parent / "shared" / "mocap" / "README.md").read_text()
    assert len(clips) == 10 and all(clip in mocap for clip in clips)
    assert json.loads(key)["ramps"] == list(RAMPS)
    assert v3_plan(db, AnnyBody())[3] == key  # fixed before any model work: the same plan every time
