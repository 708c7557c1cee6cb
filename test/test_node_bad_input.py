"""Bad input: the pure checks directly, the node's output guard in-process, and a live node over DDS.

Every case: nothing crashes, no non-finite value is published, the last good mesh is kept, the rejection is counted
by reason on ~/status and the warning names what was wrong.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agentdress_ros.motion.joint_names import JOINT_NAMES
from agentdress_ros.ros.inputs import InputRejected, PoseInput, check_shape_values
from agentdress_ros.engine.config import EngineKnobs
from agentdress_ros.ros.params import GarmentEngines, ParameterError, check_garment_config, parse_garment_map, validate
from agentdress_ros.ros.runtime import GarmentSpec, SceneSpec, build_model_set

# ---------------------------------------------------------------------------------------------------- pure checks


def _reason(call) -> str:
    with pytest.raises(InputRejected) as info:
        call()
    return info.value.reason, str(info.value)


def test_joint_state_rejections_name_the_problem_and_change_nothing():
    pose = PoseInput()
    pose.accept(["LeftArm_rx", "Hips_tz"], [0.5, 0.1], stamp_ns=1_000)
    before, version = pose.values.copy(), pose.version
    assert _reason(lambda: pose.accept([], []))[0] == "empty"
    reason, text = _reason(lambda: pose.accept(["LeftArm_rx", "LeftArm_ry"], [0.1]))
    assert reason == "length_mismatch" and "2 names but 1 positions" in text
    reason, text = _reason(lambda: pose.accept(["LeftArm_rx", "Spine_ry"], [0.2, math.nan]))
    assert reason == "non_finite" and "Spine_ry" in text
    reason, text = _reason(lambda: pose.accept(["Hips_tx"], [math.inf]))
    assert reason == "non_finite" and "Hips_tx" in text
    reason, text = _reason(lambda: pose.accept(["Hips_tx"], [1e30]))
    assert reason == "out_of_range" and "Hips_tx" in text
    assert _reason(lambda: pose.accept(["LeftArm_rx"], [0.3], stamp_ns=999))[0] == "out_of_order"
    assert _reason(lambda: pose.accept(["Tail_rx"], [0.3]))[0] == "no_known_joints"
    np.testing.assert_array_equal(pose.values, before)
    assert pose.version == version and pose.stamp_ns == 1_000


def test_unknown_joint_names_are_reported_once_and_known_ones_applied():
    pose = PoseInput()
    assert pose.accept(["Tail_rx", "LeftArm_rz"], [1.0, 0.25]) == ["Tail_rx"]
    assert pose.accept(["Tail_rx", "LeftArm_rz", "Ear_ry"], [1.0, 0.5, 2.0]) == ["Ear_ry"]
    assert pose.values[JOINT_NAMES.index("LeftArm_rz")] == 0.5
    assert pose.accept(["LeftArm_rx"], [0.1], stamp_ns=0) == []  # unstamped: no ordering check


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(list(JOINT_NAMES[:6]) + ["bogus", ""]),
                          st.floats(allow_nan=True, allow_infinity=True, width=64)), max_size=8),
       st.integers(min_value=0, max_value=3), st.integers(min_value=0, max_value=2**62))
def test_no_joint_state_makes_the_pose_non_finite(entries, extra, stamp):
    pose = PoseInput()
    names = [n for n, _ in entries]
    positions = [v for _, v in entries] + [0.0] * (extra % 2)  # sometimes a length mismatch
    try:
        pose.accept(names, positions, stamp)
    except InputRejected as error:
        assert error.reason in {"empty", "length_mismatch", "non_finite", "out_of_range", "no_known_joints"}
    assert np.isfinite(pose.values).all() and np.abs(pose.values).max() <= 1e4


def test_shape_values_clamped_or_rejected_with_the_phenotype_named():
    update = check_shape_values([0.5, 1.7, 0.5, -0.2, 0.5, 0.5])
    assert update.clamped and "age=1.7" in update.message and "weight=-0.2" in update.message
    np.testing.assert_array_equal(update.beta, [0.5, 1.0, 0.5, 0.0, 0.5, 0.5])
    reason, text = _reason(lambda: check_shape_values([0.5, 0.5, float("nan"), 0.5, 0.5, 0.5]))
    assert reason == "non_finite" and "muscle" in text
    assert _reason(lambda: check_shape_values([0.5] * 5))[0] == "length_mismatch"
    assert _reason(lambda: check_shape_values([]))[0] == "empty"
    assert not check_shape_values([0.5] * 6).clamped


def test_parameter_validation_reasons():
    assert validate("rate_hz", 90) == 90.0
    for name, value, words in [("rate_hz", 0.0, "rate_hz"), ("rate_hz", "fast", "number"),
                               ("marker_rate_hz", 30.0, "[0, 10]"), ("keepalive_hz", -1.0, "keepalive_hz"),
                               ("garments", ["tshirt", "tshirt"], "repeat"), ("garments", ["bad name"], "valid"),
                               ("garment_vertices", ["tshirt:ten"], "integer"), ("garment_vertices", ["tshirt:5"], "100"),
                               ("garment_vertices", ["tshirt"], "garment:value"), ("shape", [0.5] * 5, "6 values"),
                               ("shape", [0.5] * 5 + [float("nan")], "proportions"),
                               ("qos.points.reliability", "sometimes", "best_effort"), ("qos.points.depth", 0, "depth"),
                               ("publish_body", "yes", "true or false"),
                               ("engine", ["neighbors"], "field=value"), ("engine", ["speed=9"], "unknown field"),
                               ("engine", ["neighbors=0"], "neighbors"), ("engine", ["decay=maybe"], "true or false"),
                               ("engine", ["pose_model=neural"], "pose_model"), ("engine", ["damping=1.5"], "damping"),
                               ("engine", ["dtype=float16"], "dtype"), ("engine", ["neighbors=2", "neighbors=3"],
                                                                        "twice"),
                               ("engine", ["tshirt:pose_model=neural"], "tshirt:pose_model"),
                               ("engine", ["tshirt:neighbors=0"], "tshirt:neighbors"), ("engine", ["bad name:decay=true"],
                                                                              "garment:field=value"),
                               ("engine", ["tshirt:decay=true", "tshirt:decay=false"], "twice")]:
        with pytest.raises(ParameterError, match=None) as info:
            validate(name, value)
        assert words in str(info.value), (name, value, str(info.value))
    assert validate("garment_vertices", None) == {}  # an empty YAML list arrives as "not set"
    assert validate("engine", ["pose_model=examples", "neighbors=3", "penetration=False", "components=all"]) == \
        GarmentEngines(EngineKnobs.of(components=None, neighbors=3, penetration=False, pose_model="examples"))
    # a "garment:" prefix overrides a knob for that garment only
    engine = validate("engine", ["pose_model=examples", "neighbors=3", "tshirt:pose_model=regressor",
                                 "tshirt:neighbors=5"])
    assert engine.for_garment("tshirt") == EngineKnobs.of(neighbors=5, pose_model="regressor")
    assert engine.for_garment("trousers") == EngineKnobs.of(neighbors=3, pose_model="examples")
    assert parse_garment_map("garment_databases", ["tshirt: a.h5", ""]) == {"tshirt": "a.h5"}
    with pytest.raises(ParameterError, match="hat"):
        check_garment_config(["tshirt", "hat"], {}, ("tshirt", "trousers"))
    check_garment_config(["hat"], {"hat": "hat.h5"}, ("tshirt",))  # a database makes any name a garment


def test_missing_database_names_the_file_or_falls_back_when_configured(body, tmp_path):
    from agentdress_ros.models.garment_models import GarmentDatabaseError

    missing = tmp_path / "nope" / "tshirt.h5"
    scene = SceneSpec((GarmentSpec("tshirt", 300, str(missing)),), False, (0.5,) * 6)
    with pytest.raises(GarmentDatabaseError, match=str(missing)):
        build_model_set(scene, body)
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"not hdf5")
    with pytest.raises(GarmentDatabaseError, match="broken.h5"):
        build_model_set(SceneSpec((GarmentSpec("tshirt", None, str(broken)),), False, (0.5,) * 6), body)
    fallback = build_model_set(SceneSpec(scene.garments, False, (0.5,) * 6, skinned_fallback=True), body)
    assert fallback.models["tshirt"].kind == "skinned" and str(missing) in " ".join(fallback.warnings)


# ------------------------------------------------------------------------------- in-process node, NaN-ing model

rclpy = pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels, requirements/runtime.txt) is not importable")

from agentdress_ros.ros.harness import node_args, ros_env, ros_node, spin_until  # noqa: E402
from agentdress_ros.ros.messages import cloud_to_vertices  # noqa: E402

from .conftest import qos, running_node  # noqa: E402


def test_node_never_publishes_non_finite_synthesis(body, ros_domain):
    """A model that starts emitting NaN (or raising): the node re-sends the last good frame and counts it."""
    from rclpy.parameter import Parameter

    from agentdress_ros.ros.node import AgentDressNode

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros_domain())
    try:
        node = AgentDressNode(body, context=context, parameter_overrides=[
            Parameter("garment_vertices", value=["tshirt:400"]), Parameter("status_rate_hz", value=0.5)])
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import PointCloud2

        published = []
        crowd = node.agents  # the crowd of one
        crowd.entities[""].points["tshirt"].publish = lambda data: published.append(
            cloud_to_vertices(deserialize_message(data, PointCloud2)))
        node._on_tick()  # the rest-pose frame: the last good one from now on
        good = published[-1]
        agent = crowd.scene.agents[""]
        garment = agent.garments["tshirt"]
        real = garment.dress

        def nan_ing(level, rotvecs, translation):
            out = real(level, rotvecs, translation).copy()
            out[5] = np.nan
            return out

        def raising(level, rotvecs, translation):
            raise RuntimeError("engine exploded")

        for broken in (nan_ing, raising):
            garment.dress = broken
            agent.pose.accept(["LeftArm_rx"], [0.3 + len(published)])
            node._on_tick()
            assert np.isfinite(published[-1]).all()
            np.testing.assert_array_equal(published[-1], good)
        assert node.stats.counts["non_finite_output:tshirt"] == 1
        assert node.stats.counts["synthesis_error:tshirt"] == 1
        garment.dress = real
        agent.pose.accept(["LeftArm_rx"], [0.9])
        node._on_tick()
        assert not np.array_equal(published[-1], good)  # recovers as soon as the model does
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


# ---------------------------------------------------------------------------------------------- live node, DDS


@pytest.fixture(scope="module")
def live(tmp_path_factory, ros_domain):
    from sensor_msgs.msg import JointState, PointCloud2
    from std_msgs.msg import Float32MultiArray, String

    domain = ros_domain()
    params = {"garment_vertices": ["tshirt:800"], "status_rate_hz": 5.0, "warn_throttle_s": 0.5}
    with running_node(tmp_path_factory.mktemp("node"), domain, params) as child, \
            ros_node("agentdress_bad_input_client", domain) as (node, executor):
        state = {"clouds": [], "status": []}
        node.create_subscription(PointCloud2, "/agentdress_node/tshirt/points", state["clouds"].append,
                                 qos("best_effort", 50))
        node.create_subscription(String, "/agentdress_node/status", lambda m: state["status"].append(json.loads(m.data)),
                                 10)
        joints = node.create_publisher(JointState, "joint_states", 10)
        shapes = node.create_publisher(Float32MultiArray, "body_shape", 10)
        assert spin_until(executor, lambda: joints.get_subscription_count() > 0 and shapes.get_subscription_count() > 0
                          and state["status"], 30.0), child.output()
        yield child, node, executor, joints, shapes, state


def _joint_state(node, names, positions, stamp_ns=None):
    from sensor_msgs.msg import JointState

    msg = JointState(name=list(names), position=[float(p) for p in positions])
    if stamp_ns is None:
        msg.header.stamp = node.get_clock().now().to_msg()
    else:
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return msg


def _send_until_counted(live, publish, key, where="rejected", timeout=20.0):
    """Publish (again every 0.5 s: best effort, depth 1) until the node's status counts `key` once more."""
    child, node, executor, joints, shapes, state = live
    spin_until(executor, lambda: False, 0.3)
    start = state["status"][-1][where].get(key, 0)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        publish()
        if spin_until(executor, lambda: state["status"][-1][where].get(key, 0) > start, 0.5):
            return
    raise AssertionError(f"status never counted {where}/{key}:\n{child.output()}")


