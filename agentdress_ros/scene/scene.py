"""A crowd of agents dressed on one thread: levels of detail, culling, idle skip and the frame budget (no ROS).

    scene = Scene(body, SceneConfig(budget_ms=8.0))
    scene.request_agent(AgentSpec("alice", garments, beta))   # built on the worker thread, installed by a tick
    scene.agents["alice"].pose.accept(...)                    # the pose input (scene.pose.PoseInput)
    scene.set_viewer(Viewer.from_pose(position, quaternion))  # optional
    report = scene.tick(publish)   # publish(agent, {garment: (V, 3) float32}, stamp_ns) per dressed agent

Each tick: install what the worker built (new agents, removals are immediate); per agent the distance to the
viewer picks a tier (hysteresis), the viewing cone culls; an agent is a candidate when it is visible, due (tiers
with `every` > 1 on their ticks, staggered over agents) and something changed (new pose, new shape, back in view,
a fade in progress); the scheduler fits the candidates into `budget_ms` with the measured cost of each agent's
level and what is left of the budget after the tick's fixed costs (taking input, deciding, bookkeeping after);
the decisions run nearest first, each timed (dressing + publish) into its level's cost estimate.
"""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from ..body import REFERENCE_SHAPE
from ..motion.skeleton import NUM_BONES
from .garments import AgentGarment, GarmentLibrary, GarmentSpec
from .lod import LodPolicy, Viewer
from .pose import PoseInput
from .scheduler import Candidate, schedule

__all__ = ["AgentSpec", "Scene", "SceneConfig", "TickReport"]

#: Height of the hips above the root translation's origin (the rest Hips sit ~0.9 m up): the agent's centre.
HIPS_HEIGHT = 0.9
DEFAULT_COST_MS = 0.2  # estimate for a level never measured yet
INTERLEAVE_MS = 1.0  # the between_agents hook runs at most this often within a tick
MIN_DRESSING_MS = 0.01  # dressing budget left when the fixed costs alone fill the tick (near agents still dressed)
# The budget holds the tick's high quantile, not its mean: each tick records how far it ran past its plan (the
# fixed costs so far, the decisions' estimates, the reserves), and the next ticks keep that quantile of the recent
# misses free. It absorbs what no estimate sees coming: bursts of arrivals answered between agents, a cost spike.
MARGIN_WINDOW = 180  # ticks of misses remembered (2 s at 90 Hz)
MARGIN_QUANTILE = 95.0
MARGIN_EVERY = 10  # ticks between updates of the margin


@dataclass(frozen=True)
class AgentSpec:
    """What an agent wears and where its frame sits: garments (in publishing order), initial shape, frame_id,
    origin (x, y, z of its frame in the scene's frame, for distances), extra_cost_ms (an artificial per-frame cost:
    tests and benchmarks of the budget), publish_body (also dress the body), skinned_fallback (a garment whose
    database is missing or unusable is dressed with its skinned template, reported through on_error)."""

    name: str
    garments: tuple = (GarmentSpec("tshirt"),)
    beta: tuple = tuple(float(b) for b in REFERENCE_SHAPE)
    frame_id: str = "agent"
    origin: tuple = (0.0, 0.0, 0.0)
    extra_cost_ms: float = 0.0
    publish_body: bool = False
    skinned_fallback: bool = False
    subdivision: int = 0  # rounds of Loop refinement of each garment for display (display.models), every tier
    layers: tuple = ()  # ((garment, layer), ...) overriding display.models.TEMPLATE_LAYERS


@dataclass(frozen=True)
class SceneConfig:
    lod: LodPolicy = LodPolicy()
    lod_enabled: bool = True  # False: every agent at the first tier, never culled
    budget_ms: float = 8.0  # <= 0: no budget
    protect_tiers: int = 1  # tiers below this index are never lowered or skipped by the budget
    max_wait: int = 9  # an agent skipped this many ticks in a row is dressed (cheapest level): >= 9 Hz at 90 Hz
    near_wait: int = 2  # a protected agent may be deferred this many ticks in a row when they alone overfill one
    fade_frames: int = 6
    cost_smoothing: float = 0.2  # weight of a new measurement in a level's cost estimate


