"""The node's parameters: defaults, descriptions, validation (pure functions, no rclpy: tested directly).

`validate(name, value, current)` returns the coerced value or raises ParameterError with the reason the parameter
callback hands back to `ros2 param set`. Parameters marked `runtime=False` are read at startup only (changing them
is rejected with "restart the node"): topics and QoS, since re-creating subscriptions mid-stream would drop data.

Per-garment settings are string lists of "garment:value" entries, so a garment list change never has to keep two
parallel arrays in step:
    garment_vertices:  ["tshirt:3000", "trousers:8000"]   vertex budget (level of detail) of a skinned template
    garment_databases: ["tshirt:data/tshirt_default.h5"]  AgentDress database of a garment (else skinned)
and the engine's speed/accuracy knobs (agentdress_ros.engine.EngineConfig) as "field=value" entries, for every
garment with a database or, prefixed with its name, for one:
    engine: ["pose_model=examples", "neighbors=3", "penetration=false", "tshirt:pose_model=regressor"]
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from ..body import PHENOTYPE_NAMES
from ..scene.lod import DEFAULT_TIER_TEXT, parse_tiers

__all__ = ["PARAMETERS", "ParameterError", "Spec", "engine_for", "parse_garment_map", "validate"]

QOS_RELIABILITY = ("best_effort", "reliable")
_GARMENT_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")  # becomes a topic token: ~/<garment>/points


class ParameterError(ValueError):
    """A rejected parameter value; the message is the reason."""


@dataclass(frozen=True)
class Spec:
    default: object
    description: str
    runtime: bool = True  # may change while the node runs


PARAMETERS: dict[str, Spec] = {
    "rate_hz": Spec(90.0, "garment output rate (timer frequency), Hz, in (0, 1000]"),
    "keepalive_hz": Spec(1.0, "re-publish the last clouds at this rate when no new pose arrived and nothing "
                              "changed (late subscribers get a frame within 1 s at no synthesis cost); 0 = off"),
    "marker_rate_hz": Spec(0.0, "visualization_msgs/Marker TRIANGLE_LIST rate for RViz, Hz, in [0, 10]; 0 = off"),
    "status_rate_hz": Spec(1.0, "rate of the JSON status on ~/status, Hz, in (0, 50]"),
    "inside_check_hz": Spec(0.0, "rate at which the last published garments are tested against the posed body (the "
                                 "winding-number test of the build and the evaluation, on a background thread; "
                                 "~/status 'inside'), Hz, in [0, 2]; 0 = off (the default: each check delays the "
                                 "ticks around it); one agent only"),
    "publish_body": Spec(False, "also publish the posed body surface on ~/body/points and ~/body/mesh, and its "
                                "skin and bones (~/body/skin, ~/body/bones)"),
    "answer_on_arrival": Spec(True, "dress a new pose as soon as it arrives (unless within half a period of the last "
                                    "answer: the timer takes those), so latency is not tied to the timer's phase"),
    "frame_id": Spec("agent", "frame_id stamped on every published message"),
    "joint_state_topic": Spec("joint_states", "sensor_msgs/JointState input topic", runtime=False),
    "shape_topic": Spec("body_shape", "std_msgs/Float32MultiArray body-shape input topic", runtime=False),
    "garments": Spec(["tshirt"], "garments to dress the agent in (templates tshirt, longsleeve, trousers)"),
    "garment_vertices": Spec([], "per-garment vertex budget 'name:count' of skinned templates (level of detail)"),
    "garment_databases": Spec([], "per-garment AgentDress database 'name:path.h5' (relative to the working dir)"),
    "garment_models": Spec([], "per-garment model of a garment with a database, 'name:model': agentdress (synthesis, "
                               "the default) or santesteban (Santesteban et al. 2019, from the database's "
                               "garment_model/santesteban group; one agent only, README 'Santesteban et al.'s "
                               "system')"),
    "engine": Spec(["pose_model=examples", "projection=8", "tshirt:pose_model=regressor", "tshirt:fold=false",
                    "trousers:pose_model=regressor", "trousers:fold=false", "longsleeve:pose_model=regressor",
                    "longsleeve:fold=false"],
                   "EngineConfig knobs of the garments with a database, 'field=value', or 'garment:field=value' "
                   "for one garment: pose_model (lbs, examples, regressor, recurrent, kdsm), fold, neighbors, "
                   "components, anchors, shape_model, penetration, projection, decay, damping, dtype (float32, "
                   "float64), taylor (augmented, plain, zeroth); see README 'Speed vs accuracy'"),
    "display_subdivision": Spec(1, "rounds of Loop subdivision (0, 1, 2) of each garment for display, published as "
                                   "its cloud and mesh (a fixed sparse matrix after penetration handling; README "
                                   "'Display')", runtime=False),
    "garment_layers": Spec([], "per-garment layer 'name:layer' (templates: trousers 1, tshirt and longsleeve 2); a "
                               "garment is pushed out of the next lower layer's; tucked in: ['trousers:3']",
                           runtime=False),
    "skinned_fallback": Spec(False, "if a garment's database is missing or unusable, dress it with the skinned "
                                    "template (warned) instead of exiting with an error"),
    "shape": Spec([0.5, 2.0 / 3.0, 0.5, 0.5, 0.5, 0.5], "initial body shape (gender, age, muscle, weight, height, "
                                                  "proportions), each in [0, 1]; setting it changes the shape"),
    "stamp_jump_threshold_s": Spec(0.5, "a JointState stamp this far (s) before or after the last accepted one "
                                        "starts a new timeline (looped bag, clock reset): accepted, warned and "
                                        "counted; closer older stamps are rejected as out of order; in (0, 86400]"),
    "warn_throttle_s": Spec(5.0, "at most one warning per kind per this many seconds, in (0, 3600]"),
    "qos.joint_states.reliability": Spec("best_effort", "JointState subscription reliability", runtime=False),
    "qos.joint_states.depth": Spec(1, "JointState subscription depth (keep last)", runtime=False),
    "qos.shape.reliability": Spec("reliable", "body shape subscription reliability", runtime=False),
    "qos.shape.depth": Spec(1, "body shape subscription depth (keep last)", runtime=False),
    "qos.points.reliability": Spec("best_effort", "PointCloud2 publisher reliability", runtime=False),
    "qos.points.depth": Spec(1, "PointCloud2 publisher depth (keep last)", runtime=False),
    # Crowd mode (agentdress_ros.ros.crowd): one node dresses every agent listed.
    "agents": Spec([], "agent names: each has <agent>/joint_states, <agent>/body_shape in and ~/<agent>/<garment>/"
                       "points, mesh out, taking the parameters above overridden by agent.<agent>.<parameter> (YAML); "
                       "agents may be added and removed at run time; empty = the single agent of today's topics"),
    "viewer_topic": Spec("viewer_pose", "geometry_msgs/PoseStamped input of the viewer (headset), crowd mode; "
                                        "empty = no viewer (every agent near, none culled)", runtime=False),
    "viewer_offset": Spec([0.0, 0.0, 0.0, 0.0], "fixed offset x, y, z (m), yaw (rad) taking viewer poses into the "
                                                "agents' frame (there is no tf2 wheel)"),
    "budget_ms": Spec(8.0, "frame budget of the crowd tick, ms: far agents are lowered or updated on alternate ticks "
                           "to hold it, near ones never; 0 = no budget"),
    "realtime_priority": Spec(0, "SCHED_FIFO priority (1-99) of the node's executor thread, so that its own DDS "
                                 "threads cannot preempt a tick (README 'A crowd in one node'); needs CAP_SYS_NICE or "
                                 "an rtprio limit, else a warning; 0 = the normal scheduler", runtime=False),
    "lod.enabled": Spec(True, "levels of detail and culling by the viewer's pose (false: every agent fully dressed)"),
    "lod.tiers": Spec(list(DEFAULT_TIER_TEXT), "tiers by distance, '<name> <max m|inf> <synthesis|skinned> "
                                               "[neighbors=n] [penetration=false] [pose_model=examples] [every=n] "
                                               "...'", runtime=False),
    "lod.hysteresis": Spec(0.5, "metres an agent must pass a tier boundary by before it changes tier"),
    "lod.fade_frames": Spec(6, "frames over which a tier change cross-fades (0: switch at once)", runtime=False),
    "lod.fov_deg": Spec(110.0, "the viewer's field of view, degrees (agents outside it, plus the margin, are culled)"),
    "lod.margin_deg": Spec(10.0, "margin added to each side of the field of view, degrees"),
    "lod.cull": Spec(True, "cull agents outside the field of view"),
}


def _number(name, value, low, high, low_open=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value < low or value > high or (low_open and value == low):
        bracket = "(" if low_open else "["
        raise ParameterError(f"{name} must be in {bracket}{low:g}, {high:g}], got {value:g}")
    return value


def _string_list(name, value) -> list[str]:
    if value is None:  # an empty YAML list arrives as "not set"
        return []
    if isinstance(value, str) or not all(isinstance(v, str) for v in value):
        raise ParameterError(f"{name} must be a list of strings, got {value!r}")
    return [v for v in value if v != ""]


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


#: The models a garment with a database can run (garment_models): AgentDress synthesis first (the default).
GARMENT_MODELS = ("agentdress", "santesteban")

# EngineConfig fields settable from a parameter, with their coercion (the rest are library-only).
_ENGINE_FIELDS = {
    "pose_model": str, "taylor": str, "dtype": str,
    "neighbors": int, "pose_neighbors": int, "components": int, "anchors": int, "projection": int,
    "shape_model": bool, "penetration": bool, "decay": bool, "clamp_to_training_range": bool, "fold": bool,
    "damping": float, "penetration_margin": float, "power": float,
}


def _engine_value(key: str, text: str):
    kind = _ENGINE_FIELDS[key]
    if kind is bool:
        if text.lower() not in ("true", "false"):
            raise ParameterError(f"engine: {key} must be true or false, got {text!r}")
        return text.lower() == "true"
    if kind is str:
        return text
    if key in ("components", "anchors") and text.lower() in ("none", "all"):
        return None
    try:
        value = kind(text)
    except ValueError:
        raise ParameterError(f"engine: {key}: {text!r} is not {'an integer' if kind is int else 'a number'}") from None
    if kind is float and not math.isfinite(value):
        raise ParameterError(f"engine: {key} must be finite, got {text!r}")
    return value


def parse_engine(value) -> tuple:
    """["neighbors=3", "tshirt:pose_model=regressor", ...] -> (("neighbors", 3), ("tshirt:pose_model", "regressor"),
    ...) sorted, checked by building an EngineConfig for every garment named (engine_for gives one garment's knobs).
    An entry "garment:field=value" overrides the field for that garment only."""
    from ..engine.config import EngineConfig

    fields = {}
    for entry in _string_list("engine", value):
        name, sep, text = (part.strip() for part in entry.partition("="))
        garment, colon, key = (part.strip() for part in name.rpartition(":"))
        if not sep or not key or not text or (colon and not _GARMENT_NAME.match(garment)):
            raise ParameterError(f"engine: entry {entry!r} must look like 'field=value' or 'garment:field=value'")
        if key not in _ENGINE_FIELDS:
            raise ParameterError(f"engine: unknown field {key!r}; one of {', '.join(sorted(_ENGINE_FIELDS))}")
        name = f"{garment}:{key}" if colon else key
        if name in fields:
            raise ParameterError(f"engine: {name} appears twice")
        fields[name] = _engine_value(key, text)
    from ..engine.pose_models import POSE_MODELS

    for name, model in fields.items():
        if name.rpartition(":")[2] == "pose_model" and model not in POSE_MODELS:
            raise ParameterError(f"engine: {name} must be one of {', '.join(sorted(POSE_MODELS))}, got {model!r}")
    entries = tuple(sorted(fields.items()))
    for garment in sorted({n.rpartition(":")[0] for n in fields}):
        try:
            EngineConfig(**dict(engine_for(entries, garment)))
        except (TypeError, ValueError) as error:
            raise ParameterError(f"engine{f' ({garment})' if garment else ''}: {error}") from None
    return entries


def engine_for(engine: tuple, garment: str) -> tuple:
    """One garment's EngineConfig overrides ((field, value), ...) from parse_engine's entries: the plain entries,
    replaced by that garment's "garment:field" ones."""
    fields = {k: v for k, v in engine if ":" not in k}
    fields.update({k.rpartition(":")[2]: v for k, v in engine if k.rpartition(":")[0] == garment})
    return tuple(sorted(fields.items()))


def validate(name: str, value):
    """Coerce and check one parameter value; raises ParameterError with the reason."""
    if name in ("rate_hz",):
        return _number(name, value, 0.0, 1000.0, low_open=True)
    if name == "keepalive_hz":
        return _number(name, value, 0.0, 100.0)
    if name == "marker_rate_hz":
        return _number(name, value, 0.0, 10.0)
    if name == "inside_check_hz":
        return _number(name, value, 0.0, 2.0)
    if name == "status_rate_hz":
        return _number(name, value, 0.0, 50.0, low_open=True)
    if name == "stamp_jump_threshold_s":
        return _number(name, value, 0.0, 86400.0, low_open=True)
    if name == "warn_throttle_s":
        return _number(name, value, 0.0, 3600.0, low_open=True)
    if name == "agents":
        agents = _string_list(name, value)
        for a in agents:
            if not _GARMENT_NAME.match(a):
                raise ParameterError(f"agents: {a!r} is not a valid agent name (a letter, then letters, digits, _)")
        if len(set(agents)) != len(agents):
            raise ParameterError(f"agents: names repeat in {agents}")
        return agents
    if name == "viewer_topic":
        if not isinstance(value, str):
            raise ParameterError(f"viewer_topic must be a string, got {value!r}")
        return value.strip()
    if name == "viewer_offset":
        if value is None or isinstance(value, (str, bool)) or len(value) != 4:
            raise ParameterError(f"viewer_offset must be four numbers x, y, z, yaw, got {value!r}")
        return [_number(name, v, -1e6, 1e6) for v in value]
    if name == "budget_ms":
        return _number(name, value, 0.0, 1000.0)
    if name == "lod.tiers":
        try:
            parse_tiers(_string_list(name, value))
        except ValueError as error:
            raise ParameterError(f"lod.tiers: {error}") from None
        return _string_list(name, value)
    if name == "lod.hysteresis":
        return _number(name, value, 0.0, 100.0)
    if name == "realtime_priority":
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 99:
            raise ParameterError(f"realtime_priority must be an integer in [0, 99], got {value!r}")
        return value
    if name == "lod.fade_frames":
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 100:
            raise ParameterError(f"lod.fade_frames must be an integer in [0, 100], got {value!r}")
        return value
    if name in ("lod.fov_deg", "lod.margin_deg"):
        return _number(name, value, 0.0, 360.0)
    if name in ("publish_body", "skinned_fallback", "answer_on_arrival", "lod.enabled", "lod.cull"):
        if not isinstance(value, bool):
            raise ParameterError(f"{name} must be true or false, got {value!r}")
        return value
    if name in ("frame_id", "joint_state_topic", "shape_topic"):
        if not isinstance(value, str) or not value.strip():
            raise ParameterError(f"{name} must be a non-empty string, got {value!r}")
        return value.strip()
    if name == "garments":
        garments = _string_list(name, value)
        for g in garments:
            if not _GARMENT_NAME.match(g) or g == "body":
                raise ParameterError(f"garments: {g!r} is not a valid garment name (letters, digits, _; not 'body')")
        if len(set(garments)) != len(garments):
            raise ParameterError(f"garments: names repeat in {garments}")
        return garments
    if name == "garment_vertices":
        budgets = {}
        for key, item in parse_garment_map(name, value).items():
            try:
                count = int(item)
            except ValueError:
                raise ParameterError(f"garment_vertices: {key}: {item!r} is not an integer") from None
            if not 100 <= count <= 200_000:
                raise ParameterError(f"garment_vertices: {key}: {count} must be in [100, 200000]")
            budgets[key] = count
        return budgets
    if name == "garment_databases":
        return parse_garment_map(name, value)
    if name == "garment_models":
        models = parse_garment_map(name, value)
        for key, item in models.items():
            if item not in GARMENT_MODELS:
                raise ParameterError(f"garment_models: {key}: {item!r} must be one of {', '.join(GARMENT_MODELS)}")
        return models
    if name == "display_subdivision":
        if isinstance(value, bool) or value not in (0, 1, 2):
            raise ParameterError(f"display_subdivision must be 0, 1 or 2, got {value!r}")
        return int(value)
    if name == "garment_layers":
        layers = {}
        for key, item in parse_garment_map(name, value).items():
            try:
                layers[key] = int(item)
            except ValueError:
                raise ParameterError(f"garment_layers: {key}: {item!r} is not an integer") from None
        return layers
    if name == "engine":
        return parse_engine(value)
    if name == "shape":
        if value is None or isinstance(value, (str, bool)) or not hasattr(value, "__len__"):
            raise ParameterError(f"shape must be a list of {len(PHENOTYPE_NAMES)} numbers, got {value!r}")
        values = list(value)
        if len(values) != len(PHENOTYPE_NAMES):
            raise ParameterError(f"shape needs {len(PHENOTYPE_NAMES)} values ({', '.join(PHENOTYPE_NAMES)}), "
                                 f"got {len(values)}")
        bad = [n for n, v in zip(PHENOTYPE_NAMES, values) if isinstance(v, bool) or not isinstance(v, (int, float))
               or not math.isfinite(v)]
        if bad:
            raise ParameterError(f"shape has non-finite or non-numeric values for {', '.join(bad)}")
        return [float(v) for v in values]
    if name.startswith("qos.") and name.endswith(".reliability"):
        if value not in QOS_RELIABILITY:
            raise ParameterError(f"{name} must be one of {QOS_RELIABILITY}, got {value!r}")
        return value
    if name.startswith("qos.") and name.endswith(".depth"):
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 1000:
            raise ParameterError(f"{name} must be an integer in [1, 1000], got {value!r}")
        return value
    raise ParameterError(f"unknown parameter {name!r}")


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
