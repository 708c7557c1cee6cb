"""The `agentdress` command: the user's commands, and the experiment commands under `agentdress lab`.

`agentdress --help` lists what a user needs: run the node with the demo and the viewer, drive it, benchmark it,
evaluate a database and build one. `agentdress lab --help` lists the experiment commands (ground-truth studies,
dynamic sequences, the trainers of the learned pose models). The node itself is `agentdress_node`.
"""
from __future__ import annotations

import argparse
import sys

TOP_HELP = """\
Real-time clothing for virtual humans on a CPU (a ROS 2 node and its tools).

  make run                  the node, a walking agent and the web viewer together
  agentdress_node           the node alone (ROS parameters: README "Parameters")

Experiment commands (ground truth, sequences, trainers): agentdress lab --help
"""


def _bench(args) -> int:
    from .evaluate.bench import bench_body, print_json

    if args.target == "body":
        print_json(bench_body(tuple(args.garments), args.vertices, args.repeats))
    elif args.target == "synth":
        from .evaluate.bench_synth import bench_synth

        print_json(bench_synth(vertices=args.vertices or 12000, anchors=args.anchors, neighbors=args.neighbors,
                               cold_start=args.cold_start))
    return 0


# User commands whose options are parsed by the module they run: (name, module, function, one-line summary).
PASSTHROUGH = (
    ("run", ".ros.run_all", "run_main", "node + demo + viewer together (what `make run` starts)"),
    ("view", ".ros.viewer", "view_main", "web viewer (three.js, WebXR) of every agent and garment in the ROS graph"),
    ("demo", ".ros.demo", "demo_main", "publish JointState from a motion (and a shape sweep); --agents N: a crowd"),
    ("eval", ".evaluate.evaluate", "main", "accuracy and speed of a database against held-out newton drapes"),
)

# Experiment commands, `agentdress lab <name> ...`: ground-truth studies, dynamic sequences and the trainers of the
# learned pose models (the shipped databases' `make regressor`).
LAB_PASSTHROUGH = (
    ("floor", ".evaluate.floor", "main", "the ground truth's own spread: held-out cases draped along another path"),
    ("groundtruth-v3", ".evaluate.groundtruth_v3", "main", "held-out cases draped from rest along 30-, 45- and "
     "60-frame ramps (resumable)"),
    ("shape-oracle", ".evaluate.shape_oracle", "main", "what a perfect pose model leaves, scored against drapes made "
     "the database's way"),
    ("page-shots", ".evaluate.page_shots", "main", "screenshots of `make run`'s page in headless Chromium and their "
     "contact sheet"),
    ("overlap-split", ".evaluate.overlap_split", "main", "inside-the-body shares split into self-overlap and truly "
     "inside at several radii"),
    ("sequences", ".offline.sequences", "main", "simulate training clips as dynamic sequences (resumable) and pack them"),
    ("settle", ".offline.settled", "main", "static drapes of training frames: settled, from rest (--start rest) or "
     "at random shapes (--start shaped)"),
    ("regressor", ".offline.regressor", "main", "train the regressor pose model into a database (--validate-*: "
     "choose its data)"),
    ("recurrent", ".offline.recurrent", "main", "train the recurrent pose model (a GRU over the regressor's inputs)"),
    ("santesteban", ".offline.santesteban", "main", "train Santesteban et al.'s garment model into a database"),
    ("shape-residual", ".offline.shape_residual", "main", "train the shape residual (engine shape_residual) from "
     "drapes at random shapes"),
)


# `agentdress bench <name> ...` whose options the module parses: node (publisher and node processes, rates, soak),
# crowd (one node dressing N agents, poses from another process), sequence (the dynamic ground truth's cost per mocap
# frame and what cheaper stepping gives up), pose-models (the engine's cost per frame with each pose model),
# cold-start (a fresh interpreter to the first frame on a real database).
BENCH_PASSTHROUGH = {"node": (".evaluate.bench_node", "main"), "crowd": (".evaluate.bench_crowd", "main"),
                     "sequence": (".evaluate.bench_sequence", "main"),
                     "pose-models": (".evaluate.bench_pose_models", "main"),
                     "cold-start": (".evaluate.bench_cold_start", "main"), "look": (".evaluate.look", "main")}


def _passthrough(module: str, function: str):
    """A subcommand whose options are parsed by the module it runs (demo, view, bench-node)."""

    def run(args) -> int:
        import importlib

        return getattr(importlib.import_module(module, __package__), function)(args.rest)

    return run


def _demo_png(args) -> int:
    from .evaluate.demo import write_demo_png

    path = write_demo_png(args.out, motion=args.motion)
    print(f"wrote {path}")
    return 0


