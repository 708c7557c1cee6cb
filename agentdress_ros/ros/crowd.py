"""The node's agents: parameters and topics of one or many agents mapped onto `agentdress_ros.scene` (wiring only).

One path for one and many agents. With `agents` empty the node dresses a crowd of one, the single agent: its
topics are the node's own (joint_state_topic and shape_topic in; ~/<garment>/points, ~/<garment>/mesh, ~/body/*,
~/marker out: the node's docstring), it has no levels of detail (the single agent is always dressed in full), and
~/status carries its keys at the top (synthesis_ms, unknown_joint_names, garments, shape, model_generation, inside).
With `agents` listing names, per agent `<a>` (topics relative to the node's namespace; `~` is
/agentdress_node):
  in   <a>/joint_states          sensor_msgs/JointState      (qos.joint_states.*; <a>/<joint_state_topic>)
  in   <a>/body_shape            std_msgs/Float32MultiArray  (qos.shape.*; <a>/<shape_topic>)
  out  ~/<a>/<garment>/points    sensor_msgs/PointCloud2     (qos.points.*), stamped with the answered JointState
  out  ~/<a>/<garment>/mesh      shape_msgs/Mesh             reliable, transient local, once per (re)build
  out  ~/<a>/body/points|mesh    with publish_body (without the faces its garments cover, as the single agent's)
  out  ~/<a>/body/skin|bones     with publish_body: the body's binding (transient local, per build and shape) and
                                 each frame's bone transforms (the node's single-agent docstring says more)
and for the scene:
  in   <viewer_topic>            geometry_msgs/PoseStamped   the headset, in the agents' frame (or moved there by
                                                             the fixed `viewer_offset` x, y, z, yaw)
Each agent takes the node's garments, garment_databases, garment_vertices, garment_models, engine, shape, frame_id
and publish_body, overridden per agent by `agent.<a>.<parameter>` (startup, from the YAML), plus `agent.<a>.origin`
(its frame's origin in the scene, for distances) and `agent.<a>.extra_cost_ms` (an artificial cost per frame, for
tests and benchmarks of the frame budget). Agents added to `agents` at run time are built on the scene's worker
thread and go live on a later tick; removed ones are dropped at once (their publishers destroyed).

With inside_check_hz > 0 the last cloud of the agent nearest the viewer in view is tested against its posed body
(~/status crowd.inside, the single agent's check).

Inputs are polled: the agents' subscriptions sit on a second node that no executor spins, and each tick takes what
waited (a KEEP_LAST queue keeps only the newest poses of agents nobody looked at). The agents nearest the viewer in
view (ARRIVAL_AGENTS; without a viewer pose, every agent of a crowd that small) also get a subscription on the spun
node, whose callback dresses each pose as it arrives.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import JointState, PointCloud2
from shape_msgs.msg import Mesh
from std_msgs.msg import Float32MultiArray

from ..scene import AgentSpec, LodPolicy, Scene, SceneConfig, Viewer, parse_tiers
from ..motion.joint_names import JOINT_NAMES
from .inputs import InputRejected, PoseInput, check_shape_values, stamp_to_ns
from .inside_check import InsideChecker
from .messages import JointStateReader, SerializedBones, SerializedCloud, make_mesh, make_skin, stamp_from_ns
from .params import PARAMETERS, ParameterError, garment_specs, number

# rclpy gives every publisher and subscription two QoS event handlers (incompatible QoS, incompatible type), and its
# executor rebuilds the wait set from every handler on each callback, matching handlers by list search: with six
# entities per agent, 100 agents made that quadratic walk the node's largest cost. Per-agent entities go without;
# the node's own topics keep them, so a mismatched QoS is still reported there.
QUIET_SUBSCRIPTION = SubscriptionEventCallbacks(use_default_callbacks=False)
QUIET_PUBLISHER = PublisherEventCallbacks(use_default_callbacks=False)
TOPICS = ("joint_states", "body_shape")  # an agent's inputs, in the order of its entity's "subs"
SHAPE_POLL_TICKS = 9  # each agent's body_shape (and, when not dressed, its pose) is looked at every 9th tick
# Agents answered on arrival, the nearest in view: their dressing runs between ticks, outside the budget, so the
# others (a crowd of near agents among them) are dressed by the ticks, which spread it over the ticks between poses.
ARRIVAL_AGENTS = 4
MAX_PENDING = 16  # serialized poses kept per agent between parses (the newest)


def dds_thread_ids() -> list[int]:
    """Thread ids of this process's DDS threads (Fast DDS names them dds.*); [] where /proc is not there."""
    ids = []
    try:
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/comm") as comm:
                    if comm.read().startswith("dds."):
                        ids.append(int(tid))
            except OSError:
                continue  # the thread ended meanwhile
    except OSError:
        pass
    return ids


SINGLE = ""  # the name of the crowd of one's agent: its topics and status keys carry no agent prefix
#: Node parameters that decide an agent's garment models: a build that fails sets them back to the running values.
SCENE_PARAMETERS = ("garments", "garment_vertices", "garment_databases", "garment_models", "engine", "publish_body",
                    "skinned_fallback", "display_subdivision", "garment_layers")


