"""The `agentdress` command: benchmarks, demos and (later) builds, each a subcommand printing what it did."""
from __future__ import annotations

import argparse
import sys


def _bench(args) -> int:
    from .evaluate.bench import bench_body, print_json

    if args.target == "body":
        print_json(bench_body(tuple(args.garments), args.vertices, args.repeats))
    return 0


def _demo_png(args) -> int:
    from .evaluate.demo import write_demo_png

    path = write_demo_png(args.out, motion=args.motion)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agentdress", description=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)

    bench = commands.add_parser("bench", help="benchmarks (JSON on stdout)")
    bench.add_argument("target", choices=["body"])
    bench.add_argument("--garments", nargs="+", default=["tshirt"], help="garment templates to pose with the body")
    bench.add_argument("--vertices", type=int, default=None, help="garment vertex count (default per template)")
    bench.add_argument("--repeats", type=int, default=500)
    bench.set_defaults(run=_bench)

    demo = commands.add_parser("demo-png", help="render dressed, posed bodies at three shapes to a PNG")
    demo.add_argument("--out", default="out/dressed_bodies.png")
    demo.add_argument("--motion", default="walk", help="procedural motion or a CMU .bvh file to take poses from")
    demo.set_defaults(run=_demo_png)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
