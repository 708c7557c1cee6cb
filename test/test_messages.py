"""Messages kept serialized (the crowd's byte paths) agree with rclpy's own serializer, field for field."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="rclpy (ros-jazzy-rclpy wheels, requirements/runtime.txt) is not importable")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import JointState, PointCloud2, PointField  # noqa: E402

from agentdress_ros.motion.joint_names import JOINT_NAMES  # noqa: E402
from agentdress_ros.ros.messages import (JointStateReader, SerializedCloud, SerializedJointState,  # noqa: E402
                                         cloud_to_vertices, serialized_cloud_to_vertices)


def _joint_state(names, positions, frame_id="world", sec=12, nanosec=345, velocity=()):
    msg = JointState(name=list(names), position=[float(p) for p in positions], velocity=list(velocity))
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    return msg


@pytest.mark.parametrize("n_vertices", [1, 7, 1200])
def test_serialized_cloud_deserializes_to_the_frame_written(n_vertices):
    rng = np.random.default_rng(n_vertices)
    cloud = SerializedCloud("agent_frame", n_vertices)
    for stamp_ns in (0, 1_796_000_000_123_456_789, 5_999_999_999):
        vertices = rng.normal(size=(n_vertices, 3)).astype(np.float32)
        msg = deserialize_message(cloud.set(vertices, stamp_ns), PointCloud2)
        assert np.array_equal(cloud_to_vertices(msg), vertices)  # bit for bit
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp_ns, 1_000_000_000)
        assert msg.header.frame_id == "agent_frame"
        assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, n_vertices, 12, 12 * n_vertices)
        assert [f.name for f in msg.fields] == ["x", "y", "z"] and msg.is_dense
        assert cloud.data == cloud.set(vertices, stamp_ns)  # `data` is the last frame (the keep-alive re-sends it)


def _cloud(points, fields, point_step, frame_id="f", height=1, big_endian=False, sec=7, nanosec=250_000_000):
    """A PointCloud2 of `points` (N, 3) at the (name, offset, datatype) `fields`, other bytes of a point random."""
    n = len(points)
    raw = np.random.default_rng(n).integers(0, 255, (n, point_step), dtype=np.uint8)
    order = ">f4" if big_endian else "<f4"
    offsets = {name: offset for name, offset, _ in fields}
    for k, axis in enumerate("xyz"):
        raw[:, offsets[axis]:offsets[axis] + 4] = np.ascontiguousarray(points[:, k], dtype=order).view(np.uint8).reshape(n, 4)
    msg = PointCloud2(height=height, width=n // height, point_step=point_step, row_step=point_step * (n // height),
                      is_bigendian=big_endian, is_dense=True, data=raw.tobytes(),
                      fields=[PointField(name=name, offset=offset, datatype=dtype, count=1)
                              for name, offset, dtype in fields])
    msg.header.frame_id = frame_id
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    return msg


def test_serialized_cloud_reader_matches_the_deserializer_on_every_layout():
    """A raw subscription's PointCloud2 bytes read with numpy (the display bridge) give what rclpy's deserializer
    and cloud_to_vertices give, bit for bit: packed x, y, z; fields after others, padding, two rows, big endian,
    odd-length frame ids and names (CDR alignment); malformed bytes raise ValueError, never read past the end."""
    rng = np.random.default_rng(5)
    points = rng.normal(size=(6, 3)).astype(np.float32)
    layouts = [
        ([("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12, {}),
        ([("intensity", 0, 7), ("x", 4, 7), ("y", 8, 7), ("z", 12, 7), ("rgb", 16, 6)], 24, {"height": 2}),
        ([("z", 0, 7), ("ring", 4, 4), ("y", 8, 7), ("x", 12, 7)], 16, {"big_endian": True, "frame_id": "abcde"}),
        ([("a_long_name", 0, 2), ("x", 1, 7), ("y", 5, 7), ("z", 9, 7)], 13, {"frame_id": ""}),
    ]
    for fields, step, extra in layouts:
        msg = _cloud(points, fields, step, **extra)
        data = serialize_message(msg)
        vertices, stamp = serialized_cloud_to_vertices(data)
        assert np.array_equal(vertices, points) and vertices.dtype == np.float32 and vertices.flags.writeable
        assert np.array_equal(vertices, cloud_to_vertices(deserialize_message(data, PointCloud2)))
        assert stamp == pytest.approx(7.25)
    packed = SerializedCloud("agent", 1200)
    frame = rng.normal(size=(1200, 3)).astype(np.float32)
    assert np.array_equal(serialized_cloud_to_vertices(packed.set(frame, 3_000_000_001))[0], frame)
    good = serialize_message(_cloud(points, layouts[1][0], 24, height=2))
    no_z = _cloud(points, layouts[0][0], 12)
    no_z.fields[2].name = "w"
    no_z = serialize_message(no_z)
    as_double = serialize_message(_cloud(points, [("x", 0, 8), ("y", 8, 8), ("z", 16, 8)], 24))
    beyond = _cloud(points, layouts[0][0], 12)
    beyond.fields[2].offset = 10
    beyond = serialize_message(beyond)
    for bad in (b"", b"\x00\x01\x00\x00", good[:60], good[:-40], b"\x07" + good[1:], no_z, as_double, beyond,
                good[:4] + b"\xff" * (len(good) - 4)):
        with pytest.raises(ValueError):
            serialized_cloud_to_vertices(bad)


def test_joint_state_reader_matches_the_deserializer_on_every_kind_of_message():
    reader = JointStateReader()
    rng = np.random.default_rng(0)
    full = list(JOINT_NAMES)
    cases = [
        _joint_state(full, rng.normal(size=len(full))),
        _joint_state(full, rng.normal(size=len(full)), sec=13),  # same names: the fast path
        _joint_state(full, rng.normal(size=len(full)), frame_id="w"),  # another frame_id shifts every offset
        _joint_state(full[:5], rng.normal(size=5), frame_id="w"),  # a partial update
        _joint_state(full[1:6], rng.normal(size=5), frame_id="w"),  # same count and lengths, other names
        _joint_state(["Hips_tx", "Hips_ty"], [np.nan, np.inf]),  # non-finite values pass through (accept rejects)
        _joint_state(["Hips_tx", "Hips_ty", "Hips_tz"], [0.5, 0.25]),  # lengths differ (accept rejects)
        _joint_state(["Hips_tx", "Hips_ty", "Hips_tz"], [0.5, 0.25, 0.125]),  # after it: same names, full again
        _joint_state(["Hüfte", "Hips_ty"], [1.0, 2.0], frame_id="wörld"),  # multi-byte UTF-8 lengths
        _joint_state([], []),
        _joint_state(full, rng.normal(size=len(full)), velocity=[1.0] * len(full), nanosec=999_999_999),
    ]
    for msg in cases:
        raw = serialize_message(msg)
        for _ in range(2):  # the second read of the same bytes goes through the cached layout
            names, positions, stamp_ns = reader.read(raw)
            assert names == list(msg.name)
            assert np.array_equal(positions, np.asarray(msg.position), equal_nan=True)
            assert stamp_ns == msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


@pytest.mark.parametrize("frame_id, names", [("world", list(JOINT_NAMES)), ("wörld", ["Hüfte", "a", "bc"]),
                                              ("", ["x"])])
def test_serialized_joint_state_is_what_the_serializer_makes_and_reads_back(frame_id, names):
    """The crowd driver's JointState bytes are rclpy's serialization of the same message, frame after frame, and
    the node's reader takes them on its fast path."""
    writer, reader = SerializedJointState(frame_id, names), JointStateReader()
    rng = np.random.default_rng(1)
    for sec, nanosec in ((0, 0), (12, 345), (1_700_000_000, 999_999_999)):
        positions = rng.normal(size=len(names))
        raw = writer.set(positions, sec * 1_000_000_000 + nanosec)
        assert len(raw) == len(serialize_message(_joint_state(names, positions, frame_id, sec, nanosec)))
        msg = deserialize_message(raw, JointState)  # bytes compare only up to CDR padding, which rclpy leaves unset
        assert (msg.header.frame_id, list(msg.name), msg.header.stamp.sec, msg.header.stamp.nanosec) == (
            frame_id, names, sec, nanosec)
        assert np.array_equal(msg.position, positions) and not len(msg.velocity) and not len(msg.effort)
        read_names, read_positions, stamp_ns = reader.read(raw)
        assert read_names == names and np.array_equal(read_positions, positions)
        assert stamp_ns == sec * 1_000_000_000 + nanosec