def scoped(name: str, what: str) -> str:
    """`what` of agent `name` (a topic, a status or warning key): "<name>/<what>", just `what` for the single agent."""
    return f"{name}/{what}" if name else what


def _never_called(msg):
    """Callback of the polled subscriptions (their node is never spun)."""


def _take_all(sub, handle) -> list:
    """Every message waiting on subscription `sub` (through its `handle`), oldest first, taken outside the
    executor (serialized for a raw subscription)."""
    taken = []
    with handle:
        while (message := handle.take_message(sub.msg_type, sub.raw)) is not None:
            taken.append(message[0])
    return taken

__all__ = ["AGENT_KEYS", "AgentTopics", "Crowd", "agent_overrides", "scene_config"]

def _origin(name, value) -> tuple:
    if value is None or isinstance(value, (str, bool)) or len(value) != 3 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value):
        raise ParameterError(f"{name} must be three finite numbers (x, y, z), got {value!r}")
    return tuple(float(v) for v in value)


#: Per-agent override keys (`agent.<name>.<key>`) and their checks: node parameters an agent may set for itself
#: (their parameter's check), and crowd-only ones.
AGENT_CHECKS = {**{key: PARAMETERS[key].check for key in ("garments", "garment_databases", "garment_vertices",
                                                          "garment_models", "engine", "shape", "frame_id",
                                                          "publish_body")},
                "origin": _origin, "extra_cost_ms": number(0.0, 1000.0)}
AGENT_KEYS = tuple(AGENT_CHECKS)


def agent_overrides(values: dict) -> dict[str, dict]:
    """{"<agent>.<key>": value} (the node's parameters under the prefix `agent`, from the YAML) -> {agent: {key:
    checked value}}; ParameterError naming an unknown key or a bad value."""
    overrides: dict[str, dict] = {}
    for name, value in sorted(values.items()):
        agent, _, key = name.partition(".")
        if key not in AGENT_KEYS:
            raise ParameterError(f"agent.{name}: unknown per-agent parameter {key!r}; one of {', '.join(AGENT_KEYS)}")
        overrides.setdefault(agent, {})[key] = AGENT_CHECKS[key](f"agent.{name}", value)
    return overrides


@dataclass
class AgentTopics:
    """One agent's ROS side: its polled input subscriptions (joint states, serialized; body shape) and their
    handles, the serialized poses waiting to be parsed and their reader, its publishers per garment (points,
    mesh; skin and bones of a plain LBS model, the body), the agent whose publishers they are, the shape
    generation whose binding went out last, and its marker publisher (the agents nearest the viewer)."""

    subs: list
    handles: list
    pending: list = field(default_factory=list)
    reader: JointStateReader = field(default_factory=JointStateReader)
    points: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)
    skin: dict = field(default_factory=dict)
    bones: dict = field(default_factory=dict)
    installed: object = None
    skin_generation: int | None = None
    drawn: dict = field(default_factory=dict)  # garment -> the topology its mesh publisher sent last
    answered_at: float = -1e18  # time.monotonic() of the last pose answered on arrival
    marker: object = None


def scene_config(config: dict) -> SceneConfig:
    """The node's crowd parameters -> SceneConfig (ValueError with the reason, e.g. a bad tier line). A crowd of
    one has no levels of detail: the single agent is dressed in full whatever the viewer does."""
    lod = LodPolicy(tiers=parse_tiers(config["lod.tiers"]), hysteresis=config["lod.hysteresis"],
                    fov_deg=config["lod.fov_deg"], margin_deg=config["lod.margin_deg"], cull=config["lod.cull"])
    return SceneConfig(lod=lod, lod_enabled=config["lod.enabled"] and bool(config["agents"]),
                       budget_ms=config["budget_ms"], fade_frames=int(config["lod.fade_frames"]))


