"""`agentdress bench crowd --agents 1 10 25 50 100 --seconds S`: one node dressing N agents over real DDS.

For each N the node runs as a child process in crowd mode (`agents: [agent_000, ...]`, T-shirt and trousers from the
shipped databases, the engine knobs of `--engine`: by default the node's own, the regressor pose model with the body
projection at the near tier, the shipped tiers; `--engine pose_model=examples` is the configuration of the README's
earlier rows), pinned to one core (`--node-cores`; its DDS threads share that core) while the pose publisher and this
process run on the others; a second child process (`agentdress demo --agents N`) publishes every agent's JointState
at `--pose-rate` and, in the spread run, a fixed viewer pose; this process listens to ~/status and to the T-shirt
cloud of the agent nearest the viewer in view (the one each status names: the agents walk). Two runs per N:
  near    every agent within 3 m, LOD off (lod.enabled false): every agent fully dressed on every new pose
  spread  agents walking about a 30 m plaza, a viewer at its edge looking in, LOD, culling and the 8 ms budget on
  cpu     no DDS: the scene in this process, every agent given a new pose every tick and dressed at one level, its
          clouds packed (not published); CPU time of this process (not wall time: what a loaded machine takes from
          the process does not count) per agent frame at each level, and per tick with all N agents at the first
Reported per N (JSON): tick_ms p50/p99 (the node's crowd timer tick: decide, dress, publish; near agents answered
on arrival are dressed in their subscription callback, outside it), late ticks (timer
ticks more than 1.5 periods after the previous one), clouds per second per agent (frames dressed / seconds / N,
from the node's counts), agents per tier (culled among them), frames degraded by the budget, the margin the
budget keeps free of recent misses (margin_ms), node CPU (100 = one
core) and RSS, RSS added per agent (against the smallest N of the same run), the nearest agent's JointState ->
PointCloud2 latency p99 (stamp to arrival here) and, beside it, the same agent's JointState stamp -> arrival here
(nearest_pose_transport_ms: what the transport alone takes, on the publisher's loaded core). Measuring starts once
every agent's shape has reached the node and been fitted (a refit takes the GIL from the ticks).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from .bench_node import _proc_cpu_seconds, _proc_rss_mb, latency_recorder

__all__ = ["bench_crowd", "main"]

ROOT = Path(__file__).resolve().parents[2]
DATABASES = {"tshirt": ROOT / "data" / "tshirt_default.h5", "trousers": ROOT / "data" / "trousers_default.h5"}
VIEWER = (-16.0, 0.0, 1.6, 0.0)  # x, y, z, yaw: at the plaza's edge, looking along +x into it


def default_engine() -> list:
    """The node's shipped engine knobs (its `engine` parameter's default)."""
    from ..ros.params import PARAMETERS

    return list(PARAMETERS["engine"].default)


def _nearest_in_view(detail: dict):
    """The name of the agent nearest the viewer in view in a status's agents_detail (None when none is)."""
    seen = [n for n in detail if detail[n]["visible"]]
    return min(seen, key=lambda n: (detail[n]["distance"], n)) if seen else None


