"""agentdress_node: dresses the agent of a JointState stream (wiring only; the work lives in runtime/inputs/params).

Topics (relative to the node, `~` = /agentdress_node):
  in   <joint_state_topic>  sensor_msgs/JointState        (QoS qos.joint_states.*, default best effort, depth 1)
  in   <shape_topic>        std_msgs/Float32MultiArray    (QoS qos.shape.*, default reliable, depth 1)
  out  ~/<garment>/points   sensor_msgs/PointCloud2       every tick with a new pose (qos.points.*: best effort, 1)
  out  ~/<garment>/mesh     shape_msgs/Mesh               reliable, transient local: once per garment (re)build
  out  ~/body/points, ~/body/mesh                         only with publish_body (points only while someone
                                                          subscribes: else the body is posed as bones alone)
  out  ~/body/skin               std_msgs/Float32MultiArray    reliable, transient local: the body's rest vertices,
                                                          bone indices and weights (messages.make_skin), once per
                                                          (re)build and shape
  out  ~/body/bones              geometry_msgs/PoseArray       with each body frame: its bone transforms, from which
                                                          a display client skins the body itself (exactly the cloud)
  out  ~/marker             visualization_msgs/Marker     only with marker_rate_hz > 0 (one per garment, ns = name;
                                                          a crowd: ~/<agent>/marker for the agents nearest the viewer)
  out  ~/status             std_msgs/String (JSON)        at status_rate_hz; "inside" (a crowd: crowd.inside, the
                                                          agent nearest the viewer): the last garments' shares
                                                          inside the body (inside_check_hz)

The status is JSON on a String rather than diagnostic_msgs on /diagnostics: its content is nested (timings,
counts by reason, per-garment facts) and the bench, the viewer and the tests parse it directly; DiagnosticArray
would flatten it into string key/values and needs an aggregator to be readable.

Timer ticks do nothing when no new pose arrived and nothing changed, except re-publishing the last clouds at
keepalive_hz (default 1 Hz: a display that joins late, or a best-effort sample lost on the way, is repaired within a
second for the cost of one publish per garment per second, with no synthesis).

No exception ends the node: every timer, subscription and parameter callback, the model worker and the marker
thread catch what they raise, log it (throttled) and count it under `errors` on ~/status; the last good clouds keep
flowing, and a worker or marker thread that dies is restarted.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, PointCloud2
from shape_msgs.msg import Mesh
from std_msgs.msg import Float32MultiArray, String
from visualization_msgs.msg import Marker

from ..garment import TEMPLATES
from ..models.garment_models import GarmentDatabaseError, skin_binding
from .inputs import InputRejected, PoseInput, check_shape_values, stamp_to_ns
from .inside_check import InsideChecker
from .messages import (SerializedBones, make_marker, make_mesh, make_point_cloud, make_skin, set_cloud_vertices,
                       stamp_from_ns)
from .params import (PARAMETERS, ParameterError, check_garment_config, database_file_problem,
                     garment_specs, validate)
from .runtime import (ModelSet, ModelWorker, OutputGuard, SceneSpec, TickStats, build_model_set,
                      scene_key)
from .spin import spin_until_shutdown

NODE_NAME = "agentdress_node"
TOPOLOGY_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: Parameters that shape the model set: a rebuild that fails rolls them back to the values of the running set.
SCENE_PARAMETERS = ("garments", "garment_vertices", "garment_databases", "garment_models", "engine", "publish_body",
                    "skinned_fallback")
MARKER_COLORS = ((0.2, 0.45, 0.85, 1.0), (0.25, 0.25, 0.3, 1.0), (0.85, 0.4, 0.2, 1.0), (0.9, 0.75, 0.6, 1.0))


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
        self.pose = PoseInput(self.stamp_jump_ns)
        self.guard = OutputGuard()
        self.publish_lock = threading.Lock()  # guards publishers against the marker thread

        from ..body import AnnyBody

        self.body = body if body is not None else AnnyBody()
        self.topology_qos = TOPOLOGY_QOS
        self.crowd = None
        if self.config["agents"]:
            self._start_crowd()
        else:
            self._start_single()
        self.status_pub = self.create_publisher(String, "~/status", 10)
        self.marker_pub = None
        self._marker_job, self._marker_event = None, threading.Event()
        self._done_version, self._dirty, self._last_publish = -1, True, 0.0
        self._last_compute = 0.0
        self._timer_by_key = {}
        self._set_timer("tick", self.config["rate_hz"], self._on_tick)
        self._set_timer("status", self.config["status_rate_hz"], self._on_status)
        self._set_timer("marker", self.config["marker_rate_hz"], self._on_marker)
        self._set_timer("inside", self.config["inside_check_hz"], self._on_inside_check)
        self._start_marker_thread()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

    def _start_crowd(self):
        """Crowd mode: every agent of `agents` dressed by one scene (agentdress_ros.ros.crowd)."""
        from .crowd import Crowd

        start = time.perf_counter()
        try:
            self.crowd = Crowd(self, self.body, {name: parameter.value for name, parameter
                                                 in self.get_parameters_by_prefix("agent").items()})
        except ParameterError as error:
            raise ConfigError(str(error)) from None
        self.get_logger().info(f"crowd ready in {time.perf_counter() - start:.2f} s: {len(self.crowd.entities)} "
                               f"agents, garments shared: {len(self.crowd.scene.library)}")

    def qos(self, kind: str) -> QoSProfile:
        """The QoS of a stream kind: joint_states, shape, points (parameters qos.<kind>.*), viewer (best effort)."""
        if kind == "viewer":
            return _qos("best_effort", 1)
        return _qos(self.config[f"qos.{kind}.reliability"], self.config[f"qos.{kind}.depth"])

    def _start_single(self):
        """Today's single agent: joint_states and body_shape in, ~/<garment>/points and mesh out."""
        start = time.perf_counter()
        model_set = build_model_set(self._scene(), self.body)  # GarmentDatabaseError names the file: exit
        self._prepare(model_set, None)
        for warning in model_set.warnings:
            self.get_logger().warning(warning)
        self.get_logger().info(f"garment models ready in {time.perf_counter() - start:.2f} s: " + ", ".join(
            f"{n} ({m.kind}, {m.n_vertices} vertices)" for n, m in model_set.models.items()))
        self.models, self.model_set = {}, None
        self.point_pubs, self.mesh_pubs, self.clouds = {}, {}, {}
        self.skin_pubs, self.bone_pubs, self.bones = {}, {}, {}  # plain LBS models (the body): skin + bones topics
        # Parameter values of the running model set, and of the sets asked for (by scene key) until one is built.
        self._running_parameters = self._scene_parameters()
        self._requested_parameters: dict[tuple, list[Parameter]] = {}
        self._retry_install = None
        self._last_pose = None  # (rotvecs, root translation) of the last frame computed
        self.inside = InsideChecker(self.body, lambda error: self.report_error("inside_check", error))
        self._install(model_set)
        self.worker = ModelWorker(self.body, model_set, on_built=self._on_built, prepare=self._prepare)

        self.create_subscription(JointState, self.config["joint_state_topic"],
                                 self.guarded("joint_states", self._on_joint_state), self.qos("joint_states"))
        self.create_subscription(Float32MultiArray, self.config["shape_topic"],
                                 self.guarded("body_shape", self._on_shape), self.qos("shape"))

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

    def _scene(self, config=None, beta=None) -> SceneSpec:
        config = config or self.config
        garments = garment_specs(config)
        if beta is None:
            beta = check_shape_values(config["shape"]).beta
        return SceneSpec(garments, config["publish_body"], tuple(float(b) for b in beta), config["skinned_fallback"],
                         config["display_subdivision"], tuple(config["garment_layers"].items()))

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

    def _scene_parameters(self) -> list[Parameter]:
        return [self.get_parameter(name) for name in SCENE_PARAMETERS]

    def _after_set_parameters(self, parameters):
        try:
            self._apply_parameters(parameters)
        except Exception as error:  # raised into rclpy's parameter service, it would end the spin
            self.report_error("parameters", error)

    def _apply_parameters(self, parameters):
        changed = {p.name for p in parameters}
        for p in parameters:
            self.config[p.name] = validate(p.name, p.value)
        for name, key, callback in (("rate_hz", "tick", self._on_tick), ("status_rate_hz", "status", self._on_status),
                                    ("marker_rate_hz", "marker", self._on_marker),
                                    ("inside_check_hz", "inside", self._on_inside_check)):
            if name in changed:
                self._set_timer(key, self.config[name], callback)
        if "warn_throttle_s" in changed:
            self.throttle.period = self.config["warn_throttle_s"]
        if self.crowd is not None:
            self.crowd.apply_parameters(changed)
            return
        if "stamp_jump_threshold_s" in changed:
            self.pose.stamp_jump_ns = self.stamp_jump_ns
        if "frame_id" in changed:
            self._dirty = True
        if "shape" in changed:
            self._apply_shape(self.config["shape"], "shape parameter")
        if changed & set(SCENE_PARAMETERS):
            self._request_scene()

    def _request_scene(self):
        """Ask the worker for the scene of the current parameters, remembering their values for a rollback."""
        scene = self._scene(beta=self.worker.wanted.beta)
        scene = self.worker.request(garments=scene.garments, publish_body=scene.publish_body,
                                    skinned_fallback=scene.skinned_fallback)
        self._requested_parameters[scene_key(scene)] = self._scene_parameters()
        while len(self._requested_parameters) > 8:  # keys of superseded requests that were never built
            self._requested_parameters.pop(next(iter(self._requested_parameters)))

    def _set_timer(self, key, rate_hz, callback):
        old = self._timer_by_key.pop(key, None)
        if old is not None:
            self.destroy_timer(old)
        if rate_hz > 0:
            self._timer_by_key[key] = self.create_timer(1.0 / rate_hz, self.guarded(key, callback))
        if key == "marker" and rate_hz > 0 and getattr(self, "marker_pub", None) is None:
            self.marker_pub = self.create_publisher(Marker, "~/marker", 10)

    def ms_until_tick(self) -> float:
        """Milliseconds until the tick timer is next due (negative: overdue; inf without a timer)."""
        timer = self._timer_by_key.get("tick")
        left = None if timer is None else timer.time_until_next_call()
        return float("inf") if left is None else left * 1e-6

    # ---- models --------------------------------------------------------------------------------------------------
    def _topology(self, model) -> Mesh:
        """The topology message of a model: its rest-pose frame and faces."""
        vertices = model.synthesize(np.zeros((self.body.n_bones, 3)), np.zeros(3))
        mesh = make_mesh(vertices, model.faces)
        model.reset()  # the rest-pose frame made for the topology is not motion: no decay history from it
        return mesh

    def _prepare(self, model_set, previous):
        """Worker thread: topology messages for models that are new (not reused or refitted clones)."""
        for name, model in model_set.models.items():
            if previous is not None and previous.specs.get(name) == model_set.specs[name]:
                continue  # the same garment refitted to a new shape: same topology, nothing to re-send
            model_set.topology[name] = self._topology(model)

    def _on_built(self, model_set, seconds):
        for warning in model_set.warnings:
            self.warn("fallback", warning)
        # A new garment or level of detail is news; a shape refit (up to once a second from a sweep) is not.
        log = self.get_logger().info if model_set.topology else self.get_logger().debug
        log(f"garment models rebuilt in {1e3 * seconds:.0f} ms (generation {model_set.generation}): "
            + ", ".join(f"{n} ({m.n_vertices} vertices)" for n, m in model_set.models.items()))

    def _install(self, model_set: ModelSet):
        """Executor thread: make `model_set` live; (re)publish the topology of every model whose spec differs from
        the running one; drop removed garments. Whatever can fail runs before the switch: a failure leaves the
        running set live and intact."""
        with self.publish_lock:
            running = self.model_set.specs if self.model_set is not None else {}
            points_qos = self.qos("points")
            for name in model_set.models:
                if name not in self.point_pubs:
                    self.point_pubs[name] = self.create_publisher(PointCloud2, f"~/{name}/points", points_qos)
                    self.mesh_pubs[name] = self.create_publisher(Mesh, f"~/{name}/mesh", TOPOLOGY_QOS)
            # The worker made the messages of its new models; one missing here (the set it was made for never
            # went live) is made now rather than leaving clouds without their mesh.
            changed = {name: model_set.topology.get(name) or self._topology(model)
                       for name, model in model_set.models.items() if running.get(name) != model_set.specs[name]}
            for name, mesh in changed.items():
                self.mesh_pubs[name].publish(mesh)
                self.guard.reset(name)  # a new topology: the last good frame of the old one no longer fits
                self.clouds.pop(name, None)
            for name, model in model_set.models.items():  # every install: a shape refit moves the rest too
                binding = skin_binding(model)
                if binding is None:
                    continue
                if name not in self.skin_pubs:
                    self.skin_pubs[name] = self.create_publisher(Float32MultiArray, f"~/{name}/skin", TOPOLOGY_QOS)
                    self.bone_pubs[name] = self.create_publisher(PoseArray, f"~/{name}/bones", points_qos)
                self.skin_pubs[name].publish(make_skin(*binding))
                self.bones.pop(name, None)
            self.models, self.model_set = dict(model_set.models), model_set
            self._dirty = True
            for name in [n for n in self.point_pubs if n not in model_set.models]:
                self.clouds.pop(name, None)
                self.guard.reset(name)
                self.destroy_publisher(self.point_pubs.pop(name))
                self.destroy_publisher(self.mesh_pubs.pop(name))
            for name in [n for n in self.skin_pubs if skin_binding(model_set.models.get(n)) is None]:
                self.bones.pop(name, None)
                self.destroy_publisher(self.skin_pubs.pop(name))
                self.destroy_publisher(self.bone_pubs.pop(name))
        parameters = self._requested_parameters.pop(scene_key(model_set.scene), None)
        if parameters is not None:
            self._running_parameters = parameters

    def _take_worker_news(self):
        """Executor thread: install a built set, act on a failed build, report what the worker caught."""
        if self.worker.ensure_running():
            self.stats.counts["worker_restarts"] += 1
            self.warn("worker", "the model worker thread had died: restarted")
            self._request_scene()
        for message in self.worker.take_errors():
            self.stats.errors["worker"] += 1
            self.warn("worker", message)
        failure = self.worker.take_failure()
        if failure is not None:
            self._on_rebuild_failed(*failure)
        # A set whose install failed is tried again next tick, unless a newer one supersedes it.
        ready, self._retry_install = self.worker.take_ready() or self._retry_install, None
        if ready is not None:
            try:
                self._install(ready)
            except Exception as error:
                self.report_error("install", error)
                self._retry_install = ready

    def _on_rebuild_failed(self, scene: SceneSpec, message: str):
        """A requested model set could not be built: the running one stays. If the parameters still ask for the
        failed set, set them back to the running set's values, so `ros2 param get` shows what runs."""
        self.stats.counts["rebuild_failures"] += 1
        self.warn("rebuild", message + "; the running garment models stay")
        if scene_key(scene) != scene_key(self._scene()):
            return  # the parameters have moved on since: their own build decides
        rollback = [p for p in self._running_parameters if p.value != self.get_parameter(p.name).value]
        if not rollback:
            return
        results = self.set_parameters(rollback)
        if all(r.successful for r in results):
            self.stats.counts["parameter_rollbacks"] += 1
            self.warn("rollback", "parameters set back to the running garment models: "
                       + ", ".join(f"{p.name}={p.value!r}" for p in rollback))
        else:
            self.warn("rollback", "cannot set the parameters back to the running garment models: "
                       + "; ".join(r.reason for r in results if not r.successful))

    # ---- inputs --------------------------------------------------------------------------------------------------
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

    def _on_joint_state(self, msg: JointState):
        self.stats.counts["joint_states_received"] += 1
        try:
            unknown = self.pose.accept(msg.name, msg.position, stamp_to_ns(msg.header.stamp.sec,
                                                                              msg.header.stamp.nanosec))
        except InputRejected as error:
            self.reject("joint_states", error)
            return
        except Exception as error:  # never let a message kill the node
            self.reject("joint_states", InputRejected("internal_error", repr(error)))
            return
        if unknown:  # each name once (the names listed on ~/status); the log line throttled like every warning
            self.stats.counts["unknown_joint_names"] += len(unknown)
            shown = ", ".join(unknown[:10]) + (f" and {len(unknown) - 10} more" if len(unknown) > 10 else "")
            self.warn("joint_states/unknown_names", f"ignoring unknown joint names: {shown}")
        if self.pose.timeline_jump_ns:
            self._on_new_timeline(self.pose.timeline_jump_ns)
        # Answer now rather than at the next tick (up to a period later). Arrivals closer than half a period to
        # the last answer wait for the timer, which dresses the newest one: a flood cannot exceed twice rate_hz,
        # and a sender at rate_hz (jittering around one period) is still answered on arrival.
        if self.config["answer_on_arrival"] and time.monotonic() - self._last_compute >= 0.5 / self.config["rate_hz"]:
            self._on_tick(from_timer=False)

    def _on_new_timeline(self, jump_ns: int):
        """The stamps jumped (looped bag, clock reset, a stamp from the future): a cut in the motion."""
        self.stats.counts["new_timelines"] += 1
        self.warn("joint_states/new_timeline", f"JointState stamps jumped {'back' if jump_ns < 0 else 'forward'} by "
                   f"{abs(jump_ns) * 1e-9:.3f} s (more than stamp_jump_threshold_s): following the new timeline")
        for model in self.models.values():
            model.reset()  # the motion history (decay) belongs to the old timeline

    def _on_shape(self, msg: Float32MultiArray):
        self.stats.counts["shapes_received"] += 1
        try:
            self._apply_shape(msg.data, "body_shape")
        except InputRejected as error:
            self.reject("body_shape", error)
        except Exception as error:
            self.reject("body_shape", InputRejected("internal_error", repr(error)))

    def _apply_shape(self, values, source: str):
        update = check_shape_values(values)
        if update.clamped:
            self.stats.counts["shapes_clamped"] += 1
            self.warn(f"{source}/clamped", f"{source}: {update.message}")
        self.worker.request(beta=tuple(float(b) for b in update.beta))

    # ---- per-frame path ------------------------------------------------------------------------------------------
    def _on_tick(self, from_timer: bool = True):
        now = time.monotonic()
        if from_timer:  # the tick-rate statistics describe the timer, not the arrivals
            self.stats.tick(now, 1.0 / self.config["rate_hz"])
        if self.crowd is not None:
            self._crowd_tick(now)
            return
        self._take_worker_news()
        if self.pose.version == self._done_version and not self._dirty:
            keepalive = self.config["keepalive_hz"]
            if keepalive > 0 and now - self._last_publish >= 1.0 / keepalive and self.clouds:
                for name, cloud in self.clouds.items():
                    self._publish_cloud(name, cloud)
                for name, bones in self.bones.items():
                    self.bone_pubs[name].publish(bones.data)
                self.stats.counts["keepalive_frames"] += 1
                self._last_publish = now
            self.stats.counts["idle_ticks"] += 1
            return
        start = time.perf_counter()
        rotvecs, translation = self.pose.rotvecs, self.pose.root_translation
        stamp = stamp_from_ns(self.pose.stamp_ns or self.get_clock().now().nanoseconds)
        synthesis = 0.0
        for name, model in self.models.items():
            if self._bones_only(name):
                self._pose_bones_only(name, model, rotvecs, translation, stamp)
                continue
            t0 = time.perf_counter()
            try:
                vertices = model.synthesize(rotvecs, translation)
            except Exception as error:
                vertices = None
                self.warn(f"synthesis/{name}", f"{name}: synthesis failed ({error!r}); re-sending the last good frame")
            synthesis += time.perf_counter() - t0
            frame, problem = self.guard.check(name, vertices)
            if problem:
                self.stats.counts[f"{problem}:{name}"] += 1
                if problem == "non_finite_output":
                    self.warn(f"nonfinite/{name}", f"{name}: synthesis produced non-finite vertices; "
                                                    "re-sending the last good frame")
            if frame is not None:
                self._publish_frame(name, frame, stamp)
                if name in self.bone_pubs and not problem:
                    self._publish_bones(name, model.transforms, stamp)
        self.stats.counts["published_frames"] += 1
        self.stats.counts["computed_ticks"] += 1
        self.stats.synthesis_ms.append(1e3 * synthesis)
        self.stats.tick_ms.append(1e3 * (time.perf_counter() - start))
        self._done_version, self._dirty, self._last_publish = self.pose.version, False, now
        self._last_compute = now
        self._last_pose = (rotvecs, translation)

    def _bones_only(self, name: str) -> bool:
        """A plain-LBS model streamed as bones (the body) whose points nobody takes - a display client skins it from
        `skin` and `bones` - is posed without its vertices (13,380 for the body, a 160 kB cloud each frame). Not
        while Markers are drawn: they need the vertices."""
        return name in self.bone_pubs and self.config["marker_rate_hz"] <= 0 \
            and self.point_pubs[name].get_subscription_count() == 0

    def _pose_bones_only(self, name: str, model, rotvecs, translation, stamp):
        try:
            model.pose_bones(rotvecs, translation)
        except Exception as error:
            self.warn(f"synthesis/{name}", f"{name}: posing failed ({error!r})")
            return
        if not np.isfinite(model.transforms).all():  # never emit garbage: the client keeps the last good bones
            self.stats.counts[f"non_finite_output:{name}"] += 1
            return
        self._publish_bones(name, model.transforms, stamp)
        self.stats.counts[f"bones_only_frames:{name}"] += 1

    def _crowd_tick(self, now: float):
        start = time.perf_counter()
        report = self.crowd.tick()
        self.stats.tick_ms.append(1e3 * (time.perf_counter() - start))  # every tick: taking input costs too
        if report.dressed:
            self.stats.counts["computed_ticks"] += 1
            self.stats.counts["published_frames"] += len(report.dressed)
            self._last_publish = now
        else:
            self.stats.counts["idle_ticks"] += 1
            keepalive = self.config["keepalive_hz"]
            if keepalive > 0 and now - self._last_publish >= 1.0 / keepalive:
                self.crowd.keepalive()
                self.stats.counts["keepalive_frames"] += 1
                self._last_publish = now

    def _publish_frame(self, name: str, frame, stamp):
        """Pack `frame` into the garment's (reused) cloud and publish it. A cloud whose packing failed may be half
        written: it is dropped (never re-sent by the keep-alive) and a fresh one made next time."""
        cloud = self.clouds.get(name)
        try:
            if cloud is None:
                cloud = make_point_cloud()
            set_cloud_vertices(cloud, frame, stamp, self.config["frame_id"])
        except Exception as error:
            self.clouds.pop(name, None)
            self.report_error(f"pack/{name}", error)
            return
        self.clouds[name] = cloud
        self._publish_cloud(name, cloud)

    def _publish_bones(self, name: str, transforms, stamp):
        bones = self.bones.get(name)
        if bones is None or bones.frame_id != self.config["frame_id"] or bones.n_bones != len(transforms):
            bones = self.bones[name] = SerializedBones(self.config["frame_id"], len(transforms))
        self.bone_pubs[name].publish(bones.set(transforms, stamp.sec * 1_000_000_000 + stamp.nanosec))

    def _publish_cloud(self, name: str, cloud):
        try:
            self.point_pubs[name].publish(cloud)
        except Exception as error:
            self.report_error(f"publish/{name}", error)

    # ---- status and markers --------------------------------------------------------------------------------------
    def status(self) -> dict:
        now = time.monotonic()
        counts = dict(self.stats.counts)
        status = {
            "node": self.get_fully_qualified_name(),
            "rate_hz": self.config["rate_hz"],
            "tick_rate_hz": round(self.stats.rate(now), 2),
            "tick_ms": TickStats.percentiles(self.stats.tick_ms),
            "published_frames": counts.pop("published_frames", 0),
            "keepalive_frames": counts.pop("keepalive_frames", 0),
            "late_ticks": counts.pop("late_ticks", 0),
            "rejected": dict(self.stats.rejected),
            "errors": dict(self.stats.errors),
            "counts": counts,
            "pid": os.getpid(),
        }
        if self.crowd is not None:
            return {**status, "crowd": self.crowd.status()}
        return {
            **status,
            "synthesis_ms": TickStats.percentiles(self.stats.synthesis_ms),
            "unknown_joint_names": sorted(self.pose.unknown_names)[:50],
            "garments": {n: {"kind": m.kind, "vertices": m.n_vertices, "faces": len(m.faces),
                             "shape_limits": getattr(m, "shape_limits", None)}  # what the garment cannot follow
                         for n, m in self.models.items()},
            "shape": list(self.model_set.scene.beta),
            "model_generation": self.model_set.generation,
            "inside": self.inside.status(),
        }

    def _on_inside_check(self):
        """Hand the last published garments (not the body) and their pose to the inside checker's thread."""
        if self.crowd is not None:
            self.crowd.check_inside()
            return
        if self._last_pose is None:
            return
        frames = {n: (self.guard.last_good[n].copy(), m.faces) for n, m in self.models.items()
                  if n in self.guard.last_good and n != "body"}
        if frames:
            self.inside.submit(frames, *self._last_pose, self.model_set.scene.beta)

    def _on_status(self):
        self.status_pub.publish(String(data=json.dumps(self.status())))

    def _start_marker_thread(self):
        self._marker_thread = threading.Thread(target=self._marker_loop, name="agentdress-marker", daemon=True)
        self._marker_thread.start()

    def _on_marker(self):
        if self.marker_pub is None:
            return
        if not self._marker_thread.is_alive():  # it died of something the loop does not catch: start a new one
            self.stats.counts["marker_restarts"] += 1
            self.warn("marker_thread", "the marker thread had died: restarted")
            self._start_marker_thread()
        # Snapshot references only; the marker thread builds the messages (tens of ms each) off the executor.
        if self.crowd is not None:
            self._marker_job = self.crowd.marker_jobs()
        else:
            frames = {n: (self.guard.last_good[n].copy(), self.models[n].faces) for n in self.models
                      if n in self.guard.last_good}
            stamp = (self.clouds[next(iter(self.clouds))].header.stamp if self.clouds
                     else self.get_clock().now().to_msg())
            self._marker_job = [(lambda: self.marker_pub, frames, stamp, self.config["frame_id"])]
        self._marker_event.set()

    def _marker_loop(self):
        while rclpy.ok(context=self.context):
            if not self._marker_event.wait(timeout=0.5):
                continue
            self._marker_event.clear()
            job, self._marker_job = self._marker_job, None
            if job is None:
                continue
            try:
                for publisher, frames, stamp, frame_id in job:
                    self._publish_markers(publisher, frames, stamp, frame_id)
            except Exception as error:  # the next job is a fresh try; the thread goes on
                self.report_error("marker_thread", error)

    def _publish_markers(self, publisher, frames, stamp, frame_id):
        """One Marker per garment of `frames` {name: (vertices, faces)} on `publisher()` (looked up under the lock:
        None once the publisher is gone)."""
        for i, (name, (vertices, faces)) in enumerate(frames.items()):
            marker = make_marker(vertices, faces, name, i, frame_id, stamp, MARKER_COLORS[i % len(MARKER_COLORS)])
            with self.publish_lock:
                pub = publisher()
                if pub is not None:
                    pub.publish(marker)

    def destroy_node(self):
        if self.crowd is not None:
            self.crowd.stop()
        else:
            self.worker.stop()
            self.inside.stop()
        return super().destroy_node()