def _build(args) -> int:
    import json

    from .offline.builder import BuildConfig, build_database

    config = BuildConfig(
        garment=args.garment,
        garment_vertices=args.vertices,
        anchors=args.anchors,
        shapes=args.shapes,
        components=args.components,
        examples=args.examples,
        sequence_frames=args.sequence_frames,
        holdout_anchors=args.holdout_anchors,
        pose_every=args.pose_every,
        clips=[str(p) for p in args.clips],
        repair_flips=not args.raw_clips,
        procedural=args.procedural,
        drape=json.loads(args.drape) if args.drape else {},
        **({"warm_drape": json.loads(args.warm_drape)} if args.warm_drape else {}),
        seed=args.seed,
    )
    report = build_database(config, args.out, workers=args.workers, scheduler=args.scheduler,
                            progress=not args.quiet, partial=args.partial, seed_drapes=args.seed_drapes,
                            pack_drapes=args.pack_drapes)
    print(json.dumps({"database": str(args.out), **report}, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress", description=TOP_HELP,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True, metavar="command")

    bench = commands.add_parser("bench", help="benchmarks, JSON on stdout: body, synth, node, crowd, pose-models, "
                                "cold-start, sequence, look", description=f"body and synth take the options below; "
                                f"{', '.join(BENCH_PASSTHROUGH)} their own (agentdress bench node --help)")
    bench.add_argument("target", choices=["body", "synth", *BENCH_PASSTHROUGH])
    bench.add_argument("--garments", nargs="+", default=["tshirt"], help="garment templates to pose with the body")
    bench.add_argument("--vertices", type=int, default=None, help="garment vertex count (default per template)")
    bench.add_argument("--repeats", type=int, default=500)
    bench.add_argument("--anchors", type=int, default=150, help="synth: anchors of the synthetic database")
    bench.add_argument("--neighbors", type=int, default=5, help="synth: anchors blended per region (K)")
    bench.add_argument("--cold-start", action="store_true", help="synth: also time import + JIT + load")
    bench.set_defaults(run=_bench)

    _add_passthrough(commands, PASSTHROUGH)

    build = commands.add_parser("build", help="build a garment database from newton drapes (resumable)")
    build.add_argument("--garment", default="tshirt", help="garment template (tshirt, longsleeve, trousers)")
    build.add_argument("--vertices", type=int, default=3000, help="garment vertex count")
    build.add_argument("--anchors", type=int, default=32, help="anchor poses N (clothing shape models)")
    build.add_argument("--shapes", type=int, default=17, help="training shapes per anchor: 1, 5, 9, 13 or 17")
    build.add_argument("--components", type=int, default=5, help="PCA components per shape model")
    build.add_argument("--examples", type=int, default=64, help="pose-model example drapes at beta0")
    build.add_argument("--sequence-frames", type=int, default=60, help="frames of the simulated sequence")
    build.add_argument("--holdout-anchors", type=int, default=4, help="anchors also draped on a held-out shape")
    build.add_argument("--pose-every", type=int, default=4, help="take one clip pose every this many frames")
    build.add_argument("--clips", nargs="*", default=[], help="CMU .bvh clips for the pose set")
    build.add_argument("--raw-clips", action="store_true", help="take the clips' poses as recorded, without "
                       "repairing knee and elbow flips (how the shipped databases were built: add it to rebuild "
                       "them from their drape packs)")
    build.add_argument("--procedural", nargs="*", default=["idle", "walk", "reach", "sweep", "wipe", "wave", "squat"],
                       help="procedural motions for the pose set")
    build.add_argument("--drape", default="", help="JSON object of DrapeSettings overrides")
    build.add_argument("--warm-drape", default="", help="JSON DrapeSettings overrides for drapes warm-started "
                       "from another drape (default {\"velocity_retention\": 0.75})")
    build.add_argument("--workers", type=int, default=2, help="local worker processes (0: in this process)")
    build.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    build.add_argument("--seed", type=int, default=0)
    build.add_argument("--partial", action="store_true", help="drape nothing: write a database now from the "
                       "anchors whose drapes are all finished (the build continues when rerun without it)")
    build.add_argument("--seed-drapes", default=None, help="start from the finished drapes in this pack")
    build.add_argument("--pack-drapes", default=None, help="pack every finished drape into this file "
                       "(one .npz) as the build goes (every 10 drapes) and at the end, so the build can be continued "
                       "on another machine with --seed-drapes (the same file may be both)")
    build.add_argument("--quiet", action="store_true", help="no progress bar")
    build.add_argument("--out", required=True, help="database file to write (.h5)")
    build.set_defaults(run=_build)

    demo = commands.add_parser("demo-png", help="dressed, posed bodies at three shapes in one PNG (no ROS)")
    demo.add_argument("--out", default="out/dressed_bodies.png")
    demo.add_argument("--motion", default="walk", help="procedural motion or a CMU .bvh file to take poses from")
    demo.set_defaults(run=_demo_png)

    lab = commands.add_parser("lab", help="experiment commands: ground-truth studies, sequences, trainers",
                              description="Experiment commands: the ground truth's studies, the dynamic sequences "
                              "and the trainers of the learned pose models (docs/building.md, docs/notes/).")
    _add_passthrough(lab.add_subparsers(dest="lab_command", required=True, metavar="command"), LAB_PASSTHROUGH)
    return parser


def _add_passthrough(commands, table) -> None:
    for name, module, function, text in table:
        sub = commands.add_parser(name, help=text, add_help=False)
        sub.add_argument("rest", nargs=argparse.REMAINDER)
        sub.set_defaults(run=_passthrough(module, function))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"] and argv[1:2] and argv[1] in BENCH_PASSTHROUGH:  # benchmarks with their own options
        return _passthrough(*BENCH_PASSTHROUGH[argv[1]])(argparse.Namespace(rest=argv[2:]))
    if argv[:1] == ["demo"] and any(a == "--agents" or a.startswith("--agents=") for a in argv):
        from .ros.crowd_demo import crowd_main

        return crowd_main(argv[1:])
    for prefix, table in (([], PASSTHROUGH), (["lab"], LAB_PASSTHROUGH)):
        for name, module, function, _ in table:
            command = [*prefix, name]
            if argv[:len(command)] == command:  # argparse's REMAINDER would reject a leading --option
                return _passthrough(module, function)(argparse.Namespace(rest=argv[len(command):]))
    args = build_parser().parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
