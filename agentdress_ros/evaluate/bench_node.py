"""`agentdress bench node`: the node end to end over real DDS, publisher and node in separate processes.

The node runs as a child process on a private ROS domain (loopback discovery); this process publishes JointStates
of the `walk` motion at `publish_rate_hz` (default: the node's rate) and subscribes to the garment's PointCloud2.
Reported per configuration (JSON):
  latency_ms         JointState stamp -> PointCloud2 arrival in this process (p50, p99, max). Includes the wait for
                     the node's next timer tick (up to one period: ~11 ms at 90 Hz, ~5.6 ms on average), synthesis,
                     packing and both DDS hops.
  clouds_per_s       distinct answered poses per second (keep-alive repeats are not counted)
  node_tick_rate_hz  the node's own timer rate (from ~/status); late_ticks: ticks > 1.5 periods after the last
  poses_unanswered   poses superseded before a tick could answer them (two poses within one tick: aliasing of two
                     unsynchronised 90 Hz clocks, not a fault)
  cpu_percent        the node process' CPU time / wall time (100 = one core), from /proc/<pid>/stat
  rss_mb             resident memory of the node (VmRSS)
Soak mode (`soak_seconds`) runs one configuration that long and reports resident-memory growth after warm-up.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["bench_node", "main"]


def _proc_cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _proc_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def latency_recorder(state: dict):
    """A PointCloud2 callback appending stamp -> arrival ms to state["latency"] while state["measuring"], each
    stamp once (keep-alive repeats skipped; state["seen"] holds the stamps), and the cloud's width to
    state["vertices"]."""

    def on_cloud(msg):
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if stamp in state["seen"]:
            return  # a keep-alive repeat
        state["seen"].add(stamp)
        if state["measuring"]:
            state["latency"].append((time.time_ns() - stamp) * 1e-6)
            state["vertices"] = getattr(msg, "width", None)

    return on_cloud


def _run_one(vertices, rate_hz, seconds, publish_rate_hz, warmup, soak_seconds, garment, database,
             log_dir: Path) -> dict:
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import String

    from ..motion.joint_names import JOINT_NAMES
    from ..motion.procedural import make_motion
    from ..ros.harness import ChildProcess, node_args, ros_env, ros_node, spin_until
    from ..ros.runtime import percentiles

    env = ros_env(log_dir=str(log_dir))
    domain = int(env["ROS_DOMAIN_ID"])
    params = {"garments": [garment], "rate_hz": float(rate_hz), "status_rate_hz": 1.0}
    if vertices is not None:
        params["garment_vertices"] = [f"{garment}:{int(vertices)}"]
    if database:
        params["garment_databases"] = [f"{garment}:{database}"]
    child = ChildProcess(node_args(params), env, log_dir / f"node_{garment}_{vertices}.log")
    try:
        if not child.wait_for_output("garment models ready", timeout=120.0):
            raise RuntimeError(f"node did not start:\n{child.output()}")
        motion = make_motion("walk", fps=publish_rate_hz)
        names = list(JOINT_NAMES)
        with ros_node("agentdress_bench", domain) as (node, executor):
            state = {"latency": [], "seen": set(), "status": [], "measuring": False, "sent": 0, "frame": 0}

            on_cloud = latency_recorder(state)

            node.create_subscription(PointCloud2, f"/agentdress_node/{garment}/points", on_cloud,
                                     QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                                                reliability=ReliabilityPolicy.BEST_EFFORT))
            node.create_subscription(String, "/agentdress_node/status",
                                     lambda m: state["status"].append(json.loads(m.data)), 10)
            publisher = node.create_publisher(JointState, "joint_states", 1)

            def publish():
                k = state["frame"] % len(motion.rotvecs)
                state["frame"] += 1
                msg = JointState(name=names, position=np.concatenate(
                    [motion.rotvecs[k].reshape(-1), motion.root_translation[k]]).tolist())
                msg.header.stamp = node.get_clock().now().to_msg()
                publisher.publish(msg)
                if state["measuring"]:
                    state["sent"] += 1

            if not spin_until(executor, lambda: publisher.get_subscription_count() > 0 and state["status"], 60.0):
                raise RuntimeError(f"the node was not discovered:\n{child.output()}")
            node.create_timer(1.0 / publish_rate_hz, publish)
            spin_until(executor, lambda: False, warmup)
            status0 = state["status"][-1]
            cpu0, wall0, rss0 = _proc_cpu_seconds(child.pid), time.monotonic(), _proc_rss_mb(child.pid)
            state["measuring"] = True
            rss_samples = [(0.0, rss0)]
            duration = soak_seconds if soak_seconds else seconds
            next_sample = wall0 + 10.0
            while time.monotonic() - wall0 < duration:
                spin_until(executor, lambda: False, min(1.0, duration - (time.monotonic() - wall0)))
                if time.monotonic() >= next_sample:
                    rss_samples.append((round(time.monotonic() - wall0, 1), round(_proc_rss_mb(child.pid), 2)))
                    next_sample += 10.0
            state["measuring"] = False
            wall = time.monotonic() - wall0
            cpu = _proc_cpu_seconds(child.pid) - cpu0
            rss1 = _proc_rss_mb(child.pid)
            spin_until(executor, lambda: False, 1.2)  # one more status
            status = state["status"][-1]
        answered = len(state["latency"])
        result = {
            "garment": garment,
            "vertices": state.get("vertices"),
            "database": database,
            "rate_hz": rate_hz,
            "publish_rate_hz": publish_rate_hz,
            "seconds": round(wall, 2),
            "latency_ms": percentiles(state["latency"], digits=3),
            "clouds_per_s": round(answered / wall, 2),
            "node_tick_rate_hz": status["tick_rate_hz"],
            "late_ticks": status["late_ticks"] - status0["late_ticks"],
            "poses_sent": state["sent"],
            "poses_unanswered": max(0, state["sent"] - answered),
            "node_synthesis_ms": status["synthesis_ms"],
            "node_tick_ms": status["tick_ms"],
            "cpu_percent": round(100.0 * cpu / wall, 1),
            "rss_mb": round(rss1, 1),
        }
        if soak_seconds:
            result["soak"] = {"rss_mb_start": round(rss0, 2), "rss_mb_end": round(rss1, 2),
                              "rss_growth_mb": round(rss1 - rss0, 2),
                              "rss_growth_mb_per_hour": round((rss1 - rss0) * 3600.0 / wall, 2),
                              "samples": rss_samples}
        return result
    finally:
        rc = child.stop()
        if rc not in (0, None):
            print(f"bench: node exited with {rc}:\n{child.output()}", file=sys.stderr)


def bench_node(garment_vertices=None, rate_hz: float = 90.0, seconds: float = 10.0, publish_rate_hz=None,
               soak_seconds: float = 0.0, garment: str = "tshirt", database: str | None = None,
               warmup: float = 2.0) -> dict:
    """Benchmark the node over DDS. garment_vertices: None = the default T-shirt and a 12k-vertex one; an int or a
    list of ints = those budgets (0 = the template default). Returns {"runs": [...], "machine": {...}} (JSON-able).
    soak_seconds > 0 runs only the first configuration that long and adds "soak" (RSS growth)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    if garment_vertices is None:
        budgets = [None, 12000]
    elif isinstance(garment_vertices, (list, tuple)):
        budgets = [v or None for v in garment_vertices]
    else:
        budgets = [garment_vertices or None]
    if soak_seconds:
        budgets = budgets[:1]
    publish_rate_hz = float(publish_rate_hz or rate_hz)
    log_dir = Path(tempfile.mkdtemp(prefix="agentdress_bench_node_"))
    runs = [_run_one(v, float(rate_hz), float(seconds), publish_rate_hz, float(warmup), float(soak_seconds),
                     garment, database, log_dir) for v in budgets]
    return {"benchmark": "node", "runs": runs,
            "machine": {"cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2)},
            "logs": str(log_dir)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress bench node", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vertices", type=int, nargs="*", default=None,
                        help="garment vertex budgets (default: the template default and 12000; 0 = default)")
    parser.add_argument("--rate", type=float, default=90.0, help="node rate_hz")
    parser.add_argument("--publish-rate", type=float, default=None, help="JointState rate (default: --rate)")
    parser.add_argument("--seconds", type=float, default=10.0, help="measured seconds per configuration")
    parser.add_argument("--soak-seconds", type=float, default=0.0, help="soak mode: run this long, report RSS growth")
    parser.add_argument("--garment", default="tshirt")
    parser.add_argument("--database", default=None, help="garment database (.h5) instead of the skinned template")
    args = parser.parse_args(argv)
    result = bench_node(args.vertices, args.rate, args.seconds, args.publish_rate, args.soak_seconds, args.garment,
                        args.database)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