def _run_one(count: int, mode: str, seconds: float, pose_rate: float, rate_hz: float, budget_ms: float,
             warmup: float, log_dir: Path, node_nice: int = 0, node_cores: tuple = (),
             realtime_priority: int = 0, engine: tuple = tuple(default_engine())) -> dict:
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import String

    from ..ros.crowd_demo import agent_names
    from ..ros.harness import ChildProcess, node_args, ros_env, ros_node, spin_until
    from ..scene.scene import percentiles

    env = ros_env(log_dir=str(log_dir))
    domain = int(env["ROS_DOMAIN_ID"])
    names = agent_names(count)
    params = {"agents": names, "garments": list(DATABASES),
              "garment_databases": [f"{g}:{p}" for g, p in DATABASES.items()],
              "rate_hz": float(rate_hz), "status_rate_hz": 1.0, "budget_ms": float(budget_ms),
              "lod.enabled": mode == "spread", "engine": list(engine)}
    if realtime_priority:
        params["realtime_priority"] = int(realtime_priority)
    prefix = ["nice", "-n", str(node_nice)] if node_nice else []
    others = sorted(os.sched_getaffinity(0) - set(node_cores))
    if node_cores and others:  # the node alone on its cores (its DDS threads too); the publisher and this process
        prefix = ["taskset", "-c", ",".join(map(str, node_cores))] + prefix  # on the others
        os.sched_setaffinity(0, others)
    node = ChildProcess(prefix + node_args(params), env, log_dir / f"node_{mode}_{count}.log")
    demo_args = ["taskset", "-c", ",".join(map(str, others))] if node_cores and others else []
    demo_args += [sys.executable, "-m", "agentdress_ros.ros.crowd_demo", "--agents", str(count), "--rate",
                  str(pose_rate)]
    demo_args += ["--near"] if mode == "near" else ["--viewer-at", *(str(v) for v in VIEWER)]
    demo = None
    try:
        if not node.wait_for_output("crowd ready", timeout=600.0):
            raise RuntimeError(f"node did not start:\n{node.output()}")
        demo = ChildProcess(demo_args, env, log_dir / f"demo_{mode}_{count}.log")
        started = time.monotonic()
        with ros_node("agentdress_bench_crowd", domain) as (client, executor):
            state = {"latency": [], "seen": set(), "status": [], "measuring": False}

            on_cloud = latency_recorder(state)
            client.create_subscription(String, "/agentdress_node/status",
                                       lambda m: state["status"].append(json.loads(m.data)), 10)
            if not spin_until(executor, lambda: state["status"] and state["status"][-1]["counts"].get(
                    "joint_states_received", 0) > count, 120.0):
                raise RuntimeError(f"no poses reached the node:\n{node.output()}\n{demo.output()}")
            # every agent's shape reached the node and was fitted: a refit (on the node's worker thread) during the
            # measurement takes the GIL from the ticks. The demo repeats the shapes every 5 s (repeats cost nothing).
            if not spin_until(executor, lambda: state["status"][-1]["counts"].get("shapes_received", 0) >= count,
                              60.0):
                raise RuntimeError(f"the agents' shapes did not reach the node:\n{node.output()}\n{demo.output()}")
            spin_until(executor, lambda: False, 2.0)  # the status after the shapes were taken
            # every agent refitted to its shape (each agent's is not the node's default), the worker idle
            if not spin_until(executor, lambda: state["status"][-1]["crowd"]["worker_idle"] and state["status"][-1][
                    "crowd"].get("refits", 0) >= count, 600.0):
                raise RuntimeError("the node did not finish fitting the agents' shapes within 600 s")
            fitted_after = time.monotonic() - started
            spin_until(executor, lambda: False, warmup)
            # The nearest agent in view changes as the agents walk about: every status names it, and its clouds (and
            # poses) are the ones measured, through a subscription made the first time an agent is the nearest.
            pose_state = {"latency": [], "seen": set(), "measuring": False}
            follow = {"nearest": None, "agents": [], "subscribed": set()}
            qos = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)

            def only_nearest(agent, callback):
                return lambda msg: callback(msg) if follow["nearest"] == agent else None

            def follow_nearest(status):
                detail = status["crowd"]["agents_detail"]
                agent = _nearest_in_view(detail)
                if agent is None:
                    return
                if state["measuring"] and agent not in follow["agents"]:
                    follow["agents"].append(agent)
                if agent not in follow["subscribed"]:
                    follow["subscribed"].add(agent)
                    client.create_subscription(PointCloud2, f"/agentdress_node/{agent}/tshirt/points",
                                               only_nearest(agent, on_cloud), qos)
                    # the same agent's poses as they reach this process: the share of the latency that is transport
                    client.create_subscription(JointState, f"/{agent}/joint_states",
                                               only_nearest(agent, latency_recorder(pose_state)), qos)
                follow["nearest"] = agent

            follow_nearest(state["status"][-1])
            nearest = follow["nearest"]
            follow["agents"] = [nearest]
            client.create_subscription(String, "/agentdress_node/status",
                                       lambda m: follow_nearest(json.loads(m.data)), 10)
            spin_until(executor, lambda: False, 3.0)  # discovery of the new subscription
            status0 = state["status"][-1]
            cpu0, wall0 = _proc_cpu_seconds(node.pid), time.monotonic()
            state["measuring"] = pose_state["measuring"] = True
            spin_until(executor, lambda: False, seconds)
            state["measuring"] = pose_state["measuring"] = False
            wall = time.monotonic() - wall0
            cpu = _proc_cpu_seconds(node.pid) - cpu0
            rss = _proc_rss_mb(node.pid)
            n_status = len(state["status"])
            spin_until(executor, lambda: len(state["status"]) > n_status, 3.0)
            status = state["status"][-1]
        crowd, crowd0 = status["crowd"], status0["crowd"]
        frames = sum(a["frames"] for a in crowd["agents_detail"].values())
        frames0 = sum(a["frames"] for a in crowd0["agents_detail"].values())
        tiers = {name: {"agents": t["agents"], "culled": t["culled"],
                        "frames_per_s": round((t["frames"] - crowd0["tiers"][name]["frames"]) / wall, 1),
                        "degraded_frames": t["degraded_frames"] - crowd0["tiers"][name]["degraded_frames"],
                        "ms": t["ms"]}
                 for name, t in crowd["tiers"].items()}
        return {
            "agents": count, "mode": mode, "node_nice": node_nice, "node_cores": list(node_cores),
            "realtime_priority": realtime_priority, "seconds": round(wall, 1), "pose_rate_hz": pose_rate,
            "rate_hz": rate_hz,
            "budget_ms": budget_ms if mode == "spread" else None,
            "tick_ms": status["tick_ms"], "late_ticks": status["late_ticks"] - status0["late_ticks"],
            "tick_rate_hz": status["tick_rate_hz"],
            "clouds_per_s_per_agent": round((frames - frames0) / wall / count, 2),
            "tiers": tiers, "margin_ms": crowd.get("margin_ms"),
            "cpu_percent": round(100.0 * cpu / wall, 1), "rss_mb": round(rss, 1),
            "nearest_agent": nearest, "nearest_agents": follow["agents"],
            "nearest_latency_ms": percentiles(state["latency"], digits=3),
            "nearest_pose_transport_ms": percentiles(pose_state["latency"], digits=3),
            "shapes_fitted_after_s": round(fitted_after, 1),
            "refits_while_measuring": crowd.get("refits", 0) - crowd0.get("refits", 0),
        }
    finally:
        if demo is not None:
            demo.stop()
        rc = node.stop()
        if rc not in (0, None):
            print(f"bench: node exited with {rc}:\n{node.output()}", file=sys.stderr)


