"""agentdress_node: dresses one agent, or a crowd, from JointState streams (wiring only: the agents live in crowd.py).

Topics of the single agent (`agents` empty: a crowd of one; relative to the node, `~` = /agentdress_node):
  in   <joint_state_topic>  sensor_msgs/JointState        (QoS qos.joint_states.*, default best effort, depth 1)
  in   <shape_topic>        std_msgs/Float32MultiArray    (QoS qos.shape.*, default reliable, depth 1)
  out  ~/<garment>/points   sensor_msgs/PointCloud2       every new pose (qos.points.*: best effort, 1)
  out  ~/<garment>/mesh     shape_msgs/Mesh               reliable, transient local: once per garment (re)build
  out  ~/body/points, ~/body/mesh                         only with publish_body (points only while someone
                                                          subscribes: else the body is posed as bones alone)
  out  ~/body/skin          std_msgs/Float32MultiArray    reliable, transient local: the body's rest vertices, bone
                                                          indices and weights (messages.make_skin), per (re)build
  out  ~/body/bones         geometry_msgs/PoseArray       with each body frame: its bone transforms, from which a
                                                          display client skins the body itself (exactly the cloud)
  out  ~/marker             visualization_msgs/Marker     only with marker_rate_hz > 0 (one per garment, ns = name)
  out  ~/status             std_msgs/String (JSON)        at status_rate_hz
A crowd (`agents` lists names) has the same per agent under its name (crowd.py says more).

The status is JSON on a String rather than diagnostic_msgs on /diagnostics: its content is nested (timings, counts
by reason, per-garment facts) and the bench, the viewer and the tests parse it directly.

Timer ticks do nothing when no new pose arrived and nothing changed, except re-publishing the last clouds at
keepalive_hz (a display that joins late, or a best-effort sample lost on the way, is repaired within a second).
No exception ends the node: every timer, subscription and parameter callback, the scene's worker and the marker
thread catch what they raise, log it (throttled) and count it under `errors` on ~/status; the last good clouds keep
flowing, and a marker thread that dies is restarted.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from ..garment import TEMPLATES
from ..models.garment_models import GarmentDatabaseError
from .crowd import Crowd
from .inputs import InputRejected
from .markers import MarkerThread
from .params import PARAMETERS, ParameterError, check_garment_config, database_file_problem, validate
from .runtime import TickStats
from .spin import raise_receive_threads, set_realtime_priority, spin_until_shutdown

NODE_NAME = "agentdress_node"
TOPOLOGY_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)


class ConfigError(RuntimeError):
    """The node cannot start with this configuration; the message says which parameter and why."""


def _qos(reliability: str, depth: int) -> QoSProfile:
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.BEST_EFFORT if reliability == "best_effort"
                      else ReliabilityPolicy.RELIABLE)


class Throttle:
    """At most one message per key per `period` seconds; counts what it held back."""

    def __init__(self, period: float):
        self.period, self.last, self.held = period, {}, {}

    def allow(self, key: str, now: float) -> tuple[bool, int]:
        if now - self.last.get(key, -1e18) >= self.period:
            self.last[key] = now
            return True, self.held.pop(key, 0)
        self.held[key] = self.held.get(key, 0) + 1
        return False, 0


class AgentDressNode(Node):
    def __init__(self, body=None, **kwargs):
        # Every override is declared, so a crowd's per-agent ones (agent.<a>.<key>, from the YAML) are parameters
        # the crowd reads by prefix; the node's own are declared again below, with their descriptions.
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True, **kwargs)
        for name, spec in PARAMETERS.items():
            if self.has_parameter(name):
                self.undeclare_parameter(name)  # the override's value is taken again by declare_parameter
            self.declare_parameter(name, spec.default, ParameterDescriptor(
                description=spec.description + ("" if spec.runtime else " (startup only)"), dynamic_typing=True))
        self.config = self._read_config()
        self.throttle = Throttle(self.config["warn_throttle_s"])
        self.stats = TickStats()
        self.publish_lock = threading.Lock()  # guards publishers against the marker thread
        self.topology_qos = TOPOLOGY_QOS
        self._timer_by_key = {}
        from ..body import AnnyBody

        start = time.perf_counter()
        try:  # GarmentDatabaseError names the file: the node exits with it
            self.agents = Crowd(self, body if body is not None else AnnyBody(), {
                name: parameter.value for name, parameter in self.get_parameters_by_prefix("agent").items()})
        except ParameterError as error:
            raise ConfigError(str(error)) from None
        self.get_logger().info(self.agents.ready_message(time.perf_counter() - start))
        self.status_pub = self.create_publisher(String, "~/status", 10)
        self.markers = MarkerThread(self)
        self._set_timer("tick", self.config["rate_hz"], self._on_tick)
        self._set_timer("status", self.config["status_rate_hz"], self._on_status)
        self._set_timer("marker", self.config["marker_rate_hz"], self._on_marker)
        self._set_timer("inside", self.config["inside_check_hz"], self.agents.check_inside)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

    def qos(self, kind: str) -> QoSProfile:
        """The QoS of a stream kind: joint_states, shape, points (parameters qos.<kind>.*), viewer (best effort)."""
        if kind == "viewer":
            return _qos("best_effort", 1)
        return _qos(self.config[f"qos.{kind}.reliability"], self.config[f"qos.{kind}.depth"])

    # ---- configuration -------------------------------------------------------------------------------------------
    def _read_config(self) -> dict:
        config = {}
        for name in PARAMETERS:
            try:
                config[name] = validate(name, self.get_parameter(name).value)
            except ParameterError as error:
                raise ConfigError(f"parameter {error}" if not str(error).startswith(name) else str(error)) from None
        try:
            check_garment_config(config["garments"], config["garment_databases"], TEMPLATES, config["garment_models"])
        except ParameterError as error:
            raise ConfigError(str(error)) from None
        return config

    def _on_set_parameters(self, parameters) -> SetParametersResult:
        """Validate a `ros2 param set` (all parameters of one request together); reject with the reason."""
        config = dict(self.config)
        try:
            for p in parameters:
                if p.name not in PARAMETERS:
                    raise ParameterError(f"unknown parameter {p.name!r}")
                if not PARAMETERS[p.name].runtime:
                    raise ParameterError(f"{p.name} is read at startup only: restart the node to change it")
                config[p.name] = validate(p.name, p.value)
            check_garment_config(config["garments"], config["garment_databases"], TEMPLATES, config["garment_models"])
            if bool(config["agents"]) != bool(self.config["agents"]):
                raise ParameterError("agents: switching between one agent (empty list) and a crowd needs a restart "
                                     "of the node")
            if any(p.name in ("garments", "garment_databases") for p in parameters):
                for g in config["garments"]:
                    path = config["garment_databases"].get(g)
                    problem = path and not config["skinned_fallback"] and database_file_problem(path)
                    if problem:
                        raise ParameterError(f"garment {g!r}: {problem}")
        except ParameterError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    @property
    def stamp_jump_ns(self) -> int:
        return int(self.config["stamp_jump_threshold_s"] * 1e9)

    def _after_set_parameters(self, parameters):
        try:
            changed = {p.name for p in parameters}
            for p in parameters:
                self.config[p.name] = validate(p.name, p.value)
            for name, key, callback in (("rate_hz", "tick", self._on_tick),
                                        ("status_rate_hz", "status", self._on_status),
                                        ("marker_rate_hz", "marker", self._on_marker),
                                        ("inside_check_hz", "inside", self.agents.check_inside)):
                if name in changed:
                    self._set_timer(key, self.config[name], callback)
            if "warn_throttle_s" in changed:
                self.throttle.period = self.config["warn_throttle_s"]
            self.agents.apply_parameters(changed)
        except Exception as error:  # raised into rclpy's parameter service, it would end the spin
            self.report_error("parameters", error)

    def _set_timer(self, key, rate_hz, callback):
        old = self._timer_by_key.pop(key, None)
        if old is not None:
            self.destroy_timer(old)
        if rate_hz > 0:
            self._timer_by_key[key] = self.create_timer(1.0 / rate_hz, self.guarded(key, callback))

    def ms_until_tick(self) -> float:
        """Milliseconds until the tick timer is next due (negative: overdue; inf without a timer)."""
        timer = self._timer_by_key.get("tick")
        left = None if timer is None else timer.time_until_next_call()
        return float("inf") if left is None else left * 1e-6

    # ---- reporting -----------------------------------------------------------------------------------------------
    def warn(self, key: str, message: str):
        allowed, held = self.throttle.allow(key, time.monotonic())
        if allowed:
            suffix = f" ({held} similar messages suppressed)" if held else ""
            self.get_logger().warning(message + suffix)

    def report_error(self, where: str, error: BaseException):
        """An exception caught at `where`: counted on ~/status (errors), logged (throttled) with its reason."""
        self.stats.errors[where] += 1
        self.warn(f"error/{where}", f"{where}: {error!r} (caught; the node goes on with the last good models)")

    def guarded(self, where: str, callback):
        """`callback` for an executor: what it raises is reported, never passed to the spin (which would end)."""
        def run(*args):
            try:
                callback(*args)
            except Exception as error:
                self.report_error(where, error)
        return run

    def reject(self, topic: str, error: InputRejected):
        self.stats.rejected[f"{topic}/{error.reason}"] += 1
        self.warn(f"{topic}/{error.reason}", f"rejected {topic} message ({error.reason}): {error}")

    # ---- the tick, status and markers ----------------------------------------------------------------------------
    def _on_tick(self):
        now = time.monotonic()
        self.stats.tick(now, 1.0 / self.config["rate_hz"])
        start = time.perf_counter()
        report = self.agents.tick()
        self.stats.tick_ms.append(1e3 * (time.perf_counter() - start))  # every tick: taking input costs too
        if report.dressed:
            self.stats.counts["computed_ticks"] += 1
            self.stats.counts["published_frames"] += len(report.dressed)
            return
        self.stats.counts["idle_ticks"] += 1
        keepalive = self.config["keepalive_hz"]
        if keepalive > 0 and now - self.agents.last_publish >= 1.0 / keepalive and self.agents.keepalive():
            self.stats.counts["keepalive_frames"] += 1

    def status(self) -> dict:
        now = time.monotonic()
        counts = dict(self.stats.counts)
        return {
            "node": self.get_fully_qualified_name(),
            "rate_hz": self.config["rate_hz"],
            "tick_rate_hz": round(self.stats.rate(now), 2),
            "tick_ms": TickStats.percentiles(self.stats.tick_ms),
            "synthesis_ms": TickStats.percentiles(self.stats.synthesis_ms),
            "published_frames": counts.pop("published_frames", 0),
            "keepalive_frames": counts.pop("keepalive_frames", 0),
            "late_ticks": counts.pop("late_ticks", 0),
            "rejected": dict(self.stats.rejected),
            "errors": dict(self.stats.errors),
            "counts": counts,
            "pid": os.getpid(),
            **self.agents.status(),
        }

    def _on_status(self):
        self.status_pub.publish(String(data=json.dumps(self.status())))

    def _on_marker(self):
        # Snapshot references only; the marker thread builds the messages (tens of ms each) off the executor.
        self.markers.submit(self.agents.marker_jobs())

    def destroy_node(self):
        self.agents.stop()
        return super().destroy_node()


def main(args=None) -> int:
    """Console script `agentdress_node [--ros-args ...]`. Exit status 0 on Ctrl-C / SIGTERM, 2 when the
    configuration cannot start (the reason, naming the parameter or database file, goes to stderr)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)  # multi-threaded BLAS on 2 cores slowed mid-size products ~100x here
    rclpy.init(args=args if args is not None else sys.argv)
    node = None
    try:
        try:
            node = AgentDressNode()
        except (ConfigError, GarmentDatabaseError, ValueError) as error:
            print(f"agentdress_node: error: {error}", file=sys.stderr, flush=True)
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if set_realtime_priority(node.config["realtime_priority"], node.get_logger()):
            raise_receive_threads(node.agents.receive_threads(), node.config["realtime_priority"] + 1,
                                  node.get_logger())
        spin_until_shutdown(executor.spin)
        return 0
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
