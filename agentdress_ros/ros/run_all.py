"""`make run`: the node, the demo driver and the web viewer as three processes on the default configuration.

The T-shirt comes from the database `data/tshirt_default.h5` when that file exists (with skinned_fallback on, so a
database the engine cannot load yet still gives a dressed agent, with a warning); otherwise both garments are the
skinned templates. Prints the viewer's URL; Ctrl-C (or any process exiting) stops all three.
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
DEFAULT_DATABASE = Path("data/tshirt_default.h5")


def node_command(params_file: Path, database: Path | None, extra=()) -> list[str]:
    """The node's command line: the YAML config plus the run's overrides (body on for the viewer)."""
    cmd = [sys.executable, "-m", "agentdress_ros.ros.node", "--ros-args", "--params-file", str(params_file),
           "-p", "garments:=['tshirt','trousers']", "-p", "publish_body:=true"]
    if database is not None:
        cmd += ["-p", f"garment_databases:=['tshirt:{database}']", "-p", "skinned_fallback:=true"]
    return cmd + list(extra)


def run_main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress run", description=__doc__)
    parser.add_argument("--motion", default="walk", help="procedural motion or CMU .bvh clip for the demo")
    parser.add_argument("--port", type=int, default=8765, help="viewer HTTP port")
    parser.add_argument("--shape-sweep", type=float, default=20.0, help="shape sweep period in s (0: off)")
    parser.add_argument("--config", default=str(ROOT / "config" / "agentdress.yaml"), help="node parameter file")
    parser.add_argument("--database", default=str(DEFAULT_DATABASE), help="T-shirt database if the file exists")
    args = parser.parse_args(argv)

    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # a one-machine demo: no multicast on the LAN
    database = Path(args.database).resolve() if Path(args.database).is_file() else None
    print(f"agentdress run: T-shirt from {'database ' + str(database) if database else 'the skinned template'}"
          f"{'' if database else f' ({args.database} not found)'}, trousers skinned", flush=True)
    commands = {
        "node": node_command(Path(args.config), database),
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
    parent = os.getppid()
    try:
        for name, cmd in commands.items():
            # Own process groups: Ctrl-C reaches them once, through us, in a defined order.
            procs[name] = subprocess.Popen(cmd, env=env, start_new_session=True)
        print(f"agentdress run: open http://127.0.0.1:{args.port}/ in a browser (Ctrl-C stops node, demo and viewer)",
              flush=True)
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