def _run_cpu(count: int, ticks: int = 60, engine: tuple = tuple(default_engine())) -> dict:
    """CPU ms per agent frame at each tier's level, and per tick, for `count` agents (in process, no DDS)."""
    from ..body import AnnyBody
    from ..ros.crowd_demo import CrowdPlayer
    from ..ros.messages import SerializedCloud
    from ..ros.params import PARAMETERS, validate
    from ..scene import AgentSpec, GarmentSpec, Scene, SceneConfig

    body = AnnyBody()
    scene = Scene(body, SceneConfig(lod_enabled=False, budget_ms=0.0, fade_frames=0))
    knobs = validate("engine", list(engine))
    garments = tuple(GarmentSpec(g, database=str(p), engine=knobs.for_garment(g)) for g, p in DATABASES.items())
    player = CrowdPlayer(count, 30.0)
    try:
        for i, track in enumerate(player.tracks):
            # dressed for display as the node's default configuration does it (refined, layered)
            scene.install(scene.build_agent(AgentSpec(f"agent_{i:03d}", garments, tuple(track.beta),
                                                      subdivision=PARAMETERS["display_subdivision"].default)))
        clouds = {}

        def pack(agent, frames, stamp_ns):  # as the node does: into the cloud's serialized bytes
            for g, vertices in frames.items():
                cloud = clouds.get((agent.name, g))
                if cloud is None or cloud.n_vertices != len(vertices):  # a tier of another topology
                    cloud = clouds[(agent.name, g)] = SerializedCloud(agent.spec.frame_id, len(vertices))
                cloud.set(vertices, stamp_ns)

        per_level = {}
        for level, tier in enumerate(scene.config.lod.tiers):
            agents, spent = list(scene.agents.values()), 0.0
            for t in range(ticks + 5):
                rotvecs, roots = player.frames(t / 30.0)
                for i, agent in enumerate(agents):
                    agent.pose.set(rotvecs[i], roots[i])
                cpu0 = time.process_time()
                for agent in agents:
                    scene._dress(agent, level, 0, pack, 0)
                spent += (time.process_time() - cpu0) if t >= 5 else 0.0  # the first ticks warm up
            per_level[tier.name] = round(1e3 * spent / (ticks * count), 4)
        tick = []
        for t in range(ticks):
            rotvecs, roots = player.frames(t / 30.0)
            for i, agent in enumerate(scene.agents.values()):
                agent.pose.set(rotvecs[i], roots[i])
            cpu0 = time.process_time()
            scene.tick(pack)
            tick.append(1e3 * (time.process_time() - cpu0))
    finally:
        scene.stop()
    from ..scene.scene import percentiles

    return {"agents": count, "mode": "cpu", "engine": list(engine), "cpu_ms_per_agent_frame": per_level,
            "cpu_ms_per_tick_all_near": percentiles(tick, digits=3)}