class Agent:
    """One agent's state: its pose input, garments (per-agent state over shared data), level of detail, costs."""

    def __init__(self, spec: AgentSpec, garments: dict, pose, slot: int, clamped: bool):
        self.spec, self.name, self.garments, self.pose, self.slot = spec, spec.name, garments, pose, slot
        self.clamped = clamped
        self.tier: int | None = None  # distance tier (hysteresis state)
        self.level: int | None = None  # level dressed last
        self.tier_dressed: int | None = None  # distance tier when last dressed (a tier change is news)
        self.visible = True
        self.distance = 0.0
        self.done_version = -1
        self.dirty = True  # dress on the next tick even without a new pose
        self.waited = 0  # ticks in a row skipped by the budget
        self.cost_ms: dict[int, float] = {}
        self.frames = 0  # frames dressed
        self.last_dressed = 0.0  # time.monotonic() of the last one
        self.shape_generation = 0
        self.beta = tuple(float(b) for b in spec.beta)
        self.specs = {}  # garment -> the GarmentSpec it was made from (a skinned fallback's, not the agent's)
        self.errors: dict = {}  # garment -> what its last dress raised (its frame is then None)
        self.dress_ms = 0.0  # the last dress, all garments

    def centre(self) -> np.ndarray:
        root = self.pose.values[3 * NUM_BONES:]
        return np.array([root[0], root[1], root[2] + HIPS_HEIGHT]) + self.spec.origin

    def fading(self) -> bool:
        return any(g.fading for g in self.garments.values())

    def dress(self, level: int) -> dict:
        """{garment: (V, 3) float32 frame (an internal buffer, valid until the next dress) or None: posed as bones
        only, or its dress raised (the error in `errors`: the other garments are dressed all the same)}."""
        start = time.perf_counter()
        rotvecs, root = self.pose.rotvecs, self.pose.root_translation
        out = {}
        if self.errors:  # the last frame's failures (a new dict only then: none per frame on the hot path)
            self.errors = {}
        for name, garment in self.garments.items():
            try:
                out[name] = garment.dress(level, rotvecs, root)
            except Exception as error:  # one garment's failure leaves the others (and the next frames) alone
                out[name], self.errors[name] = None, error
        self.dress_ms = 1e3 * (time.perf_counter() - start)
        if self.spec.extra_cost_ms > 0:  # an artificially expensive agent: spin for the injected cost
            end = time.perf_counter() + self.spec.extra_cost_ms * 1e-3
            while time.perf_counter() < end:
                pass
        return out

    def memory_bytes(self, shared=()) -> int:
        """Bytes of the numpy arrays reachable from this agent's garments that are not reachable from `shared`
        (the library's models): the agent's own state."""
        exclude = {id(a) for a in _arrays(shared)}
        return sum(a.nbytes for a in _arrays(self.garments.values()) if id(a) not in exclude)


def _arrays(roots, depth: int = 4) -> list:
    """Distinct numpy arrays owning their memory, reachable from `roots` through attributes, dicts and sequences."""
    seen, found = set(), []

    def walk(obj, level):
        if isinstance(obj, np.ndarray):
            base = obj if obj.base is None else obj.base
            if isinstance(base, np.ndarray) and id(base) not in seen:
                seen.add(id(base))
                found.append(base)
            return
        if level > depth or id(obj) in seen or isinstance(obj, (str, bytes, int, float)):
            return
        seen.add(id(obj))
        if isinstance(obj, dict):
            items = obj.values()
        elif isinstance(obj, (list, tuple)):
            items = obj
        elif hasattr(obj, "__dict__"):
            items = vars(obj).values()
        else:
            return
        for item in items:
            walk(item, level + 1)

    for root in roots:
        walk(root, 0)
    return found


@dataclass
class TickReport:
    dressed: list = field(default_factory=list)  # agent names dressed this tick
    skipped: list = field(default_factory=list)  # skipped by the budget
    culled: int = 0
    idle: int = 0
    ms: float = 0.0
    estimate_ms: float = 0.0


def percentiles(values, digits: int = 4) -> dict:
    """p50, p99, max and count of a sequence of timings (None when empty), rounded for JSON."""
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    array = np.fromiter(values, dtype=np.float64)
    p50, p99 = np.percentile(array, [50, 99])
    return {"p50": round(float(p50), digits), "p99": round(float(p99), digits),
            "max": round(float(array.max()), digits), "n": int(array.size)}


