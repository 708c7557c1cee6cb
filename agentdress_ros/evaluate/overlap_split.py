"""`agentdress lab overlap-split`: how the inside-the-body shares split into "in the body's self-overlap" and "truly
inside" as the split's radius changes, for the held-out v2 ground truth and the node default's synthesis.

A garment vertex inside the posed body counts as trapped in the body's self-overlap when it is inside two body parts
at once, or within `radius` of a body face that lies inside another part (garment.inside). The shipped radius is
5 mm; this command reports the shares at several radii, so the split's sensitivity is stated, not assumed.
Reads the committed v2 packs; simulates nothing.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

RADII = (0.002, 0.005, 0.01, 0.03)


def split_shares(database, folder, radii=RADII, engine: dict | None = None, progress: bool = True) -> dict:
    """{"ground truth": {radius_mm: (inside, in overlap, truly inside) shares}, "node default": ...} over every
    (pose, shape) case of the v2 set of `database` (drapes from `folder`/ground_truth_drapes.npz)."""
    from tqdm import tqdm

    from ..body import AnnyBody
    from ..engine import Engine, EngineConfig, read_database
    from ..garment.inside import BodyInside
    from ..offline.jobs import read_drape_pack
    from ..body.model import visible_body
    from .evaluate import synthesize_poses
    from .testset import held_out_poses, held_out_shapes, held_out_v2

    db = read_database(database)
    body = AnnyBody()
    config = held_out_v2()
    poses, _, _, _ = held_out_poses(body, config)
    betas, _ = held_out_shapes(db, config)
    drapes = read_drape_pack(Path(folder) / "ground_truth_drapes.npz")["drapes"]
    model = Engine(db, body, EngineConfig(**engine)) if engine is not None else None
    ids, faces = visible_body(body)
    counts = {name: {r: np.zeros(3) for r in radii} for name in ("ground truth", "node default")}
    total = 0
    for k, beta in enumerate(tqdm(betas, desc="shapes", disable=not progress)):
        shape = body.shape(beta)
        outputs = synthesize_poses(model, beta, poses) if model is not None else None
        for p, pose in enumerate(poses):
            posed = body.posed_vertices(shape, body.pose(shape, pose)[0])[ids]
            candidates = {"ground truth": drapes[f"test_{p:04d}_{k:02d}"][0]}
            if outputs is not None:
                candidates["node default"] = outputs[p]
            test = BodyInside(posed, faces)  # one winding field per case; the radius only changes the split
            for r in radii:
                test.radius = r
                for name, vertices in candidates.items():
                    report = test.report(vertices)
                    counts[name][r] += (report["inside_count"], report["overlap_count"], report["truly_inside_count"])
            total += len(candidates["ground truth"])
    return {name: {f"{1000 * r:g} mm": dict(zip(("inside", "in_overlap", "truly_inside"),
                                                (c / max(total, 1)).tolist()))
                   for r, c in by_radius.items()}
            for name, by_radius in counts.items() if model is not None or name == "ground truth"}


def main(argv=None) -> int:
    import argparse

    from ..engine import read_database
    from ..ros.params import default_engine
    from .bench import print_json

    parser = argparse.ArgumentParser(prog="agentdress lab overlap-split", description=__doc__.split("\n")[0])
    parser.add_argument("--database", default="data/tshirt_default.h5")
    parser.add_argument("--folder", default="docs/eval/v2/tshirt", help="the v2 evaluation folder")
    parser.add_argument("--out", default=None, help="write the report (JSON) here too")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    engine = default_engine(read_database(args.database).garment)
    print_json({"database": args.database, "engine": engine,
                "shares": split_shares(args.database, args.folder, engine=engine, progress=not args.quiet)}, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