def bench_crowd(counts=(1, 10, 25, 50, 100), seconds: float = 20.0, modes=("near", "spread"),
                pose_rate: float = 30.0, rate_hz: float = 90.0, budget_ms: float = 8.0, warmup: float = 5.0,
                node_nice: int = 0, node_cores=None, realtime_priority: int = 0, engine=()):
    """Yields one result dict per (mode, N), RSS added per agent against the smallest N of the same mode. engine:
    the agents' engine knobs (empty: the node's default)."""
    engine = tuple(engine) or tuple(default_engine())
    log_dir = Path(tempfile.mkdtemp(prefix="agentdress_bench_crowd_"))
    if node_cores is None:  # the goals are for one core: the node on the first, the rest of the machine beside it
        cores = sorted(os.sched_getaffinity(0))
        node_cores = cores[:1] if len(cores) > 1 and shutil.which("taskset") else []
    for mode in modes:
        if mode == "cpu":
            for count in sorted(counts):
                yield _run_cpu(int(count), engine=engine)
            continue
        base = None
        for count in sorted(counts):
            result = _run_one(int(count), mode, float(seconds), float(pose_rate), float(rate_hz), float(budget_ms),
                              float(warmup), log_dir, int(node_nice), tuple(node_cores), int(realtime_priority),
                              engine)
            if base is None:
                base = result
            elif count > base["agents"]:
                result["rss_added_per_agent_mb"] = round((result["rss_mb"] - base["rss_mb"])
                                                         / (count - base["agents"]), 3)
            result["engine"] = list(engine)
            result["load_avg_1min"] = round(os.getloadavg()[0], 2)
            result["logs"] = str(log_dir)
            yield result


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="agentdress bench crowd", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", type=int, nargs="+", default=[1, 10, 25, 50, 100])
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds per N")
    parser.add_argument("--modes", nargs="+", choices=("near", "spread", "cpu"), default=["near", "spread"])
    parser.add_argument("--pose-rate", type=float, default=30.0, help="JointState rate per agent, Hz (default 30)")
    parser.add_argument("--rate", type=float, default=90.0, help="node rate_hz")
    parser.add_argument("--budget-ms", type=float, default=8.0)
    parser.add_argument("--node-cores", type=int, nargs="*", default=None,
                        help="CPU cores the node runs on, pinned with taskset (default: the first core when there "
                             "are two or more; the pose publisher and this process run on the others). "
                             "Empty: not pinned")
    parser.add_argument("--realtime-priority", type=int, default=0,
                        help="the node's realtime_priority parameter (SCHED_FIFO for its executor thread; 0: off)")
    parser.add_argument("--node-nice", type=int, default=0,
                        help="run the node under `nice -n N` (negative: ahead of other work on a shared machine)")
    parser.add_argument("--engine", nargs="+", default=None,
                        help="the node's engine knobs for every agent ('field=value', 'garment:field=value'; default: "
                             "the node's own, the regressor pose model with the body projection)")
    args = parser.parse_args(argv)
    for result in bench_crowd(args.agents, args.seconds, args.modes, args.pose_rate, args.rate, args.budget_ms,
                              node_nice=args.node_nice, node_cores=args.node_cores,
                              realtime_priority=args.realtime_priority, engine=tuple(args.engine or ())):
        print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
