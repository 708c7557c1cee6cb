"""Typed configuration: one table of engine knobs read from text (the node's `engine` parameter, its per-garment
entries, a crowd's tier lines, Engine.fork), and node parameters that each carry their own check."""
from __future__ import annotations

import dataclasses
import math

import pytest

from agentdress_ros.engine.config import ENGINE_KNOBS, PER_FRAME_KNOBS, EngineConfig, EngineKnobs
from agentdress_ros.engine.engine import Engine
from agentdress_ros.ros.params import PARAMETERS, GarmentEngines, ParameterError, validate
from agentdress_ros.scene.lod import parse_tier

# a text each knob takes, and the value it reads as
GOOD = {"pose_model": ("examples", "examples"), "taylor": ("plain", "plain"), "dtype": ("float64", "float64"),
        "neighbors": ("3", 3), "pose_neighbors": ("2", 2), "components": ("all", None), "anchors": ("4", 4),
        "projection": ("0", 0), "shape_model": ("False", False), "penetration": ("false", False),
        "decay": ("true", True), "clamp_to_training_range": ("false", False), "fold": ("false", False),
        "damping": ("0.25", 0.25), "penetration_margin": ("0.01", 0.01), "power": ("2", 2.0)}
# a text each knob refuses, and words of the reason
BAD = {"pose_model": ("neural", "one of"), "taylor": ("cubic", "one of"), "dtype": ("float16", "one of"),
       "neighbors": ("0", ">= 1"), "pose_neighbors": ("two", "integer"), "components": ("0", ">= 1"),
       "anchors": ("1.5", "integer"), "projection": ("-1", ">= 0"), "shape_model": ("yes", "true or false"),
       "penetration": ("1", "true or false"), "decay": ("maybe", "true or false"),
       "clamp_to_training_range": ("no", "true or false"), "fold": ("on", "true or false"),
       "damping": ("nan", "finite"), "penetration_margin": ("wide", "number"), "power": ("inf", "finite")}


def test_every_knob_is_an_engine_config_field_and_reads_its_text():
    fields = {f.name for f in dataclasses.fields(EngineConfig)}
    assert set(ENGINE_KNOBS) <= fields
    assert set(GOOD) == set(ENGINE_KNOBS) == set(BAD)
    for name, (text, value) in GOOD.items():
        assert ENGINE_KNOBS[name].read(name, text) == value, name
        assert EngineKnobs.parse([f"{name}={text}"]).as_dict() == {name: value}
    for name, (text, words) in BAD.items():
        with pytest.raises(ValueError, match=words) as info:
            ENGINE_KNOBS[name].read(name, text)
        assert name in str(info.value)


def test_the_per_frame_knobs_are_the_forks_and_the_tiers():
    assert Engine.FORK_FIELDS == PER_FRAME_KNOBS
    assert set(PER_FRAME_KNOBS) == {"neighbors", "penetration", "projection", "decay", "damping", "power",
                                    "pose_model"}
    for name in ENGINE_KNOBS:
        text, value = GOOD[name]
        line = f"t inf synthesis {name}={text}"
        if name in PER_FRAME_KNOBS:
            assert parse_tier(line).engine == EngineKnobs.of(**{name: value})
        else:
            with pytest.raises(ValueError, match="unknown key"):
                parse_tier(line)
    with pytest.raises(ValueError, match="unknown field 'fold'"):
        EngineKnobs.parse(["fold=false"], per_frame=True)


def test_knobs_compare_by_value_print_back_and_build_a_config():
    knobs = EngineKnobs.parse(["penetration=false", "neighbors=2", "components=all"])
    assert knobs == EngineKnobs.of(neighbors=2, components=None, penetration=False)
    assert hash(knobs) == hash(EngineKnobs.of(penetration=False, components=None, neighbors=2))
    assert EngineKnobs.parse(knobs.words()) == knobs
    assert knobs.config() == EngineConfig(neighbors=2, components=None, penetration=False)
    assert knobs.without("neighbors") == EngineKnobs.of(components=None, penetration=False)
    assert EngineKnobs.of(neighbors=4).over(knobs).get("neighbors") == 4
    assert not EngineKnobs() and knobs
    for words, reason in ((["neighbors"], "field=value"), (["speed=9"], "unknown field"),
                          (["neighbors=2", "neighbors=3"], "twice")):
        with pytest.raises(ValueError, match=reason):
            EngineKnobs.parse(words)
    with pytest.raises(ValueError, match="unknown engine knob"):
        EngineKnobs.of(vertices=(1, 2))


def test_the_engine_parameter_gives_each_garment_its_knobs():
    engines = validate("engine", ["pose_model=examples", "projection=8", "tshirt:pose_model=regressor",
                                  "tshirt:fold=false"])
    assert isinstance(engines, GarmentEngines)
    assert engines.for_garment("tshirt") == EngineKnobs.of(pose_model="regressor", fold=False, projection=8)
    assert engines.for_garment("trousers") == EngineKnobs.of(pose_model="examples", projection=8)
    # the shipped default: every garment it names builds a config
    default = validate("engine", PARAMETERS["engine"].default)
    for garment in ("tshirt", "trousers", "longsleeve", "hat"):
        default.for_garment(garment).config()
    with pytest.raises(ParameterError, match=r"engine \(tshirt\): taylor='zeroth'"):
        validate("engine", ["taylor=zeroth", "tshirt:shape_model=false"])


def test_every_parameter_carries_its_check_and_its_default_passes_it():
    for name, spec in PARAMETERS.items():
        assert callable(spec.check), name
        value = validate(name, spec.default)
        if name == "engine":
            assert isinstance(value, GarmentEngines)
        elif isinstance(spec.default, list) and name not in ("shape", "viewer_offset"):
            assert isinstance(value, (list, dict)), name
        else:
            assert value == spec.default or (isinstance(value, float) and math.isclose(value, spec.default)), name
        # a value of the wrong kind is refused, naming the parameter
        wrong = {"shape": "tall", "viewer_offset": [1.0], "lod.tiers": ["a 3 synthesis"]}.get(
            name, [1] if isinstance(spec.default, list) else "yes" if isinstance(spec.default, bool) else object())
        with pytest.raises(ParameterError) as info:
            validate(name, wrong)
        assert name in str(info.value), (name, str(info.value))
    with pytest.raises(ParameterError, match="unknown parameter"):
        validate("speed", 1)


def test_a_crowd_agents_overrides_take_their_parameters_checks():
    from agentdress_ros.ros.crowd import AGENT_CHECKS, agent_overrides

    for key, check in AGENT_CHECKS.items():
        if key in PARAMETERS:
            assert check is PARAMETERS[key].check, key
    assert agent_overrides({"bob.origin": [3, 0, 0], "bob.engine": ["neighbors=2"], "amy.extra_cost_ms": 2}) == {
        "amy": {"extra_cost_ms": 2.0}, "bob": {"origin": (3.0, 0.0, 0.0), "engine": GarmentEngines(
            EngineKnobs.of(neighbors=2))}}
    for values, words in (({"bob.origin": [1, 2]}, "agent.bob.origin must be three"),
                          ({"bob.engine": ["neighbors=0"]}, "agent.bob.engine: neighbors must be >= 1"),
                          ({"bob.extra_cost_ms": -1}, "agent.bob.extra_cost_ms must be in [0, 1000]"),
                          ({"bob.colour": "red"}, "unknown per-agent parameter 'colour'")):
        with pytest.raises(ParameterError) as info:
            agent_overrides(values)
        assert words in str(info.value), str(info.value)
