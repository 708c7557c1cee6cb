"""The shipped garment databases (data/<garment>_default.h5): complete, small, reproducible from their recorded
build command and drape pack, and the engine reproduces their newton drapes at the anchor poses."""
import shlex
from pathlib import Path

import numpy as np
import pytest

from agentdress_ros.offline.builder import _plan_key
from agentdress_ros.offline.jobs import read_drape_pack
from agentdress_ros.engine.config import EngineConfig
from agentdress_ros.engine.database import read_database
from agentdress_ros.engine.engine import load_engine

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "data").glob("*_default.h5"))
MAX_BYTES = 30 * 2**20

if not SHIPPED:
    pytest.skip(f"no shipped database in {ROOT / 'data'}", allow_module_level=True)


def _pack(path: Path) -> Path:
    return path.with_name(path.name.replace(".h5", ".drapes.npz"))


@pytest.fixture(scope="module", params=SHIPPED, ids=lambda p: p.stem)
def shipped(request):
    path = request.param
    return path, read_database(path)


def test_shipped_database_is_complete_small_and_reproducible(shipped):
    path, db = shipped
    assert path.stat().st_size < MAX_BYTES
    report, config = db.provenance["report"], db.provenance["config"]
    assert not report["partial"]
    assert len(db.anchor_poses) == config["anchors"] >= 32
    assert len(db.training_betas) == config["shapes"] == 17
    assert db.garment == config["garment"] and path.stem == f"{db.garment}_default"
    # the recorded command rebuilds this file from its pack of drapes
    command = shlex.split(db.build_command)
    assert command[:2] == ["agentdress", "build"]
    assert command[command.index("--out") + 1] == f"data/{path.name}"
    packs = {command[i + 1] for i, word in enumerate(command) if word in ("--seed-drapes", "--pack-drapes")}
    assert packs == {f"data/{_pack(path).name}"}
    pack = read_drape_pack(_pack(path))
    assert pack["plan_key"] == _plan_key(config)
    assert len(pack["drapes"]) == report["drapes"]
    assert report["shape_model_train_error_mm"] < 2.0


def test_engine_reproduces_the_anchor_drapes(shipped):
    """At an anchor pose the engine returns that anchor's newton drape: exactly the beta0 drape (up to the other
    examples' residual weights and float32), a training shape within its shape model's error."""
    path, db = shipped
    engine = load_engine(path, EngineConfig(pose_model="examples"))
    anchors = (0, len(db.anchor_poses) // 2, len(db.anchor_poses) - 1)
    drapes = read_drape_pack(_pack(path))["drapes"]
    for shape_index in (0, 4, 8, 16):  # beta0, then one step of three phenotypes at +2 levels
        engine.set_shape(db.training_betas[shape_index])
        errors = []
        for s in anchors:
            engine.reset()
            out = engine.synthesize(db.anchor_poses[s])
            assert np.isfinite(out).all()
            truth = drapes[f"anchor_{s:04d}_{shape_index:02d}"][0]
            errors.append(np.linalg.norm(out - truth, axis=1).mean())
        limit = 1e-3 if shape_index == 0 else 10e-3
        assert max(errors) < limit, (shape_index, errors)


def test_shipped_data_stays_under_60_mb():
    """Everything in data/ (databases, drape packs, sequence packs) travels with every clone: at most 60 MB."""
    size = sum(p.stat().st_size for p in (ROOT / "data").iterdir() if p.is_file())
    assert size < 60 * 10**6, f"data/ holds {size / 1e6:.1f} MB"
