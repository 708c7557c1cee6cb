"""`agentdress eval --test-set v3`: accuracy against several valid drapes of each held-out case, as a ratio to
physics' own spread.

Ground truth v3 (`groundtruth_v3`) drapes every case along R paths (R = 3 ramps). For a case with drapes D_1..D_R:
- noise ceiling: each drape against the mean of the others, leave-one-out,
      ceiling = mean_r d(D_r, mean_{s != r} D_s),
  and a model M is scored the same way, against the same R - 1 drape means:
      error = mean_r d(M, mean_{s != r} D_s),
  so model and ceiling meet references made of the same number of drapes. d is the mean vertex distance (cm).
- ratio to the ceiling: mean error / mean ceiling over the cases, with a 95 % bootstrap interval (cases resampled,
  the same resamples for numerator and denominator).
- to the mean drape: d(M, mean_r D_r); to the nearest drape: min_r d(M, D_r) (the ceiling's analogue: each drape's
  nearest other drape).
- surface-to-surface: the symmetric, area-weighted distance between the two surfaces (each face centre of one to
  the closest point of the other, weighted by face area, both ways averaged), which does not count cloth sliding
  along itself as error; against the mean drape.
- face centres inside the body (winding number, as the drapes' own report).
Each figure comes with a 95 % interval over cases.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

BOOTSTRAP_DRAWS = 4000


def vertex_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean distance (cm) between corresponding vertices of (V, 3) and (V, 3)."""
    return float(np.linalg.norm(a - b, axis=1).mean() * 100.0)


def leave_one_out(candidate: np.ndarray | None, drapes: np.ndarray) -> float:
    """Mean over r of d(x_r, mean of the drapes other than r) (cm), drapes (R, V, 3); x_r = candidate (V, 3), or the
    drape r itself when candidate is None (the noise ceiling)."""
    r = len(drapes)
    total = drapes.sum(axis=0)
    out = []
    for i in range(r):
        others = (total - drapes[i]) / (r - 1)
        out.append(vertex_distance(drapes[i] if candidate is None else candidate, others))
    return float(np.mean(out))


def nearest(candidate: np.ndarray | None, drapes: np.ndarray) -> float:
    """min_r d(candidate, D_r) (cm); with candidate None, the mean over r of drape r's nearest other drape."""
    if candidate is not None:
        return min(vertex_distance(candidate, d) for d in drapes)
    return float(np.mean([min(vertex_distance(d, e) for j, e in enumerate(drapes) if j != i)
                          for i, d in enumerate(drapes)]))


def surface_distance(a: np.ndarray, b: np.ndarray, faces: np.ndarray) -> float:
    """Symmetric area-weighted surface-to-surface distance (cm) between two meshes (V, 3) of the same faces (F, 3):
    every face centre of one to the closest point on the other, weighted by its face's area, both ways averaged."""
    import trimesh

    def one_way(source, target):
        corners = source[faces]
        centres = corners.mean(axis=1)
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        _, distance, _ = trimesh.proximity.closest_point(trimesh.Trimesh(target, faces, process=False), centres)
        return float((distance * area).sum() / max(area.sum(), 1e-12) * 100.0)

    return 0.5 * (one_way(a, b) + one_way(b, a))


def interval(values, draws: int = BOOTSTRAP_DRAWS, seed: int = 0) -> list:
    """95 % percentile-bootstrap interval of the mean of per-case values (cases resampled)."""
    values = np.asarray(values, dtype=np.float64)
    picks = np.random.default_rng(seed).integers(0, len(values), size=(draws, len(values)))
    return np.percentile(values[picks].mean(axis=1), [2.5, 97.5]).tolist()


def ratio_interval(numerator, denominator, draws: int = BOOTSTRAP_DRAWS, seed: int = 0) -> list:
    """95 % bootstrap interval of mean(numerator) / mean(denominator) over the same resampled cases."""
    numerator, denominator = np.asarray(numerator, np.float64), np.asarray(denominator, np.float64)
    picks = np.random.default_rng(seed).integers(0, len(numerator), size=(draws, len(numerator)))
    return np.percentile(numerator[picks].mean(axis=1) / denominator[picks].mean(axis=1), [2.5, 97.5]).tolist()


def case_metrics(candidate: np.ndarray | None, drapes: np.ndarray, faces: np.ndarray, inside=None) -> dict:
    """Every per-case figure of one candidate (V, 3) (None: the drapes themselves, i.e. the noise ceiling)."""
    mean = drapes.mean(axis=0)
    out = {"loo_cm": leave_one_out(candidate, drapes), "nearest_cm": nearest(candidate, drapes)}
    if candidate is None:
        out["to_mean_cm"] = float(np.mean([vertex_distance(d, mean) for d in drapes]))
        out["surface_cm"] = float(np.mean([surface_distance(d, mean, faces) for d in drapes]))
        if inside is not None:
            out["inside_faces"] = float(np.mean([inside.fraction(d[faces].mean(axis=1)) for d in drapes]))
    else:
        out["to_mean_cm"] = vertex_distance(candidate, mean)
        out["surface_cm"] = surface_distance(candidate, mean, faces)
        if inside is not None:
            out["inside_faces"] = inside.fraction(candidate[faces].mean(axis=1))
    return out


METRICS = ("loo_cm", "to_mean_cm", "nearest_cm", "surface_cm", "inside_faces")