def test_serialized_bones_carry_the_skinning_transforms_and_reproduce_the_body_frame():
    """A body frame's bone transforms through PoseArray bytes (SerializedBones, quaternions written by its kernel)
    and back skin the binding of make_skin to the frame the node published (LBS, float32), within 1e-5 m; the
    quaternions are unit with w >= 0, also for rotations near pi (Shepperd's pivots)."""
    from geometry_msgs.msg import PoseArray

    from agentdress_ros.body import AnnyBody
    from agentdress_ros.body.kinematics import linear_blend_skinning
    from agentdress_ros.motion.rotations import rotvec_to_matrix
    from agentdress_ros.models.garment_models import BodyModel, skin_binding
    from agentdress_ros.ros.messages import SerializedBones, bones_to_transforms, make_skin, skin_to_arrays

    body = AnnyBody()
    model = BodyModel(body)
    rng = np.random.default_rng(3)
    bones = SerializedBones("agent", body.n_bones)
    rest, indices, weights = skin_to_arrays(make_skin(*skin_binding(model)))
    assert rest.shape == (13380, 3) and indices.shape == weights.shape == (13380, 4)
    for stamp_ns in (1, 1_796_000_000_123_456_789):
        frame = model.synthesize(rng.normal(0.0, 0.8, (body.n_bones, 3)), rng.normal(0.0, 1.0, 3)).copy()
        msg = deserialize_message(bones.set(model.transforms, stamp_ns), PoseArray)
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(stamp_ns, 1_000_000_000)
        assert msg.header.frame_id == "agent"
        skinned = linear_blend_skinning(rest, indices.astype(np.int64), weights, bones_to_transforms(msg),
                                        np.empty_like(rest))
        assert np.abs(skinned - frame).max() < 1e-5
    # rotations of every kind, pi included: each quaternion is the rotation's, unit, with w >= 0
    axes = rng.normal(size=(31, 3))
    angles = np.concatenate([[np.pi, np.pi - 1e-7, 0.0, 1e-8], rng.uniform(0, np.pi, 27)])
    transforms = np.zeros((31, 3, 4))
    transforms[:, :, :3] = rotvec_to_matrix(axes / np.linalg.norm(axes, axis=1, keepdims=True) * angles[:, None])
    transforms[:, :, 3] = rng.normal(size=(31, 3))
    msg = deserialize_message(SerializedBones("f", 31).set(transforms, 0), PoseArray)
    q = np.array([(p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w) for p in msg.poses])
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12) and (q[:, 3] >= 0).all()
    assert np.abs(bones_to_transforms(msg) - transforms).max() < 1e-6


def test_skin_message_layout_is_checked():
    from std_msgs.msg import Float32MultiArray

    from agentdress_ros.ros.messages import make_skin, skin_to_arrays

    msg = make_skin(np.zeros((5, 3)), np.zeros((5, 4), int), np.ones((5, 4)) / 4)
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="holds 54 values, its layout says 55"):
        skin_to_arrays(msg)
    with pytest.raises(ValueError, match="not a skin message"):
        skin_to_arrays(Float32MultiArray(data=[1.0, 2.0]))