def test_live_node_rejects_bad_messages_and_stays_finite(live):
    child, node, executor, joints, shapes, state = live
    from std_msgs.msg import Float32MultiArray

    cases = [
        (lambda: joints.publish(_joint_state(node, ["LeftArm_rx", "LeftArm_ry"], [0.1])), "joint_states/length_mismatch"),
        (lambda: joints.publish(_joint_state(node, ["LeftArm_rx", "Spine_ry"], [0.1, math.nan])), "joint_states/non_finite"),
        (lambda: joints.publish(_joint_state(node, ["Hips_tz"], [-math.inf])), "joint_states/non_finite"),
        (lambda: joints.publish(_joint_state(node, [], [])), "joint_states/empty"),
        (lambda: joints.publish(_joint_state(node, ["Bogus_joint"], [1.0])), "joint_states/no_known_joints"),
        (lambda: shapes.publish(Float32MultiArray(data=[0.5, 0.5, math.nan, 0.5, 0.5, 0.5])), "body_shape/non_finite"),
        (lambda: shapes.publish(Float32MultiArray(data=[0.5] * 3)), "body_shape/length_mismatch"),
        (lambda: shapes.publish(Float32MultiArray(data=[])), "body_shape/empty"),
    ]
    for publish, key in cases:
        _send_until_counted(live, publish, key)
    _send_until_counted(live, lambda: shapes.publish(Float32MultiArray(data=[0.5, 1.5, 0.5, 0.5, 0.5, -3.0])),
                        "shapes_clamped", where="counts")
    assert spin_until(executor, lambda: state["status"][-1]["shape"] == [0.5, 1.0, 0.5, 0.5, 0.5, 0.0], 20.0)

    # Out of order: a stamp older than the last accepted one.
    now_ns = node.get_clock().now().nanoseconds
    _send_until_counted(live, lambda: joints.publish(_joint_state(node, ["LeftArm_rx"], [0.2], now_ns)),
                        "joint_states_received", where="counts")
    _send_until_counted(live, lambda: joints.publish(_joint_state(node, ["LeftArm_rx"], [0.4], now_ns - 10**8)),
                        "joint_states/out_of_order")

    # Unknown names mixed with known ones: applied, reported once.
    for _ in range(3):
        _send_until_counted(live, lambda: joints.publish(_joint_state(node, ["Tail_rx", "LeftArm_rx"], [1.0, 0.3])),
                            "joint_states_received", where="counts")
    assert "Tail_rx" in state["status"][-1]["unknown_joint_names"]

    log = child.output(200_000)
    assert log.count("Tail_rx") == 1, "unknown joint names must be reported once"
    for words in ("Spine_ry", "2 names but 1 positions", "muscle", "age=1.5", "out_of_order", "proportions=-3"):
        assert words in log, f"no warning naming {words!r}:\n{log[-3000:]}"
    assert child.proc.poll() is None
    assert state["clouds"], "no cloud was published"
    for cloud in state["clouds"]:
        assert np.isfinite(cloud_to_vertices(cloud)).all()