class TierStats:
    """Per tier: agents now, dressed frames, frames degraded by the budget, ms per tick (rolling)."""

    def __init__(self, names, window: int = 1000):
        self.names = list(names)
        self.agents = Counter()
        self.culled = Counter()
        self.frames = Counter()
        self.degraded = Counter()
        self.ms = {n: deque(maxlen=window) for n in self.names}

    def as_dict(self) -> dict:
        return {n: {"agents": self.agents[n], "culled": self.culled[n], "frames": self.frames[n],
                    "degraded_frames": self.degraded[n], "ms": percentiles(self.ms[n])} for n in self.names}


class Scene:
    """Agents dressed on the caller's thread; agents built and shapes refitted on one worker thread."""

    def __init__(self, body, config: SceneConfig = SceneConfig(), library: GarmentLibrary | None = None,
                 pose_factory=PoseInput, on_error=None, prepare=None, clock=time.perf_counter):
        self.body, self.config = body, config
        self.clock = clock  # seconds, for the budget and the measured costs (a test may stop it)
        self.library = library if library is not None else GarmentLibrary(body)
        self.pose_factory = pose_factory
        self.before_dress = None  # called with an agent just before it is dressed (e.g. to parse waiting input)
        self.between_agents = None  # called between the agents a tick dresses, at most every INTERLEAVE_MS (e.g. to
        # answer a pose of the nearest agent that arrived meanwhile)
        self.agents: dict[str, Agent] = {}
        self.viewer: Viewer | None = None
        self.ticks = 0
        self.refits = 0  # shape refits done by the worker (a repeated shape is not one)
        self.after_ms = 0.0  # smoothed caller's work after each tick (note_after_ms), reserved from the budget
        self.between_ms = 0.0  # smoothed work of the between_agents hook per tick (arrivals answered), reserved too
        self.margin_ms = 0.0  # MARGIN_QUANTILE of the recent ticks' misses (time past their plan), reserved too
        self._misses: deque = deque(maxlen=MARGIN_WINDOW)
        self.level_cost: dict[int, float] = {}
        self.stats = TierStats([t.name for t in config.lod.tiers])
        self.on_error = on_error or (lambda message: None)
        self._failures: list = []  # (agent name, the AgentSpec whose build failed, message), for take_failures
        self.prepare = prepare  # prepare(agent) on the worker thread after a build (e.g. topology messages)
        self._slots = 0
        self._ready: list[Agent] = []
        self._jobs: dict = {}  # name -> ("add", spec) | ("shape", beta), newest wins
        self._cond = threading.Condition()
        self._stop = False
        self._busy = False
        self._thread = threading.Thread(target=self._work, name="agentdress-scene-worker", daemon=True)
        self._thread.start()

    # ---- agents (building off the frame path) -----------------------------------------------------------------
    def build_agent(self, spec: AgentSpec) -> Agent:
        """Build an agent now (loads shared garment data on first use). Raises what the garment makers raise."""
        tiers = self.config.lod.tiers
        covering = tuple(g.name for g in spec.garments)
        specs = list(spec.garments) + ([GarmentSpec("body", covered_by=covering)] if spec.publish_body else [])
        garments, used, clamped = {}, {}, False
        for g in specs:
            if g.covered_by:  # the body, masked by the garments it wears as the single agent's is
                shared, used[g.name] = self.library.covered_body(tuple(used[n] for n in g.covered_by)), g
            else:
                shared, used[g.name] = self._shared(g, spec.skinned_fallback)
            garment = garments[g.name] = AgentGarment(shared, tiers, 0 if g.name == "body" else self.config.fade_frames)
            clamped |= self.library.fitted(used[g.name], spec.beta, garment)
        garments = {name: garments[name] for name in self._dress_for_display(spec, garments, spec.beta)}
        agent = Agent(spec, garments, self.pose_factory(), 0, clamped)
        agent.specs = used
        agent.beta = tuple(float(b) for b in spec.beta)
        with self._cond:
            agent.slot, self._slots = self._slots, self._slots + 1
        return agent

    def _dress_for_display(self, spec: AgentSpec, garments: dict, beta) -> list:
        """Give each garment of `garments` {name: AgentGarment} the single agent's display stages
        (display.models.dress_for_display: layering, refinement, the edges kept off the drawn body), their bindings
        made between models fitted to `beta`, each display model dressing its garment's level. Returns the names
        in drawing order: inner layers first, the body last."""
        from ..display.models import DisplayModel, dress_for_display

        if not any(tier.display == "full" for tier in self.config.lod.tiers):
            return list(garments)
        fitted = {name: garment.fitted_model() if name != "body" else garment.base
                  for name, garment in garments.items()}
        display = dress_for_display(fitted, self.body, dict(spec.layers), spec.subdivision, beta)
        for name, model in display.items():
            if name == "body":
                continue
            if isinstance(model, DisplayModel):
                model.base = garments[name]
                garments[name].set_display(model)
            else:
                garments[name].set_display(None)
        return list(display)

    def _shared(self, spec: GarmentSpec, fallback: bool):
        """(the library's model of `spec`, the spec it was made from): the skinned template's when the database
        cannot be used and `fallback` is set."""
        from ..models.garment_models import GarmentDatabaseError

        try:
            return self.library.get(spec), spec
        except GarmentDatabaseError as error:
            if not fallback:
                raise
            self.on_error(f"{error}; using the skinned {spec.name} template instead (skinned_fallback)")
            spec = GarmentSpec(spec.name, spec.vertices)
            return self.library.get(spec), spec

    def request_agent(self, spec: AgentSpec):
        """Add (or rebuild) an agent off the frame path; a tick installs it when built."""
        self._submit(spec.name, ("add", spec))

    def request_shape(self, name: str, beta):
        """Refit agent `name` to beta (6,) off the frame path (newest request wins)."""
        self._submit(name, ("shape", tuple(float(b) for b in beta)))

    def remove_agent(self, name: str) -> bool:
        with self._cond:
            self._jobs.pop(name, None)
            self._ready = [a for a in self._ready if a.name != name]
        return self.agents.pop(name, None) is not None

    def install(self, agent: Agent):
        old = self.agents.get(agent.name)
        if old is not None:  # a rebuilt agent keeps its pose input
            agent.pose = old.pose
        self.agents[agent.name] = agent

    def idle(self) -> bool:
        """The worker has nothing left to do (built agents may still wait for the next tick to install them)."""
        with self._cond:
            return not self._jobs and not self._busy

    def _submit(self, name, job):
        with self._cond:
            if job[0] == "shape" and self._jobs.get(name, ("",))[0] == "add":
                spec = self._jobs[name][1]
                job = ("add", AgentSpec(**{**spec.__dict__, "beta": job[1]}))
            self._jobs[name] = job
            self._cond.notify()

    def _work(self):
        while True:
            with self._cond:
                while not self._stop and not self._jobs:
                    self._cond.wait()
                if self._stop:
                    return
                name = next(iter(self._jobs))
                kind, arg = self._jobs.pop(name)
                self._busy = True
            try:
                if kind == "add":
                    agent = self.build_agent(arg)
                    if self.prepare is not None:
                        self.prepare(agent)
                    with self._cond:
                        self._ready.append(agent)
                else:
                    agent = self.agents.get(name)
                    if agent is not None and agent.beta != arg:  # a repeated shape costs nothing
                        agent.clamped = any([self.library.fitted(agent.specs[n], arg, g)
                                             for n, g in agent.garments.items()])
                        self._dress_for_display(agent.spec, agent.garments, arg)  # bindings of the new shape
                        agent.beta = arg
                        agent.shape_generation += 1
                        agent.dirty = True
                        self.refits += 1
            except Exception as error:  # a bad request never stops the scene: report, keep what runs
                message = f"agent {name!r}: cannot {'build' if kind == 'add' else 'refit'}: {error}"
                with self._cond:
                    self._failures.append((name, arg if kind == "add" else None, message))
                self.on_error(message)
            finally:
                with self._cond:
                    self._busy = False

    def take_failures(self) -> list:
        """[(agent name, AgentSpec of the failed build or None for a refit, message)] since the last call."""
        with self._cond:
            failures, self._failures = self._failures, []
        return failures

    def stop(self):
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=5.0)

    # ---- viewer ---------------------------------------------------------------------------------------------
    def set_viewer(self, viewer: Viewer | None):
        self.viewer = viewer

    # ---- the tick -------------------------------------------------------------------------------------------
    def estimate(self, agent: Agent, level: int) -> float:
        """ms that dressing (and publishing) `agent` at `level` is expected to take: its own measured cost, else
        the level's across agents, plus the old level's while a cross-fade runs both."""
        cost = agent.cost_ms.get(level)
        if cost is None:
            cost = self.level_cost.get(level, DEFAULT_COST_MS)
        if agent.fading() and agent.level is not None and agent.level != level:
            cost += agent.cost_ms.get(agent.level, 0.0)
        return cost

    def _record(self, agent: Agent, level: int, ms: float):
        a = self.config.cost_smoothing
        old = agent.cost_ms.get(level)
        agent.cost_ms[level] = ms if old is None else (1 - a) * old + a * ms
        old = self.level_cost.get(level)
        self.level_cost[level] = ms if old is None else (1 - a) * old + a * ms

    def tick(self, publish=None, now_ns: int = 0, started: float | None = None) -> TickReport:
        """One frame: decide, dress, publish. `publish(agent, frames, stamp_ns)` is timed as part of each agent.

        The budget holds the whole tick: the agents get what is left of `budget_ms` after the time since
        `started` (the caller's perf_counter() when its tick began: taking input) and the caller's expected work
        after this call (`note_after_ms`)."""
        start, tick_began = self.clock(), time.monotonic()
        started = start if started is None else started
        with self._cond:
            ready, self._ready = self._ready, []
        for agent in ready:
            self.install(agent)
        config, lod, tiers = self.config, self.config.lod, self.config.lod.tiers
        report = TickReport()
        self.stats.agents.clear()
        self.stats.culled.clear()
        candidates, by_key = [], {}
        viewer = self.viewer if config.lod_enabled else None
        agents = list(self.agents.values())
        if viewer is not None and agents:  # every agent's distance, tier and visibility in a few array operations
            centres = np.array([agent.centre() for agent in agents])
            d = centres - viewer.position
            distances = np.sqrt(np.einsum("ij,ij->i", d, d))
            new_tiers = lod.tiers_of(distances, np.array([-1 if a.tier is None else a.tier for a in agents]))
            seen = lod.visible_of(viewer, centres)
        for i, agent in enumerate(agents):
            if viewer is not None:
                agent.distance, agent.tier, visible = float(distances[i]), int(new_tiers[i]), bool(seen[i])
            else:
                agent.distance, agent.tier, visible = 0.0, 0, True
            tier_name = tiers[agent.tier].name
            self.stats.agents[tier_name] += 1
            if not visible:
                if agent.visible:
                    agent.visible = False
                self.stats.culled[tier_name] += 1
                report.culled += 1
                continue
            if not agent.visible:  # back in view: dressed on this frame
                agent.visible, agent.dirty = True, True
                for garment in agent.garments.values():
                    garment.reset()
            changed = (agent.pose.version != agent.done_version or agent.dirty or agent.fading()
                       or agent.tier != agent.tier_dressed)
            if not changed or not self._due(agent):
                report.idle += 1
                continue
            costs = [self.estimate(agent, level) for level in range(len(tiers))]
            candidate = Candidate(agent.name, agent.distance, agent.tier, costs, agent.waited)
            candidates.append(candidate)
            by_key[agent.name] = agent
        planned = 1e3 * (self.clock() - started) + self.between_ms  # so far, and the hook's reserve
        decisions = schedule(candidates, self._dressing_budget(started), config.protect_tiers, config.max_wait,
                             config.near_wait)
        decisions.sort(key=lambda d: by_key[d.key].distance)
        tier_ms = Counter()
        between = self.clock()
        hook_ms = 0.0
        for decision in decisions:
            if self.between_agents is not None and self.clock() - between >= INTERLEAVE_MS * 1e-3:
                t0 = self.clock()
                self.between_agents()
                between = self.clock()
                hook_ms += 1e3 * (between - t0)
            agent = by_key[decision.key]
            if agent.last_dressed >= tick_began:  # answered through between_agents during this tick: nothing left
                continue
            tier_name = tiers[decision.tier].name
            if decision.degraded:
                self.stats.degraded[tier_name] += 1
            if decision.level is None:
                agent.waited += 1
                report.skipped.append(agent.name)
                continue
            report.estimate_ms += decision.estimate
            tier_ms[tier_name] += self._dress(agent, decision.level, decision.tier, publish, now_ns)
            report.dressed.append(agent.name)
        for name in self.stats.names:
            if tier_ms[name] or self.stats.agents[name]:
                self.stats.ms[name].append(round(tier_ms[name], 4))
        a = self.config.cost_smoothing
        self.between_ms = (1 - a) * self.between_ms + a * hook_ms
        self.ticks += 1
        end = self.clock()
        report.ms = 1e3 * (end - start)
        if decisions:
            self._note_miss(1e3 * (end - started) - planned - report.estimate_ms)
        return report

    def _note_miss(self, ms: float):
        """A dressing tick ran `ms` past its plan (negative: under it); every MARGIN_EVERY ticks the margin becomes
        the MARGIN_QUANTILE of the recent misses, at most half the budget."""
        self._misses.append(ms)
        if self.ticks % MARGIN_EVERY == 0 and len(self._misses) >= MARGIN_EVERY:
            quantile = float(np.percentile(np.fromiter(self._misses, dtype=np.float64), MARGIN_QUANTILE))
            self.margin_ms = min(max(0.0, quantile), 0.5 * max(self.config.budget_ms, 0.0))

    def _dressing_budget(self, started: float) -> float:
        """ms left for dressing this tick: budget_ms less the tick's fixed costs (spent so far, expected after), the
        arrivals the between_agents hook is expected to answer and the margin of recent misses; never 0 (which the
        scheduler reads as no budget) while a budget is set."""
        budget = self.config.budget_ms
        if budget <= 0:
            return budget
        spent = 1e3 * (self.clock() - started)
        return max(MIN_DRESSING_MS, budget - spent - self.after_ms - self.between_ms - self.margin_ms)

    def note_after_ms(self, ms: float):
        """The caller's work after `tick` returned (publishing bookkeeping, subscriptions): smoothed into what the
        next ticks reserve."""
        a = self.config.cost_smoothing
        self.after_ms = (1 - a) * self.after_ms + a * max(0.0, ms)

    def _dress(self, agent: Agent, level: int, tier: int, publish, now_ns: int) -> float:
        """Dress and publish one agent at `level`; returns the ms it took (recorded as that level's cost)."""
        t0 = self.clock()
        if self.before_dress is not None:
            self.before_dress(agent)
        version = agent.pose.version
        frames = agent.dress(level)
        if publish is not None:
            publish(agent, frames, agent.pose.stamp_ns or now_ns)
        ms = 1e3 * (self.clock() - t0)
        self._record(agent, level, ms)
        self.stats.frames[self.config.lod.tiers[tier].name] += 1
        agent.level, agent.done_version, agent.dirty, agent.waited = level, version, False, 0
        agent.tier_dressed = tier
        agent.frames += 1
        agent.last_dressed = time.monotonic()
        return ms

    def _due(self, agent: Agent) -> bool:
        """The tick `self.ticks` is one of the agent's at its tier's rate (`every`, staggered by slot), or the
        budget made it wait."""
        every = self.config.lod.tiers[agent.tier].every
        return every <= 1 or agent.waited > 0 or (self.ticks + agent.slot) % every == 0

    def needs_input(self, agent: Agent) -> bool:
        """Whether the next tick may dress `agent`, as far as the last one knows: in view and due at its tier's
        rate (an agent never placed yet, or any agent without levels of detail, always is)."""
        if agent.tier is None or self.viewer is None or not self.config.lod_enabled:
            return True
        return agent.visible and self._due(agent)

    def dress_now(self, name: str, publish=None, now_ns: int = 0) -> bool:
        """Dress agent `name` right away at its tier's level if it is in view (a pose that just arrived at one of
        the agents nearest the viewer, answered without waiting for the tick). Returns whether it was dressed."""
        agent = self.agents.get(name)
        if agent is None or agent.tier is None or not agent.visible:
            return False
        if agent.pose.version == agent.done_version and not agent.dirty:
            return False
        self._dress(agent, agent.tier, agent.tier, publish, now_ns)
        return True

    def status(self) -> dict:
        return {"agents": len(self.agents), "tiers": self.stats.as_dict(),
                "budget_ms": self.config.budget_ms, "margin_ms": round(self.margin_ms, 3),
                "lod": self.config.lod_enabled,
                "viewer": None if self.viewer is None else [round(float(v), 3) for v in self.viewer.position],
                "shared_garments": len(self.library), "refits": self.refits}
