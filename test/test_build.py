"""The offline stage end to end on tiny inputs: real newton drapes, a real HDF5 database, an interrupted build."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("newton", reason="newton (the build extra, requirements/build.txt) is not installed")
pytest.importorskip("dask.distributed", reason="dask distributed (requirements/build.txt) is not installed")

from agentdress_ros.build.builder import BuildConfig, build_database  # noqa: E402
from agentdress_ros.build.shape_model import fit_shape_model  # noqa: E402
from agentdress_ros.build.shapes import shape_scale, training_shapes  # noqa: E402
from agentdress_ros.engine.database import read_database  # noqa: E402

# A coarse garment, two anchors, five shapes, short drapes: every stage runs, in about a minute.
TINY = dict(garment="tshirt", garment_vertices=700, anchors=2, shapes=5, components=4, examples=3,
            sequence_frames=2, holdout_anchors=1, procedural=["walk", "wave"],
            drape={"max_frames": 40, "min_frames": 8})
TINY_ARGS = ["--garment", "tshirt", "--vertices", "700", "--anchors", "2", "--shapes", "5", "--components", "4",
             "--examples", "3", "--sequence-frames", "2", "--holdout-anchors", "1", "--procedural", "walk", "wave",
             "--drape", json.dumps(TINY["drape"]), "--quiet"]


@pytest.fixture(scope="module")
def tiny_build(tmp_path_factory):
    out = tmp_path_factory.mktemp("build") / "tiny.h5"
    report = build_database(BuildConfig(**TINY), out, workers=2, progress=False, command="test tiny build")
    return out, report


def test_tiny_database_builds_and_reads_back(tiny_build):
    out, report = tiny_build
    db = read_database(out)
    assert db.n_anchors == 2 and db.training_betas.shape == (5, 6) and db.n_components == 4
    assert db.example_drapes.shape == (3, db.n_vertices, 3) and db.sequence_drapes.shape == (2, db.n_vertices, 3)
    assert db.build_command == "test tiny build" and db.provenance["config"]["anchors"] == 2
    assert report["drapes"] == 2 * 5 + 1 + 1 + 2  # anchors x shapes, held-out, extra example, sequence
    assert report["drape_vertices_inside_body_max"] == 0
    assert np.isfinite(db.pca_mean).all() and np.isfinite(db.ridge).all()
    # the drapes moved the cloth off its skinned warm start: the database holds information LBS does not
    assert report["drape_displacement_mean_mm"] > 5.0
    assert report["coverage_weighted_kmeans"] <= report["coverage_uniform"] + 1e-12


def test_shape_model_errors_are_reported(tiny_build):
    # Five shapes varying gender only and 40-frame drapes: a sanity bound; the acceptance numbers (< 2 mm train,
    # < 5 mm held-out) are measured on full builds and recorded in the README.
    out, report = tiny_build
    assert 0.0 < report["shape_model_train_error_mm"] < 10.0
    assert 0.0 < report["shape_model_holdout_error_mm"] < 20.0


def test_shape_model_is_exact_on_a_quadratic_family():
    """Analytic truth: drapes that are exactly linear in (z, z^2) are reproduced to round-off (alpha -> 0)."""
    rng = np.random.default_rng(0)
    betas = training_shapes(17)
    scale = shape_scale()
    z = (betas - betas[0]) / scale
    basis = rng.normal(size=(12, 50, 3))
    drapes = rng.normal(size=(50, 3)) + np.tensordot(np.hstack([z, z**2]), basis, axes=(1, 0)) * 1e-3
    model = fit_shape_model(drapes, betas, betas[0], scale, n_components=12, alpha=1e-12)
    np.testing.assert_allclose(model.predict(betas), drapes, atol=1e-9)


def _drape_files(out: Path):
    return sorted((out.parent / (out.name + ".work") / "drapes").glob("*.npz"))


def test_killed_build_resumes_to_the_same_database(tiny_build, tmp_path):
    reference_path, _ = tiny_build
    out = tmp_path / "resumed.h5"
    command = [sys.executable, "-m", "agentdress_ros.cli", "build", *TINY_ARGS, "--workers", "0", "--out", str(out)]
    process = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while len(_drape_files(out)) < 3 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert process.poll() is None, f"the build ended before it could be killed: {process.stderr.read()[-2000:]}"
    os.killpg(process.pid, signal.SIGKILL)  # at any moment: here, with drapes done and one in flight
    process.wait()
    assert not out.exists(), "no database file from a killed build"
    done = {p.name: p.stat().st_mtime_ns for p in _drape_files(out)}
    assert len(done) >= 3

    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    for name, mtime in done.items():  # finished drapes are reused, not redone
        assert (out.parent / (out.name + ".work") / "drapes" / name).stat().st_mtime_ns == mtime
    resumed, reference = read_database(out), read_database(reference_path)
    for field in ("rest", "anchor_poses", "pca_mean", "pca_components", "ridge", "example_drapes", "sequence_drapes",
                  "region_dof", "joint_weights"):
        np.testing.assert_array_equal(getattr(resumed, field), getattr(reference, field), err_msg=field)


def test_resuming_with_other_parameters_is_refused(tiny_build, tmp_path):
    out = tmp_path / "db.h5"
    work = tmp_path / "db.h5.work"
    work.mkdir()
    (work / "plan.pkl").write_bytes((tiny_build[0].parent / "tiny.h5.work" / "plan.pkl").read_bytes())
    with pytest.raises(ValueError, match="belongs to a build with other parameters"):
        build_database(BuildConfig(**{**TINY, "anchors": 3}), out, workers=0, progress=False)