class Crowd:
    """The crowd on `node` (an AgentDressNode): subscriptions and publishers per agent, the viewer, the tick."""

    def __init__(self, node, body, overrides: dict):
        """`node`: an AgentDressNode (its public publishing, QoS and reporting methods); `overrides`: the values of
        its parameters under the prefix `agent` ({"<agent>.<key>": value})."""
        self.node, self.config = node, node.config
        self.single = not self.config["agents"]
        self.scene = Scene(body, scene_config(self.config), pose_factory=self._pose_input,
                           on_error=lambda message: node.warn("fallback", message), prepare=self._prepare)
        self.overrides = agent_overrides(overrides)
        self.entities: dict[str, AgentTopics] = {}
        self.arrivals: dict = {}  # agent -> its JointState reader on the spun node (the agents answered on arrival)
        # The agents' inputs live on a second node that no executor spins: rclpy's executor walks every entity it
        # waits on for each message it hands out, so with hundreds of subscriptions (2 per agent) receiving cost
        # grew with the crowd. The tick takes what waited since the last one; only the agents it dresses cost
        # more than a take, and a KEEP_LAST queue holds just the newest poses of the others.
        # That node has a DDS participant of its own (a second context): the crowd's poses (3,000 a second for 100
        # agents at 30 Hz) are received by its threads, and the node's own participant receives only the poses of
        # the agents answered on arrival, the viewer pose and the like - few enough that, with realtime_priority,
        # its receive threads run above the executor thread (receive_threads) and hand a pose over at once.
        dds_before = set(dds_thread_ids())
        self.inputs_context = rclpy.Context()
        rclpy.init(context=self.inputs_context, domain_id=node.context.get_domain_id())
        self.inputs = Node(f"{node.get_name()}_inputs", namespace=node.get_namespace(), context=self.inputs_context,
                           enable_rosout=False, start_parameter_services=False)
        self.input_threads = set(dds_thread_ids()) - dds_before
        self._shape_turn = 0
        self.scene.before_dress = self._parse_pending
        self.scene.between_agents = self._answer_arrivals
        self.clouds: dict[tuple, SerializedCloud] = {}  # (agent, garment) -> its last cloud, serialized
        self.bones: dict[tuple, SerializedBones] = {}  # (agent, garment) -> its last bone transforms, serialized
        self.topology: dict[str, dict] = {}  # agent -> {garment: Mesh}, made on the worker
        self.viewer_sub = None
        if self.config["viewer_topic"]:
            self.viewer_sub = node.create_subscription(PoseStamped, self.config["viewer_topic"], self._on_viewer,
                                                       node.qos("viewer"))
        self.viewer_stamp_ns = 0
        # inside_check_hz: the garments of the agent nearest the viewer in view, tested against its posed body
        self.inside = InsideChecker(body, lambda error: node.report_error("inside_check", error))
        self.inside_agent = None
        self.last_publish = 0.0  # time.monotonic() of the last clouds sent (the keep-alive waits a period after)
        self.installs: dict[str, int] = {}  # agent -> agents installed under its name (model_generation)
        # the values of SCENE_PARAMETERS behind the running agents, and behind each build asked for until it goes live
        self._running_parameters = self._scene_parameters()
        self._requested: dict = {}
        self.set_agents(self.names(), initial=True)

    def names(self) -> list[str]:
        """The agents to dress: those `agents` lists, or the single agent."""
        return list(self.config["agents"]) or [SINGLE]

    def ready_message(self, seconds: float) -> str:
        """The start-up log line."""
        if self.single:
            agent = self.scene.agents[SINGLE]
            return f"garment models ready in {seconds:.2f} s: " + ", ".join(
                f"{n} ({g.kind}, {g.n_vertices} vertices)" for n, g in agent.garments.items())
        return (f"crowd ready in {seconds:.2f} s: {len(self.entities)} agents, garments shared: "
                f"{len(self.scene.library)}")

    # ---- agents ---------------------------------------------------------------------------------------------
    def _pose_input(self):
        return PoseInput(self.node.stamp_jump_ns)

    def apply_parameters(self, changed: set):
        """Executor thread, after a successful `ros2 param set`."""
        if changed & {"budget_ms", "viewer_offset"} or any(n.startswith("lod.") for n in changed):
            self.scene.config = scene_config(self.config)
        if "stamp_jump_threshold_s" in changed:
            for agent in self.scene.agents.values():
                agent.pose.stamp_jump_ns = self.node.stamp_jump_ns
        if changed & ((set(AGENT_KEYS) | set(SCENE_PARAMETERS)) - {"shape"}):
            self.rebuild()
        elif "shape" in changed:  # a refit, as a body_shape message: the agents that take the node's shape
            for name in self.entities:
                if "shape" not in self.overrides.get(name, {}):
                    self._apply_shape(name, self.config["shape"], "shape parameter")
        if "agents" in changed:
            self.set_agents(self.names())

    def _scene_parameters(self) -> list:
        return [self.node.get_parameter(name) for name in SCENE_PARAMETERS]

    def spec(self, name: str) -> AgentSpec:
        """The agent's spec: the node's parameters with the agent's overrides."""
        config = {**{k: self.config[k] for k in AGENT_KEYS if k in self.config}, **self.overrides.get(name, {})}
        garments = garment_specs(config)
        beta = tuple(float(b) for b in check_shape_values(config["shape"]).beta)
        return AgentSpec(name, garments, beta, config["frame_id"], config.get("origin", (0.0, 0.0, 0.0)),
                         config.get("extra_cost_ms", 0.0), config["publish_body"], self.config["skinned_fallback"],
                         self.config["display_subdivision"], tuple(self.config["garment_layers"].items()))

    def set_agents(self, names, initial: bool = False):
        """Make the agents `names`: build new ones (at startup now, later on the worker), drop the others."""
        for name in [n for n in self.entities if n not in names]:
            self.scene.remove_agent(name)
            self._destroy(name)
        for name in names:
            if name in self.entities:
                continue
            self._create_inputs(name)
            if initial:
                agent = self.scene.build_agent(self.spec(name))
                self._prepare(agent)
                self.scene.install(agent)
                self._install(agent)
            else:
                self._request(name)

    def _request(self, name: str):
        """Build agent `name` from the current parameters on the worker, remembering them for a rollback."""
        spec = self.spec(name)
        self._requested[spec] = self._scene_parameters()
        while len(self._requested) > 8 + len(self.entities):  # requests superseded before they were built
            self._requested.pop(next(iter(self._requested)))
        self.scene.request_agent(spec)

    def rebuild(self):
        """Every agent again from the current parameters (a garment or engine change), off the frame path (the
        garment data stays loaded in the scene's library: a build that changes nothing is quick)."""
        for name in self.entities:
            self._request(name)

    def take_failures(self):
        """Executor thread: builds that failed keep the running agent; when the parameters still ask for the failed
        build they are set back to the running agent's values, so `ros2 param get` shows what runs."""
        node = self.node
        for name, spec, message in self.scene.take_failures():
            node.stats.counts["rebuild_failures"] += 1
            node.warn("rebuild", message + "; the running garment models stay")
            if spec is None or spec != self.spec(name):
                continue  # a refit, or the parameters have moved on since: their own build decides
            rollback = [p for p in self._running_parameters if p.value != node.get_parameter(p.name).value]
            if not rollback:
                continue
            results = node.set_parameters(rollback)
            if all(r.successful for r in results):
                node.stats.counts["parameter_rollbacks"] += 1
                node.warn("rollback", "parameters set back to the running garment models: "
                          + ", ".join(f"{p.name}={p.value!r}" for p in rollback))
            else:
                node.warn("rollback", "cannot set the parameters back to the running garment models: "
                          + "; ".join(r.reason for r in results if not r.successful))

    def _input_topic(self, name: str, parameter: str) -> str:
        """An agent's input topic: the single agent's (joint_state_topic, shape_topic) under its name."""
        return f"{name}/{self.config[parameter].lstrip('/')}" if name else self.config[parameter]

    def _create_inputs(self, name: str):
        """The agent's input subscriptions, on the node the executor never waits on (see `poll`)."""
        inputs = self.inputs
        subs = [inputs.create_subscription(JointState, self._input_topic(name, "joint_state_topic"), _never_called,
                                           self.node.qos("joint_states"), event_callbacks=QUIET_SUBSCRIPTION,
                                           raw=True),
                inputs.create_subscription(Float32MultiArray, self._input_topic(name, "shape_topic"), _never_called,
                                           self.node.qos("shape"), event_callbacks=QUIET_SUBSCRIPTION)]
        self.entities[name] = AgentTopics(subs, [sub.handle for sub in subs])

    def _prepare(self, agent):
        """Worker thread: topology messages of a built agent, per garment one for each topology its tiers draw
        (lod.Tier.display: the display's, refined, or the garment's own), inner layers first."""
        topology = {}
        for g, garment in agent.garments.items():
            levels = {garment.topology_at(level): level for level in reversed(range(len(self.scene.config.lod.tiers)))}
            topology[g] = {kind: make_mesh(garment.rest_frame(level), garment.faces_at(level))
                           for kind, level in levels.items()}
        self.topology[agent.name] = topology

    def _install(self, agent):
        """Executor thread: publishers of a new (or rebuilt) agent, its topology sent."""
        entity = self.entities.get(agent.name)
        if entity is None:
            return
        node = self.node
        for g in [g for g in entity.points if g not in agent.garments]:
            node.destroy_publisher(entity.points.pop(g))
            node.destroy_publisher(entity.mesh.pop(g))
            self.clouds.pop((agent.name, g), None)
        for g in [g for g in entity.skin if g not in agent.garments or agent.garments[g].skin_binding() is None]:
            node.destroy_publisher(entity.skin.pop(g))
            node.destroy_publisher(entity.bones.pop(g))
            self.bones.pop((agent.name, g), None)
        for g in agent.garments:
            if g not in entity.points:
                entity.points[g] = node.create_publisher(PointCloud2, "~/" + scoped(agent.name, f"{g}/points"),
                                                         node.qos("points"), event_callbacks=QUIET_PUBLISHER)
                entity.mesh[g] = node.create_publisher(Mesh, "~/" + scoped(agent.name, f"{g}/mesh"),
                                                       node.topology_qos, event_callbacks=QUIET_PUBLISHER)
            entity.drawn.pop(g, None)
            self.clouds.pop((agent.name, g), None)  # of the old topology: never re-sent with the new mesh
            self._send_topology(agent, entity, g, agent.garments[g].topology_at(agent.level or 0))
            if g not in entity.skin and agent.garments[g].skin_binding() is not None:
                entity.skin[g] = node.create_publisher(Float32MultiArray, "~/" + scoped(agent.name, f"{g}/skin"),
                                                       node.topology_qos, event_callbacks=QUIET_PUBLISHER)
                entity.bones[g] = node.create_publisher(PoseArray, "~/" + scoped(agent.name, f"{g}/bones"),
                                                        node.qos("points"), event_callbacks=QUIET_PUBLISHER)
        entity.installed = agent
        entity.skin_generation = None  # sent with the agent's next frame
        self.installs[agent.name] = self.installs.get(agent.name, 0) + 1
        parameters = self._requested.pop(agent.spec, None)
        if parameters is not None:
            self._running_parameters = parameters

    def _send_topology(self, agent, entity: "AgentTopics", g: str, kind: str):
        """The garment's topology message of `kind` (Crowd._prepare), unless it is the one sent last: a tier
        change between a displayed and a plain tier changes the faces the clouds follow."""
        if entity.drawn.get(g) == kind:
            return
        mesh = self.topology.get(agent.name, {}).get(g, {}).get(kind)
        if mesh is not None:
            entity.mesh[g].publish(mesh)
            entity.drawn[g] = kind

    def _destroy(self, name: str):
        entity = self.entities.pop(name, None)
        if entity is None:
            return
        for sub in entity.subs:
            self.inputs.destroy_subscription(sub)
        if name in self.arrivals:
            self.node.destroy_subscription(self.arrivals.pop(name))
        for pub in [*entity.points.values(), *entity.mesh.values(), *entity.skin.values(),
                    *entity.bones.values()]:
            self.node.destroy_publisher(pub)
        if entity.marker is not None:
            with self.node.publish_lock:  # the marker thread may be publishing on it
                marker, entity.marker = entity.marker, None
                self.node.destroy_publisher(marker)
        for key in [k for k in self.clouds if k[0] == name]:
            del self.clouds[key]
        for key in [k for k in self.bones if k[0] == name]:
            del self.bones[key]
        self.topology.pop(name, None)

    # ---- inputs ---------------------------------------------------------------------------------------------
    def _take(self, entity: AgentTopics, which: int) -> list:
        """Every message waiting on an agent's subscription `which` (0 joint states, serialized; 1 body shape),
        oldest first."""
        return _take_all(entity.subs[which], entity.handles[which])

    def poll(self):
        """Tick, before the scene decides: take the waiting poses, serialized, of every agent the tick may dress.
        They are parsed only when the agent is dressed (`_parse_pending`, from the scene) or, for every agent,
        every SHAPE_POLL_TICKS-th tick so that distances and visibility stay current; that tick also looks at the
        agent's body shapes."""
        turn = self._shape_turn % SHAPE_POLL_TICKS
        agents = self.scene.agents
        small = len(self.entities) <= ARRIVAL_AGENTS  # a small crowd looks at every shape on every tick
        for i, (name, entity) in enumerate(sorted(self.entities.items())):
            agent = agents.get(name)
            shape_turn = small or i % SHAPE_POLL_TICKS == turn
            # an agent the next tick will not dress (culled, or not due at its tier's rate) leaves its poses in
            # the keep-last queue: taking them is most of the tick's fixed cost in a large crowd
            if shape_turn or agent is None or self.scene.needs_input(agent):
                self._take_poses(name, entity, agent)
            if shape_turn:
                if entity.pending:
                    self._parse_pending(agent)
                shape = self.node.guarded(scoped(name, "body_shape"), self._on_shape)
                for msg in self._take(entity, 1):
                    shape(name, msg)
        self._shape_turn += 1

    def _take_poses(self, name: str, entity: AgentTopics, agent) -> None:
        """The agent's waiting JointStates (serialized) into its pending list; a pose to dress marks it dirty. Poses
        of an agent with an arrival reader are dropped: that reader has them."""
        raw = self._take(entity, 0)
        if raw and name not in self.arrivals:
            self.node.stats.counts["joint_states_received"] += len(raw)
            pending = entity.pending
            pending.extend(raw)
            del pending[:-MAX_PENDING]
            if agent is not None:
                agent.dirty = True  # a pose to dress (parsed as it is dressed)

    def _parse_pending(self, agent):
        """The agent's waiting serialized poses into its pose: the newest, when it names every joint (the older
        ones could not change the result), else all of them oldest first (partial JointStates add up). Poses
        still in its queue (left there by `poll`) are taken first."""
        entity = None if agent is None else self.entities.get(agent.name)
        if entity is None:
            return
        self._take_poses(agent.name, entity, agent)
        if not entity.pending:
            return
        pending, entity.pending = entity.pending, []
        accept = self.node.guarded(scoped(agent.name, "joint_states"), self._on_joint_state)
        newest = entity.reader.read(pending[-1])
        if len(newest[0]) < len(JOINT_NAMES):  # a partial update: the older ones count too (parsing is the cost)
            for raw in pending[:-1]:
                accept(agent.name, *entity.reader.read(raw))
        accept(agent.name, *newest)

    def sync_arrival(self):
        """After a tick: the ARRIVAL_AGENTS agents nearest the viewer in view get a second JointState subscription on
        the spun node, whose callback answers each pose as it arrives (at most once per half period: a flood is
        answered at the node's rate); an agent leaving that set loses it. The executor waits on few entities."""
        node = self.node
        answered = set(self._answered_on_arrival()) if self.config["answer_on_arrival"] else set()
        for name in [n for n in self.arrivals if n not in answered]:
            node.destroy_subscription(self.arrivals.pop(name))
        for name in answered:
            if name not in self.arrivals and name in self.entities:
                self.arrivals[name] = node.create_subscription(
                    JointState, self._input_topic(name, "joint_state_topic"),
                    node.guarded(scoped(name, "joint_states"), lambda m, n=name: self._on_arrival(n, m)),
                    node.qos("joint_states"), event_callbacks=QUIET_SUBSCRIPTION, raw=True)

    def _answered_on_arrival(self) -> list[str]:
        """The agents whose poses are dressed as they arrive: the nearest in view. Without a viewer pose (or with
        LOD off) no agent is nearer than another, so that holds only for a crowd of at most ARRIVAL_AGENTS: in a larger one, a few agents
        picked by name took the budget's slack and the ticks dressed the rest on alternate ticks (ten agents: 60
        frames a second to four, 15 to the other six)."""
        ranked = self.scene.viewer is not None and self.scene.config.lod_enabled  # else every distance is 0
        if not ranked and len(self.scene.agents) > ARRIVAL_AGENTS:
            return []
        return self._nearest_in_view()

    def _nearest_in_view(self) -> list[str]:
        """The ARRIVAL_AGENTS agents nearest the viewer in view, nearest first."""
        near = sorted((a.distance, a.name) for a in self.scene.agents.values() if a.tier is not None and a.visible)
        return [name for _, name in near[:ARRIVAL_AGENTS]]

    def _on_arrival(self, name: str, raw: bytes):
        self.node.stats.counts["joint_states_received"] += 1
        entity = self.entities.get(name)
        if entity is None:
            return
        entity.pending.clear()  # taken by the tick before this reader matched: older than this pose
        self._on_joint_state(name, *entity.reader.read(raw))
        agent = self.scene.agents.get(name)
        if agent is None:
            return
        # Arrivals closer than half a period to the last one answered wait for the tick, which dresses the newest:
        # a flood is answered at twice the rate at most. (Measured from the last answer on arrival, not from the
        # tick's: against the tick's, a sender at the node's rate locked in phase just after the ticks and every
        # pose waited most of a period for one.)
        now = time.monotonic()
        if now - entity.answered_at < 0.5 / self.config["rate_hz"]:
            self.node.stats.counts["arrivals_left_to_tick"] += 1
            return
        # A tick about to start (or overdue) would wait for this agent: leave its pose to the tick, which dresses
        # it among the first (nearest first) inside the budget, instead of making that tick late.
        if agent.tier is not None and self.node.ms_until_tick() < self.scene.estimate(agent, agent.tier):
            self.node.stats.counts["arrivals_left_to_tick"] += 1
            return  # its new pose version makes it a candidate of that tick
        start = time.perf_counter()
        entity.answered_at = now
        if self.scene.dress_now(name, self._publish):
            stats = self.node.stats
            stats.counts["published_frames"] += 1
            stats.counts["computed_ticks"] += 1  # a frame computed outside the timer's ticks
            stats.tick_ms.append(1e3 * (time.perf_counter() - start))

    def _answer_arrivals(self):
        """Scene hook, between the agents a tick dresses: poses that reached the agents answered on arrival while
        the tick runs are answered now instead of after it (their reader's callback would wait for the tick)."""
        for name, sub in list(self.arrivals.items()):
            raws = _take_all(sub, sub.handle)
            if raws:
                answer = self.node.guarded(scoped(name, "joint_states"), self._on_arrival)
                for raw in raws:  # oldest first, as the callback would have had them
                    answer(name, raw)

    def _on_joint_state(self, name: str, names: list, positions: np.ndarray, stamp_ns: int):
        """One JointState (read by the agent's JointStateReader) into the agent's pose."""
        node = self.node
        agent = self.scene.agents.get(name)
        if agent is None:
            return
        try:
            unknown = agent.pose.accept(names, positions, stamp_ns)
        except InputRejected as error:
            node.reject(scoped(name, "joint_states"), error)
            return
        if unknown:  # each name once (listed on ~/status); the log line throttled like every warning
            node.stats.counts["unknown_joint_names"] += len(unknown)
            shown = ", ".join(unknown[:10]) + (f" and {len(unknown) - 10} more" if len(unknown) > 10 else "")
            node.warn(scoped(name, "joint_states/unknown_names"),
                      (f"{name}: " if name else "") + f"ignoring unknown joint names: {shown}")
        jump = agent.pose.timeline_jump_ns
        if jump:  # a cut in this agent's motion: its decay history is from the old one
            node.stats.counts["new_timelines"] += 1
            node.warn(scoped(name, "joint_states/new_timeline"),
                      f"{scoped(name, 'JointState')} stamps jumped {'back' if jump < 0 else 'forward'} by "
                      f"{abs(jump) * 1e-9:.3f} s (more than stamp_jump_threshold_s): following the new timeline")
            for garment in agent.garments.values():
                garment.reset()

    def _on_shape(self, name: str, msg: Float32MultiArray):
        self.node.stats.counts["shapes_received"] += 1
        try:
            self._apply_shape(name, msg.data, scoped(name, "body_shape"))
        except InputRejected as error:
            self.node.reject(scoped(name, "body_shape"), error)

    def _apply_shape(self, name: str, values, source: str):
        """Refit agent `name` to the shape `values` (checked: InputRejected, or clamped with a warning)."""
        update = check_shape_values(values)
        if update.clamped:
            self.node.stats.counts["shapes_clamped"] += 1
            self.node.warn(f"{source}/clamped", f"{source}: {update.message}")
        self.scene.request_shape(name, update.beta)

    def _on_viewer(self, msg: PoseStamped):
        p, q = msg.pose.position, msg.pose.orientation
        try:
            viewer = Viewer.from_pose((p.x, p.y, p.z), (q.x, q.y, q.z, q.w), self.config["viewer_offset"])
        except ValueError as error:
            self.node.reject("viewer_pose", InputRejected("non_finite", str(error)))
            return
        self.viewer_stamp_ns = stamp_to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
        self.scene.set_viewer(viewer)

    # ---- the tick -------------------------------------------------------------------------------------------
    def _publish(self, agent, frames: dict, stamp_ns: int):
        """An agent's dressed frames out, each garment's packed into its (reused) serialized cloud. A garment whose
        dress raised or gave non-finite vertices is never emitted: its last good cloud goes out again, stamped
        with this frame."""
        node = self.node
        node.stats.synthesis_ms.append(agent.dress_ms)
        entity = self.entities.get(agent.name)
        if entity is None or entity.installed is not agent:
            return
        stamp_ns = stamp_ns or node.get_clock().now().nanoseconds
        frame_id = agent.spec.frame_id
        self.last_publish = time.monotonic()
        for g, vertices in frames.items():
            label = scoped(agent.name, g)
            garment = agent.garments[g]
            if vertices is None and g not in agent.errors:  # posed as bones only (_sync_bones_only)
                if g in entity.bones and np.isfinite(garment.base.transforms).all():
                    self._publish_bones(agent, entity, g, stamp_ns)
                    node.stats.counts[f"bones_only_frames:{label}"] += 1
                continue
            key = (agent.name, g)
            if vertices is None or not np.isfinite(vertices).all():
                problem = "synthesis_error" if vertices is None else "non_finite_output"
                node.stats.counts[f"{problem}:{label}"] += 1
                node.warn(f"{problem}/{label}", f"{label}: " + (
                    f"synthesis failed ({agent.errors[g]!r})" if vertices is None else
                    "synthesis produced non-finite vertices") + "; re-sending the last good frame")
                cloud = self.clouds.get(key)
                if cloud is None or cloud.frame_id != frame_id:
                    continue
                vertices = cloud.vertices().copy()
            self._send_topology(agent, entity, g, garment.topology_at(garment.level))
            cloud = self.clouds.get(key)
            try:
                if cloud is None or cloud.frame_id != frame_id or cloud.n_vertices != len(vertices):
                    cloud = self.clouds[key] = SerializedCloud(frame_id, len(vertices))
                data = cloud.set(vertices, stamp_ns)
            except Exception as error:  # a half-written cloud is dropped, never re-sent by the keep-alive
                self.clouds.pop(key, None)
                node.report_error(f"pack/{label}", error)
                continue
            try:
                entity.points[g].publish(data)
            except Exception as error:
                node.report_error(f"publish/{label}", error)
            if g in entity.bones and g not in agent.errors:
                self._publish_bones(agent, entity, g, stamp_ns)

    def _publish_bones(self, agent, entity, g: str, stamp_ns: int):
        """The frame's bone transforms of a plain LBS garment (the body); its binding first when the agent's shape
        changed since it was last sent (the frame was skinned from the new rest)."""
        model = agent.garments[g].base
        if entity.skin_generation != agent.shape_generation:
            for name, pub in entity.skin.items():
                pub.publish(make_skin(*agent.garments[name].base.skin_binding()))
            entity.skin_generation = agent.shape_generation
        key = (agent.name, g)
        bones = self.bones.get(key)
        if bones is None or bones.frame_id != agent.spec.frame_id or bones.n_bones != len(model.transforms):
            bones = self.bones[key] = SerializedBones(agent.spec.frame_id, len(model.transforms))
        entity.bones[g].publish(bones.set(model.transforms, stamp_ns))

    def tick(self) -> dict:
        started = time.perf_counter()
        self.take_failures()
        self.poll()
        self._install_new()
        if self.scene.ticks % SHAPE_POLL_TICKS == 0:
            self._sync_bones_only()
        report = self.scene.tick(self._publish, started=started)
        after = time.perf_counter()
        self.sync_arrival()
        self._install_new()  # agents installed by this tick (built on the worker)
        self.scene.note_after_ms(1e3 * (time.perf_counter() - after))
        return report

    def _sync_bones_only(self):
        """A template streamed as bones (the body) whose points nobody takes (a display client skins it from the
        bones) is posed without vertices: its LBS and 160 kB cloud were most of an agent's frame. Markers need the
        vertices, so not while they are drawn. A late subscriber to the points gets them within SHAPE_POLL_TICKS."""
        markers = self.config["marker_rate_hz"] > 0
        for name, entity in self.entities.items():
            agent = entity.installed
            if agent is None:
                continue
            for g in entity.bones:
                garment = agent.garments.get(g)
                if garment is not None:
                    garment.bones_only = not markers and entity.points[g].get_subscription_count() == 0

    def _install_new(self):
        """Executor thread: make the agents the worker built live. One whose install fails is tried again next
        tick; until then its old publishers and topology stay."""
        for agent in list(self.scene.agents.values()):
            entity = self.entities.get(agent.name)
            if entity is not None and entity.installed is not agent:
                try:
                    self._install(agent)
                except Exception as error:
                    self.node.report_error("install", error)

    def marker_jobs(self) -> list:
        """Executor thread, at marker_rate_hz: (publisher getter, {garment: (vertices copy, faces)}, stamp,
        frame_id) for the ARRIVAL_AGENTS agents nearest the viewer in view (a Marker costs milliseconds of Python
        per garment, built on the node's marker thread: RViz sees the agents it is close to). Their `~/<a>/marker`
        publishers are made here and dropped with the agent."""
        from visualization_msgs.msg import Marker

        node, jobs = self.node, []
        for name in self._nearest_in_view():
            entity, agent = self.entities.get(name), self.scene.agents[name]
            clouds = {g: self.clouds[(name, g)] for g in agent.garments if (name, g) in self.clouds}
            if entity is None or not clouds:
                continue
            if entity.marker is None:
                with node.publish_lock:
                    entity.marker = node.create_publisher(Marker, "~/" + scoped(name, "marker"), 10,
                                                             event_callbacks=QUIET_PUBLISHER)
            frames = {g: (cloud.vertices(), agent.garments[g].faces) for g, cloud in clouds.items()}
            jobs.append((lambda e=entity: e.marker, frames,
                         stamp_from_ns(max(c.stamp_ns for c in clouds.values())), agent.spec.frame_id))
        return jobs

    def keepalive(self) -> bool:
        """Re-send the last clouds of agents in view (a display that joined late); culled agents stay silent.
        Returns whether anything went out."""
        sent = False
        for (name, g), cloud in list(self.clouds.items()):
            agent = self.scene.agents.get(name)
            if agent is not None and agent.visible and name in self.entities:
                self.entities[name].points[g].publish(cloud.data)
                bones = self.bones.get((name, g))
                if bones is not None and g in self.entities[name].bones:
                    self.entities[name].bones[g].publish(bones.data)
                sent = True
        self.last_publish = time.monotonic()
        return sent

    def status(self) -> dict:
        status = self.scene.status()
        status["agents_detail"] = {a.name: {"tier": None if a.tier is None else self.scene.config.lod.tiers[a.tier].name,
                                            "visible": a.visible, "frames": a.frames,
                                            "distance": round(a.distance, 2)}
                                   for a in self.scene.agents.values()}
        status["pending"] = sorted(set(self.entities) - set(self.scene.agents))
        status["worker_idle"] = self.scene.idle()  # no agent build or shape refit waiting
        status["inside"] = {"agent": self.inside_agent, **self.inside.status()}
        if not self.single:
            return {"crowd": status}
        agent = self.scene.agents[SINGLE]
        return {"crowd": status, "unknown_joint_names": sorted(agent.pose.unknown_names)[:50],
                "garments": {n: {"kind": g.kind, "vertices": g.n_vertices, "faces": len(g.faces),
                                 "shape_limits": g.shape_limits}  # what the garment cannot follow
                             for n, g in agent.garments.items()},
                "shape": list(agent.beta), "model_generation": self.installs[SINGLE] - 1 + agent.shape_generation,
                "inside": self.inside.status()}

    def check_inside(self):
        """Executor thread, at inside_check_hz: hand the last clouds of the agent nearest the viewer in view (not its
        body) to the inside checker's thread, with the pose they were dressed for (skipped while a newer pose
        waits: the next call takes it)."""
        nearest = self._nearest_in_view()
        agent = self.scene.agents.get(nearest[0]) if nearest else None
        if agent is None or agent.pose.version != agent.done_version:
            return
        frames = {g: (self.clouds[(agent.name, g)].vertices(), garment.faces) for g, garment in agent.garments.items()
                  if g != "body" and (agent.name, g) in self.clouds}
        if frames:
            self.inside_agent = agent.name
            self.inside.submit(frames, agent.pose.rotvecs, agent.pose.root_translation, agent.beta)

    def receive_threads(self) -> list[int]:
        """Thread ids of the DDS threads of the node's own participant (not those of the crowd's inputs)."""
        return [t for t in dds_thread_ids() if t not in self.input_threads]

    def stop(self):
        self.inside.stop()
        self.scene.stop()
        self.inputs.destroy_node()
        self.inputs_context.try_shutdown()