def set_realtime_priority(priority: int, logger) -> bool:
    """SCHED_FIFO at `priority` for the calling thread only (the executor's; the DDS threads keep the normal
    scheduler and run while it waits between ticks). Returns whether it took; a refusal is logged with the remedy."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as error:
        logger.warning(f"realtime_priority {priority}: not allowed ({error.strerror or error}); running with the "
                       "normal scheduler. Grant CAP_SYS_NICE (e.g. docker --cap-add SYS_NICE) or an rtprio limit "
                       "(ulimit -r, /etc/security/limits.conf)")
        return False
    logger.info(f"executor thread at SCHED_FIFO priority {priority}")
    return True


def raise_receive_threads(thread_ids, priority: int, logger) -> int:
    """SCHED_FIFO at `priority` (above the executor's) for the crowd node's own DDS threads: they receive only the
    poses answered on arrival and other low-rate input, and hand them over without waiting for the end of a tick.
    Returns how many threads took it."""
    raised = 0
    for tid in thread_ids:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            raised += 1
        except (PermissionError, OSError):
            continue  # ended meanwhile, or refused like the executor's would have been
    logger.info(f"{raised} DDS receive threads of the node's own participant at SCHED_FIFO priority {priority}")
    return raised


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
            message = f"agentdress_node: error: {error}"
            print(message, file=sys.stderr, flush=True)
            return 2
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        if set_realtime_priority(node.config["realtime_priority"], node.get_logger()) and node.crowd is not None:
            raise_receive_threads(node.crowd.receive_threads(), node.config["realtime_priority"] + 1,
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