def test_live_node_survives_a_1khz_flood(live):
    child, node, executor, joints, shapes, state = live
    from agentdress_ros.motion.procedural import make_motion

    motion = make_motion("wave", fps=1000.0, duration=2.0)
    names = list(JOINT_NAMES)
    n_clouds = len(state["clouds"])
    rejected = state["status"][-1]["rejected"].get("joint_states/non_finite", 0)  # earlier tests' NaNs included
    start, sent = time.monotonic(), 0
    while time.monotonic() - start < 2.0:
        # 1 kHz, good and bad mixed: every 10th message has a NaN
        k = sent % len(motion.rotvecs)
        positions = np.concatenate([motion.rotvecs[k].reshape(-1), motion.root_translation[k]])
        if sent % 10 == 9:
            positions[4] = np.nan
        joints.publish(_joint_state(node, names, positions))
        sent += 1
        target = start + sent / 1000.0
        while time.monotonic() < target:
            executor.spin_once(timeout_sec=0)
    assert spin_until(executor, lambda: len(state["status"]) > 2, 10.0)
    assert child.proc.poll() is None, child.output()
    # the clouds keep coming through the flood (how many a second is `agentdress bench node`'s to measure)
    new = state["clouds"][n_clouds:]
    assert new, f"no cloud during the flood of {sent} JointStates"
    for cloud in new:
        assert np.isfinite(cloud_to_vertices(cloud)).all()
    # every 10th message had a NaN: those that reached the node are counted (best effort may drop some of them)
    assert spin_until(executor, lambda: state["status"][-1]["rejected"].get("joint_states/non_finite", 0) > rejected,
                      10.0), state["status"][-1]["rejected"]


def test_missing_database_stops_the_node_with_the_file_named(tmp_path, ros_domain):
    missing = tmp_path / "no_such" / "tshirt_default.h5"
    env = ros_env(ros_domain(), str(tmp_path))
    proc = subprocess.run(node_args({"garment_databases": [f"tshirt:{missing}"]}), env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert str(missing) in proc.stderr and "does not exist" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_ros_free_modules_do_not_import_rclpy():
    """The garment-model protocol, input checks, parameters and runtime are usable without ROS."""
    code = ("import sys; import agentdress_ros.models.garment_models, agentdress_ros.ros.inputs, "
            "agentdress_ros.ros.params, agentdress_ros.ros.runtime; "
            "sys.exit('rclpy imported' if 'rclpy' in sys.modules else 0)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
