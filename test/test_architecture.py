"""The layer order of docs/architecture.md: import-linter's contracts (.importlinter) hold, every package has its
place in them, and one dressed frame of the node's path loads no evaluation, offline or learning code."""
from __future__ import annotations

import configparser
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / ".importlinter"
PACKAGE = REPO / "agentdress_ros"


def test_import_contracts_hold():
    """lint-imports exits 0 only when every contract is kept; its report names the broken import chain."""
    lint = Path(sys.executable).with_name("lint-imports")
    proc = subprocess.run([str(lint), "--config", str(CONFIG), "--no-cache"], cwd=REPO, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "3 kept, 0 broken" in proc.stdout, proc.stdout[-2000:]


def _layers() -> list[str]:
    config = configparser.ConfigParser()
    config.read(CONFIG)
    rows = config["importlinter:contract:layers"]["layers"].split("\n")
    return [name.strip() for row in rows for name in row.split("|") if name.strip()]


def test_every_package_has_a_layer():
    """A package outside the layers contract would escape it: each module and sub-package of agentdress_ros is
    named exactly once."""
    found = sorted({p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
                   | {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"})
    layers = _layers()
    assert sorted(layers) == found, f"layers {layers} against packages {found}"


# One frame of what the node runs with publish_body:=true and the three shipped garments: the garment models from
# their databases, dressed for display (layers, the covered body) as the node dresses them, then synthesized.
DRESSED_FRAME = textwrap.dedent("""
    import sys
    import numpy as np
    from agentdress_ros.body import REFERENCE_SHAPE, AnnyBody
    from agentdress_ros.display.models import dress_for_display
    from agentdress_ros.models.garment_models import make_body_model, make_garment_model

    body = AnnyBody()
    databases = {"tshirt": "data/tshirt_default.h5", "trousers": "data/trousers_default.h5",
                 "longsleeve": "data/longsleeve_default.h5"}
    models = {name: make_garment_model(name, path, None, body, REFERENCE_SHAPE) for name, path in databases.items()}
    models["body"] = make_body_model(body, REFERENCE_SHAPE)
    dressed = dress_for_display(models, body, {}, 1, REFERENCE_SHAPE)
    pose = np.zeros((len(body.assets.bone_names), 3))
    pose[body.assets.bone_names.index("LeftArm"), 2] = 0.4
    for name, model in dressed.items():
        vertices = np.asarray(model.synthesize(pose, np.zeros(3)))
        assert vertices.shape == (model.n_vertices, 3) and np.isfinite(vertices).all(), name
    print(sorted(dressed))
    loaded = sorted(m for m in sys.modules
                    if m.startswith(("agentdress_ros.offline", "agentdress_ros.evaluate", "agentdress_ros.sim"))
                    or m.split(".")[0] in ("sklearn", "jax", "newton", "warp", "rclpy"))
    sys.exit("loaded: " + " ".join(loaded) if loaded else 0)
""")


def test_dressed_frame_loads_no_offline_code():
    """Garment models of the three shipped databases, the body published (covered faces), one frame: no module of
    agentdress_ros.offline, .evaluate or .sim, of scikit-learn, JAX, newton or rclpy is imported on the way."""
    proc = subprocess.run([sys.executable, "-c", DRESSED_FRAME], cwd=REPO, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.stdout.strip() == "['body', 'longsleeve', 'trousers', 'tshirt']", proc.stdout
