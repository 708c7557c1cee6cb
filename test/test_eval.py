"""`agentdress eval --quick` on the shipped database: a held-out drape from newton, every trade-table row measured."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from .conftest import shared_path

from agentdress_ros.evaluate.evaluate import BASELINE, evaluate, trade_rows
from agentdress_ros.evaluate.testset import HELD_OUT_CLIPS

DATABASE = Path(__file__).resolve().parents[1] / "data" / "tshirt_default.h5"
GROUPS = {"baseline", "pose model", "default", "neighbors", "anchors", "components", "refinement", "ablation",
          "precision"}


@pytest.fixture(scope="module")
def quick_eval(tmp_path_factory):
    if not DATABASE.is_file():
        pytest.skip(f"{DATABASE} is not built")
    clip = shared_path("mocap", "cmu", f"{HELD_OUT_CLIPS[0]}.bvh")
    folder = tmp_path_factory.mktemp("eval")
    report = evaluate(DATABASE, folder / "report", folder / "cache", clips=[clip], quick=True, workers=0,
                      progress=False)
    return folder, report


def test_quick_eval_measures_every_row_with_finite_numbers(quick_eval):
    folder, report = quick_eval
    rows = report["rows"]
    assert rows[0]["name"] == BASELINE
    assert GROUPS <= {r["group"] for r in rows}
    assert [r["name"] for r in rows] == [r.name for r in trade_rows(report["database_anchors"],
                                                                      report["database_components"])]
    neighbors = {r["config"]["neighbors"] for r in rows if r["group"] == "neighbors"}
    assert neighbors == {1, 3, 8}
    for r in rows:
        for key in ("error_mean_cm", "error_p95_cm", "inside_fraction", "ms_per_frame", "jitter_mm"):
            assert math.isfinite(r[key]) and r[key] >= 0.0, (r["name"], key, r[key])
        assert r["error_p95_cm"] >= r["error_mean_cm"] * 0.5
        assert len(r["error_per_shape_cm"]) == 2  # one shape inside, one just outside the training range
    assert report["test_set"]["shape_labels"] == ["inside", "outside"]
    # losers are named, the baseline is never its own loser
    assert BASELINE not in report["loses_to_baseline"]
    assert set(report["loses_to_baseline"]) == {r["name"] for r in rows[1:] if not r["beats_baseline"]}


def test_quick_eval_writes_table_json_and_plots(quick_eval):
    folder, report = quick_eval
    out = folder / "report"
    assert json.loads((out / "report.json").read_text())["rows"][0]["name"] == BASELINE
    table = (out / "trade.md").read_text().splitlines()
    body = [line for line in table if line.startswith("| ") and not line.startswith("| # |")
            and not line.startswith("| extreme")]
    assert len(body) == len(report["rows"]) + len(report["stability"])
    for name in ("pareto.png", "anchors.png", "shape_distance.png"):
        assert (out / name).stat().st_size > 10_000


def test_stability_cases_stay_finite_and_near_the_skinned_garment(quick_eval):
    _, report = quick_eval
    assert len(report["stability"]) >= 10
    for case in report["stability"]:
        assert case["non_finite"] == 0 and case["rejected_frames"] == 0, case
        assert case["max_deviation_from_skinned_cm"] < 50.0, case


def test_ground_truth_is_cached_and_reused(quick_eval, tmp_path):
    folder, report = quick_eval
    clip = shared_path("mocap", "cmu", f"{HELD_OUT_CLIPS[0]}.bvh")
    drapes = sorted((folder / "cache" / "drapes").glob("*.npz"))
    assert len(drapes) == report["test_set"]["drapes"] == 2
    stamps = [p.stat().st_mtime_ns for p in drapes]
    again = evaluate(DATABASE, tmp_path / "again", folder / "cache", clips=[clip], quick=True, workers=0,
                     progress=False)
    assert [p.stat().st_mtime_ns for p in drapes] == stamps  # no drape simulated twice
    first = {r["name"]: r["error_mean_cm"] for r in report["rows"]}
    for r in again["rows"]:
        np.testing.assert_allclose(r["error_mean_cm"], first[r["name"]], rtol=1e-5)


def test_training_clips_are_refused(quick_eval, tmp_path):
    from agentdress_ros.engine import read_database

    built_from = read_database(DATABASE).provenance["config"]["clips"]
    if not built_from:
        pytest.skip("the database was built from procedural motion only")
    with pytest.raises(ValueError, match="used to build the database"):
        clip = shared_path("mocap", "cmu", Path(built_from[0]).name)
        evaluate(DATABASE, tmp_path / "x", tmp_path / "cache", clips=[clip], quick=True, workers=0,
                 progress=False)
