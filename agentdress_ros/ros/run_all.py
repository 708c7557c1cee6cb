"""`make run`: the node, the demo driver and the web viewer as three processes on the default configuration.

Each garment comes from its shipped database `data/<garment>_default.h5` when that file exists (with
skinned_fallback on, so a database the engine cannot load yet still gives a dressed agent, with a warning); otherwise
it is the skinned template. Prints the viewer's URL; Ctrl-C (or any process exiting) stops all three.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GARMENTS = ("tshirt", "trousers")
DATA = Path("data")


def node_command(params_file: Path, databases: dict, extra=()) -> list[str]:
    """The node's command line: the YAML config plus the run's overrides (body on for the viewer).

    databases: {garment: database path} of the garments the engine synthesises (the others are skinned)."""
    cmd = [sys.executable, "-m", "agentdress_ros.ros.node", "--ros-args", "--params-file", str(params_file),
           "-p", f"garments:={list(GARMENTS)}", "-p", "publish_body:=true"]
    if databases:
        entries = [f"{g}:{path}" for g, path in databases.items()]
        cmd += ["-p", f"garment_databases:={entries}", "-p", "skinned_fallback:=true"]
    return cmd + list(extra)


def run_main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress run", description=__doc__)
    parser.add_argument("--motion", default="walk", help="procedural motion or CMU .bvh clip for the demo")
    parser.add_argument("--port", type=int, default=8765, help="viewer HTTPS port")
    parser.add_argument("--shape-sweep", type=float, default=20.0, help="shape sweep period in s (0: off)")
    parser.add_argument("--config", default=str(ROOT / "config" / "agentdress.yaml"), help="node parameter file")
    parser.add_argument("--data", default=str(DATA), help="folder of the <garment>_default.h5 databases to use")
    args = parser.parse_args(argv)

    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # a one-machine demo: no multicast on the LAN
    found = {g: Path(args.data, f"{g}_default.h5").resolve() for g in GARMENTS}
    databases = {g: path for g, path in found.items() if path.is_file()}
    for g, path in found.items():
        print(f"agentdress run: {g} from {'database ' + str(path) if g in databases else 'the skinned template'}"
              f"{'' if g in databases else f' ({path} not found)'}", flush=True)
    commands = {
        "node": node_command(Path(args.config), databases),
        "demo": [sys.executable, "-m", "agentdress_ros.ros.demo", "--motion", args.motion,
                 "--shape-sweep", str(args.shape_sweep)],
        "viewer": [sys.executable, "-m", "agentdress_ros.ros.viewer", "--port", str(args.port)],
    }
    procs = {}
    code = 0

    def stop(signum, frame):  # a kill or a closed terminal stops the three processes too, not only Ctrl-C
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGHUP, stop)
    signal.signal(signal.SIGINT, stop)  # also when started with SIGINT ignored (a background job of a script)
    parent = os.getppid()
    try:
        for name, cmd in commands.items():
            # Own process groups: Ctrl-C reaches them once, through us, in a defined order.
            procs[name] = subprocess.Popen(cmd, env=env, start_new_session=True)
        print("agentdress run: the viewer prints the URL to open (with its access token); Ctrl-C stops node, demo "
              "and viewer", flush=True)
        while True:
            if os.getppid() != parent:  # whoever started us (make, a shell) is gone: do not leave orphans
                raise StopIteration
            for name, proc in procs.items():
                rc = proc.poll()
                if rc is not None:
                    print(f"agentdress run: {name} exited with status {rc}; stopping the others", flush=True)
                    code = rc or 1
                    raise StopIteration
            time.sleep(0.2)
    except (KeyboardInterrupt, StopIteration):
        pass
    finally:
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):  # a second signal must not cut the cleanup short
            signal.signal(sig, signal.SIG_IGN)
        for proc in procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10.0
        for proc in procs.values():
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return code


if __name__ == "__main__":
    sys.exit(run_main())
