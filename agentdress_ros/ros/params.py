"""The node's parameters: defaults, descriptions, each with its own check (pure functions, no rclpy: tested directly).

`validate(name, value)` returns the coerced value or raises ParameterError with the reason the parameter callback
hands back to `ros2 param set`; the check is the parameter's Spec's. Parameters marked `runtime=False` are read at
startup only (changing them is rejected with "restart the node"): topics and QoS, since re-creating subscriptions
mid-stream would drop data.

Per-garment settings are string lists of "garment:value" entries, so a garment list change never has to keep two
parallel arrays in step:
    garment_vertices:  ["tshirt:3000", "trousers:8000"]   vertex budget (level of detail) of a skinned template
    garment_databases: ["tshirt:data/tshirt_default.h5"]  AgentDress database of a garment (else skinned)
and the engine's speed/accuracy knobs (agentdress_ros.engine.config.ENGINE_KNOBS) as "field=value" entries, for every
garment with a database or, prefixed with its name, for one:
    engine: ["pose_model=examples", "neighbors=3", "penetration=false", "tshirt:pose_model=regressor"]
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..body import PHENOTYPE_NAMES
from ..engine.config import EngineKnobs
from ..scene.garments import GarmentSpec
from ..scene.lod import DEFAULT_TIER_TEXT, parse_tiers

__all__ = ["PARAMETERS", "GarmentEngines", "ParameterError", "Spec", "garment_specs", "parse_garment_map", "validate"]

QOS_RELIABILITY = ("best_effort", "reliable")
_GARMENT_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")  # becomes a topic token: ~/<garment>/points
#: The models a garment with a database can run (garment_models): AgentDress synthesis first (the default).
GARMENT_MODELS = ("agentdress", "santesteban")


class ParameterError(ValueError):
    """A rejected parameter value; the message is the reason."""


# ---- checks: each takes (name, value) and returns the coerced value or raises ParameterError --------------------
def number(low: float, high: float, low_open: bool = False) -> Callable:
    def check(name, value) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(f"{name} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value) or value < low or value > high or (low_open and value == low):
            raise ParameterError(f"{name} must be in {'(' if low_open else '['}{low:g}, {high:g}], got {value:g}")
        return value
    return check


def integer(low: int, high: int) -> Callable:
    def check(name, value) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ParameterError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
        return value
    return check


def one_of(*choices) -> Callable:
    def check(name, value):
        if isinstance(value, bool) or value not in choices:
            raise ParameterError(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value
    return check


def subdivision_rounds(name, value) -> int:
    if isinstance(value, bool) or value not in (0, 1, 2):
        raise ParameterError(f"{name} must be 0, 1 or 2, got {value!r}")
    return int(value)


def boolean(name, value) -> bool:
    if not isinstance(value, bool):
        raise ParameterError(f"{name} must be true or false, got {value!r}")
    return value


def text(name, value) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ParameterError(f"{name} must be a non-empty string, got {value!r}")
    return value.strip()


def text_or_empty(name, value) -> str:
    if not isinstance(value, str):
        raise ParameterError(f"{name} must be a string, got {value!r}")
    return value.strip()


def _string_list(name, value) -> list[str]:
    if value is None:  # an empty YAML list arrives as "not set"
        return []
    if isinstance(value, str) or not all(isinstance(v, str) for v in value):
        raise ParameterError(f"{name} must be a list of strings, got {value!r}")
    return [v for v in value if v != ""]


def names(what: str, rule: str, reserved=()) -> Callable:
    """A list of distinct names that become topic tokens (`what`: garment, agent)."""
    def check(name, value) -> list[str]:
        items = _string_list(name, value)
        for item in items:
            if not _GARMENT_NAME.match(item) or item in reserved:
                raise ParameterError(f"{name}: {item!r} is not a valid {what} name ({rule})")
        if len(set(items)) != len(items):
            raise ParameterError(f"{name}: names repeat in {items}")
        return items
    return check


def parse_garment_map(name: str, value) -> dict[str, str]:
    """["tshirt:3000", ...] -> {"tshirt": "3000"}; ParameterError for entries without a colon or repeated keys."""
    result = {}
    for entry in _string_list(name, value):
        key, sep, item = entry.partition(":")
        key, item = key.strip(), item.strip()
        if not sep or not key or not item:
            raise ParameterError(f"{name}: entry {entry!r} must look like 'garment:value'")
        if key in result:
            raise ParameterError(f"{name}: garment {key!r} appears twice")
        result[key] = item
    return result


def garment_map(read=None) -> Callable:
    """A "garment:value" list -> {garment: read(garment, value)} (`read` raises ParameterError; None: the text)."""
    def check(name, value) -> dict:
        entries = parse_garment_map(name, value)
        return entries if read is None else {key: read(name, key, item) for key, item in entries.items()}
    return check


def _vertex_budget(name, garment, item) -> int:
    try:
        count = int(item)
    except ValueError:
        raise ParameterError(f"{name}: {garment}: {item!r} is not an integer") from None
    if not 100 <= count <= 200_000:
        raise ParameterError(f"{name}: {garment}: {count} must be in [100, 200000]")
    return count


def _layer(name, garment, item) -> int:
    try:
        return int(item)
    except ValueError:
        raise ParameterError(f"{name}: {garment}: {item!r} is not an integer") from None


def _garment_model(name, garment, item) -> str:
    if item not in GARMENT_MODELS:
        raise ParameterError(f"{name}: {garment}: {item!r} must be one of {', '.join(GARMENT_MODELS)}")
    return item


def shape(name, value) -> list[float]:
    if value is None or isinstance(value, (str, bool)) or not hasattr(value, "__len__"):
        raise ParameterError(f"{name} must be a list of {len(PHENOTYPE_NAMES)} numbers, got {value!r}")
    values = list(value)
    if len(values) != len(PHENOTYPE_NAMES):
        raise ParameterError(f"{name} needs {len(PHENOTYPE_NAMES)} values ({', '.join(PHENOTYPE_NAMES)}), "
                             f"got {len(values)}")
    bad = [n for n, v in zip(PHENOTYPE_NAMES, values) if isinstance(v, bool) or not isinstance(v, (int, float))
           or not math.isfinite(v)]
    if bad:
        raise ParameterError(f"{name} has non-finite or non-numeric values for {', '.join(bad)}")
    return [float(v) for v in values]


def viewer_offset(name, value) -> list[float]:
    if value is None or isinstance(value, (str, bool)) or len(value) != 4:
        raise ParameterError(f"{name} must be four numbers x, y, z, yaw, got {value!r}")
    return [number(-1e6, 1e6)(name, v) for v in value]


def tier_lines(name, value) -> list[str]:
    lines = _string_list(name, value)
    try:
        parse_tiers(lines)
    except ValueError as error:
        raise ParameterError(f"{name}: {error}") from None
    return lines


@dataclass(frozen=True)
class GarmentEngines:
    """The `engine` parameter: knobs for every garment with a database (`common`), and a garment's own on top of
    them (`garments`: ((garment, EngineKnobs), ...) sorted)."""

    common: EngineKnobs = EngineKnobs()
    garments: tuple = ()

    def for_garment(self, garment: str) -> EngineKnobs:
        """One garment's knobs: the common ones, replaced by that garment's "garment:field" entries."""
        return dict(self.garments).get(garment, EngineKnobs()).over(self.common)

    @classmethod
    def parse(cls, name: str, value) -> "GarmentEngines":
        """["neighbors=3", "tshirt:pose_model=regressor", ...] -> GarmentEngines, checked by building an
        EngineConfig for every garment named; ParameterError with the reason."""
        words: dict[str, list] = {}
        for entry in _string_list(name, value):
            field, sep, item = (part.strip() for part in entry.partition("="))
            garment, colon, key = (part.strip() for part in field.rpartition(":"))
            if not sep or not key or not item or (colon and not _GARMENT_NAME.match(garment)):
                raise ParameterError(f"{name}: entry {entry!r} must look like 'field=value' or 'garment:field=value'")
            words.setdefault(garment, []).append(f"{key}={item}")
        knobs = {}
        for garment, entries in words.items():
            try:
                knobs[garment] = EngineKnobs.parse(entries, prefix=f"{garment}:" if garment else "")
            except ValueError as error:
                raise ParameterError(f"{name}: {error}") from None
        engines = cls(knobs.pop("", EngineKnobs()), tuple(sorted(knobs.items())))
        for garment in [""] + [g for g, _ in engines.garments]:
            try:
                engines.for_garment(garment).config()
            except (TypeError, ValueError) as error:
                raise ParameterError(f"{name}{f' ({garment})' if garment else ''}: {error}") from None
        return engines


@dataclass(frozen=True)
class Spec:
    """One parameter: its default, description (both in the README's table), whether it may change while the node
    runs, and its check ((name, value) -> coerced value, or ParameterError with the reason)."""

    default: object
    description: str
    runtime: bool = True
    check: Callable = None

    def validate(self, name: str, value):
        return self.check(name, value)


PARAMETERS: dict[str, Spec] = {
    "rate_hz": Spec(90.0, "garment output rate (timer frequency), Hz, in (0, 1000]",
        check=number(0.0, 1000.0, low_open=True)),
    "keepalive_hz": Spec(1.0, "re-publish the last clouds at this rate when no new pose arrived and nothing "
                              "changed (late subscribers get a frame within 1 s at no synthesis cost); 0 = off",
                                  check=number(0.0, 100.0)),
    "marker_rate_hz": Spec(0.0, "visualization_msgs/Marker TRIANGLE_LIST rate for RViz, Hz, in [0, 10]; 0 = off",
        check=number(0.0, 10.0)),
    "status_rate_hz": Spec(1.0, "rate of the JSON status on ~/status, Hz, in (0, 50]",
        check=number(0.0, 50.0, low_open=True)),
    "inside_check_hz": Spec(0.0, "rate at which the last published garments are tested against the posed body (the "
                                 "winding-number test of the build and the evaluation, on a background thread; "
                                 "~/status 'inside'), Hz, in [0, 2]; 0 = off (the default: each check delays the "
                                 "ticks around it); a crowd checks the agent nearest the viewer in view",
        check=number(0.0, 2.0)),
    "publish_body": Spec(False, "also publish the posed body surface on ~/body/points and ~/body/mesh, and its "
                                "skin and bones (~/body/skin, ~/body/bones)", check=boolean),
    "answer_on_arrival": Spec(True, "dress a new pose as soon as it arrives (unless within half a period of the last "
                                    "answer: the timer takes those), so latency is not tied to the timer's phase",
                                        check=boolean),
    "frame_id": Spec("agent", "frame_id stamped on every published message", check=text),
    "joint_state_topic": Spec("joint_states", "sensor_msgs/JointState input topic (a crowd agent's: <agent>/<topic>)",
                              runtime=False, check=text),
    "shape_topic": Spec("body_shape", "std_msgs/Float32MultiArray body-shape input topic (a crowd agent's: "
                                    "<agent>/<topic>)", runtime=False, check=text),
    "garments": Spec(["tshirt"], "garments to dress the agent in (templates tshirt, longsleeve, trousers)",
        check=names("garment", "letters, digits, _; not 'body'", reserved=("body",))),
    "garment_vertices": Spec([], "per-garment vertex budget 'name:count' of skinned templates (level of detail)",
        check=garment_map(_vertex_budget)),
    "garment_databases": Spec([], "per-garment AgentDress database 'name:path.h5' (relative to the working dir)",
        check=garment_map()),
    "garment_models": Spec([], "per-garment model of a garment with a database, 'name:model': agentdress (synthesis, "
                               "the default) or santesteban (Santesteban et al. 2019, from the database's "
                               "garment_model/santesteban group, at every tier of a crowd; README 'Santesteban "
                               "et al.'s system')", check=garment_map(_garment_model)),
    "engine": Spec(["pose_model=examples", "projection=8", "tshirt:pose_model=regressor", "tshirt:fold=false",
                    "trousers:pose_model=regressor", "trousers:fold=false", "longsleeve:pose_model=regressor",
                    "longsleeve:fold=false"],
                   "EngineConfig knobs of the garments with a database, 'field=value', or 'garment:field=value' "
                   "for one garment: pose_model (lbs, examples, regressor, recurrent, kdsm), fold, neighbors, "
                   "components, anchors, shape_model, penetration, projection, decay, damping, dtype (float32, "
                   "float64), taylor (augmented, plain, zeroth); see README 'Speed vs accuracy'",
                       check=GarmentEngines.parse),
    "display_subdivision": Spec(1, "rounds of Loop subdivision (0, 1, 2) of each garment for display, published as "
                                   "its cloud and mesh (a fixed sparse matrix after penetration handling; README "
                                   "'Display')", runtime=False, check=subdivision_rounds),
    "garment_layers": Spec([], "per-garment layer 'name:layer' (templates: trousers 1, tshirt and longsleeve 2); a "
                               "garment is pushed out of the next lower layer's; tucked in: ['trousers:3']",
                           runtime=False, check=garment_map(_layer)),
    "skinned_fallback": Spec(False, "if a garment's database is missing or unusable, dress it with the skinned "
                                    "template (warned) instead of exiting with an error", check=boolean),
    "shape": Spec([0.5, 2.0 / 3.0, 0.5, 0.5, 0.5, 0.5], "initial body shape (gender, age, muscle, weight, height, "
                                                  "proportions), each in [0, 1]; setting it changes the shape",
                                                      check=shape),
    "stamp_jump_threshold_s": Spec(0.5, "a JointState stamp this far (s) before or after the last accepted one "
                                        "starts a new timeline (looped bag, clock reset): accepted, warned and "
                                        "counted; closer older stamps are rejected as out of order; in (0, 86400]",
                                            check=number(0.0, 86400.0, low_open=True)),
    "warn_throttle_s": Spec(5.0, "at most one warning per kind per this many seconds, in (0, 3600]",
        check=number(0.0, 3600.0, low_open=True)),
    "qos.joint_states.reliability": Spec("best_effort", "JointState subscription reliability", runtime=False,
        check=one_of(*QOS_RELIABILITY)),
    "qos.joint_states.depth": Spec(1, "JointState subscription depth (keep last)", runtime=False,
        check=integer(1, 1000)),
    "qos.shape.reliability": Spec("reliable", "body shape subscription reliability", runtime=False,
        check=one_of(*QOS_RELIABILITY)),
    "qos.shape.depth": Spec(1, "body shape subscription depth (keep last)", runtime=False, check=integer(1, 1000)),
    "qos.points.reliability": Spec("best_effort", "PointCloud2 publisher reliability", runtime=False,
        check=one_of(*QOS_RELIABILITY)),
    "qos.points.depth": Spec(1, "PointCloud2 publisher depth (keep last)", runtime=False, check=integer(1, 1000)),
    # Crowd mode (agentdress_ros.ros.crowd): one node dresses every agent listed.
    "agents": Spec([], "agent names: each has <agent>/joint_states, <agent>/body_shape in and ~/<agent>/<garment>/"
                       "points, mesh out, taking the parameters above overridden by agent.<agent>.<parameter> (YAML); "
                       "agents may be added and removed at run time; empty = one agent (a crowd of one) on the node's own topics",
                           check=names("agent", "a letter, then letters, digits, _")),
    "viewer_topic": Spec("viewer_pose", "geometry_msgs/PoseStamped input of the viewer (headset), crowd mode; "
                                        "empty = no viewer (every agent near, none culled)", runtime=False,
                                            check=text_or_empty),
    "viewer_offset": Spec([0.0, 0.0, 0.0, 0.0], "fixed offset x, y, z (m), yaw (rad) taking viewer poses into the "
                                                "agents' frame (there is no tf2 wheel)", check=viewer_offset),
    "budget_ms": Spec(8.0, "frame budget of the crowd tick, ms: far agents are lowered or updated on alternate ticks "
                           "to hold it, near ones never; 0 = no budget", check=number(0.0, 1000.0)),
    "realtime_priority": Spec(0, "SCHED_FIFO priority (1-99) of the node's executor thread, so that its own DDS "
                                 "threads cannot preempt a tick (README 'A crowd in one node'); needs CAP_SYS_NICE or "
                                 "an rtprio limit, else a warning; 0 = the normal scheduler", runtime=False,
                                     check=integer(0, 99)),
    "lod.enabled": Spec(True, "levels of detail and culling by the viewer's pose (false: every agent fully dressed)",
        check=boolean),
    "lod.tiers": Spec(list(DEFAULT_TIER_TEXT), "tiers by distance, '<name> <max m|inf> <synthesis|skinned> "
                                               "[neighbors=n] [penetration=false] [pose_model=examples] [every=n] "
                                               "[display=full|none] "
                                               "...'", runtime=False, check=tier_lines),
    "lod.hysteresis": Spec(0.5, "metres an agent must pass a tier boundary by before it changes tier",
        check=number(0.0, 100.0)),
    "lod.fade_frames": Spec(6, "frames over which a tier change cross-fades (0: switch at once)", runtime=False,
        check=integer(0, 100)),
    "lod.fov_deg": Spec(110.0, "the viewer's field of view, degrees (agents outside it, plus the margin, are culled)",
        check=number(0.0, 360.0)),
    "lod.margin_deg": Spec(10.0, "margin added to each side of the field of view, degrees", check=number(0.0, 360.0)),
    "lod.cull": Spec(True, "cull agents outside the field of view", check=boolean),
}


def validate(name: str, value):
    """Coerce and check one parameter value; raises ParameterError with the reason."""
    spec = PARAMETERS.get(name)
    if spec is None:
        raise ParameterError(f"unknown parameter {name!r}")
    return spec.validate(name, value)


def default_engine(garment: str) -> dict:
    """The node's default engine knobs for one garment (EngineConfig fields), from the `engine` parameter's default."""
    return GarmentEngines.parse("engine", PARAMETERS["engine"].default).for_garment(garment).as_dict()


def garment_specs(config: dict) -> tuple[GarmentSpec, ...]:
    """The garments of checked parameter values (the node's, or an agent's with its overrides), in publishing
    order: each one's vertex budget, database, and for a garment with a database its engine knobs and model."""
    specs = []
    for g in config["garments"]:
        database = config["garment_databases"].get(g)
        specs.append(GarmentSpec(g, config["garment_vertices"].get(g), database,
                                 config["engine"].for_garment(g) if database else EngineKnobs(),
                                 config.get("garment_models", {}).get(g, GARMENT_MODELS[0])))
    return tuple(specs)


def check_garment_config(garments, databases: dict, known_garments, models: dict | None = None) -> None:
    """Cross-parameter check: every garment is a known template or has a database, and a garment whose model is not
    the default has a database. Entries of the per-garment maps for garments not listed are kept (they apply once
    the garment is listed). Missing database files are not checked here (startup names the file and exits; see
    make_garment_model)."""
    for g in garments:
        if g not in known_garments and g not in databases:
            raise ParameterError(f"garments: {g!r} is neither a template ({', '.join(known_garments)}) nor has a "
                                 "database in garment_databases")
        model = (models or {}).get(g, GARMENT_MODELS[0])
        if model != GARMENT_MODELS[0] and g not in databases:
            raise ParameterError(f"garment_models: {g!r} runs {model!r}, which needs a database in garment_databases")


def database_file_problem(path: str) -> str:
    """'' when `path` is a readable file, else the reason naming the file (for the runtime parameter callback)."""
    resolved = Path(path).expanduser().resolve()
    return "" if resolved.is_file() else f"database file {resolved} does not exist"