def summarise(per_case: list, ceiling: list | None = None) -> dict:
    """Means with 95 % intervals of each metric over the cases; with the ceiling's per-case figures, the ratio of
    the leave-one-out error to the ceiling and its interval."""
    out = {}
    for metric in METRICS:
        values = [c[metric] for c in per_case if metric in c]
        if values:
            out[metric] = {"mean": float(np.mean(values)), "ci": interval(values)}
    if ceiling is not None:
        model = [c["loo_cm"] for c in per_case]
        floor = [c["loo_cm"] for c in ceiling]
        out["ratio_to_ceiling"] = {"mean": float(np.mean(model) / np.mean(floor)), "ci": ratio_interval(model, floor)}
    return out


def node_default_rows(garment: str) -> list:
    """(name, EngineConfig fields or None for the skinned baseline) of the rows scored on v3: the skinned baseline,
    the examples synthesis, and the node's default engine for this garment."""
    from ..ros.params import default_engine

    default = default_engine(garment)
    return [("skinned template fitted to beta (no database)", None),
            ("synthesis, examples pose model", {"pose_model": "examples"}),
            ("node default (" + ", ".join(f"{k}={v}" for k, v in sorted(default.items())) + ")", default)]


def evaluate_v3(database, pack, out_dir=None, rows=None, progress: bool = True) -> dict:
    """Score the rows (node_default_rows) of a database on its v3 pack; writes report_v3.json and trade_v3.md into
    out_dir when given."""
    from tqdm import tqdm

    from ..body import AnnyBody
    from ..engine import read_database
    from ..garment import make_garment
    from .evaluate import InsideTest, Row, _model, synthesize_poses
    from .groundtruth_v3 import RAMPS, v3_drapes, v3_plan

    db = read_database(database)
    body = AnnyBody()
    garment = make_garment(db.garment, body, db.n_vertices)
    cases, poses, betas, key = v3_plan(db, body)
    drapes, kept, convergence = v3_drapes(pack, expected_key=key)
    faces = np.asarray(db.faces)
    rows = rows or node_default_rows(db.garment)
    inside = [InsideTest(body, betas[c], poses[c]) for c in kept]
    ceiling = [case_metrics(None, drapes[i], faces, inside[i])
               for i in tqdm(range(len(kept)), desc="ceiling", disable=not progress)]
    report = {"database": str(database), "pack": str(pack), "ramps": list(RAMPS), "cases": len(cases),
              "kept": kept, "excluded": convergence["not_converged"], "missing": convergence["missing"],
              "clips": sorted({c.pose_label.split("@")[0] for c in cases}),
              "convergence": convergence, "ceiling": summarise(ceiling), "rows": []}
    for name, config in tqdm(rows, desc="rows", disable=not progress):
        model = _model(Row(name, "v3", config), db, body, garment)
        per_case = []
        for i, c in enumerate(kept):
            out = synthesize_poses(model, betas[c], poses[c][None])[0]
            per_case.append(case_metrics(out, drapes[i], faces, inside[i]))
        report["rows"].append({"name": name, "config": config, **summarise(per_case, ceiling),
                               "per_case_loo_cm": [p["loo_cm"] for p in per_case]})
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "report_v3.json").write_text(json.dumps(report, indent=1))
        (out_dir / "trade_v3.md").write_text(markdown(report))
    return report


def _cell(entry: dict | None, scale: float = 1.0, digits: int = 2, suffix: str = "") -> str:
    if entry is None:
        return "-"
    low, high = entry["ci"]
    return f"{entry['mean'] * scale:.{digits}f}{suffix} [{low * scale:.{digits}f}, {high * scale:.{digits}f}]"


def markdown(report: dict) -> str:
    """The v3 table: one line for the ceiling, one per row, each figure with its 95 % interval over cases."""
    excluded, missing = report["excluded"], report.get("missing", [])
    lines = [f"Ground truth v3: {len(report['kept'])} of {report['cases']} cases kept (every drape converged; "
             f"excluded as not converged even when extended: {excluded if excluded else 'none'}"
             f"{f'; not complete yet: {len(missing)} cases' if missing else ''}), ramps {report['ramps']}, clips "
             f"{', '.join(report['clips'])}. Means over cases with 95 % bootstrap intervals.", "",
             "| row | leave-one-out (cm) | ratio to ceiling | to mean drape (cm) | to nearest drape (cm) | "
             "surface (cm) | face centres inside |",
             "|---|---|---|---|---|---|---|"]
    c = report["ceiling"]
    lines.append(f"| noise ceiling (each drape vs the others) | {_cell(c['loo_cm'])} | 1 | {_cell(c['to_mean_cm'])} | "
                 f"{_cell(c['nearest_cm'])} | {_cell(c['surface_cm'])} | {_cell(c.get('inside_faces'), 100, 2, ' %')} |")
    for r in report["rows"]:
        lines.append(f"| {r['name']} | {_cell(r['loo_cm'])} | {_cell(r['ratio_to_ceiling'])} | "
                     f"{_cell(r['to_mean_cm'])} | {_cell(r['nearest_cm'])} | {_cell(r['surface_cm'])} | "
                     f"{_cell(r.get('inside_faces'), 100, 2, ' %')} |")
    return "\n".join(lines) + "\n"
