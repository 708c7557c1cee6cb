"""Message packing with numpy (the PyPI wheels ship no sensor_msgs_py): PointCloud2, shape_msgs/Mesh, Marker, and a
skinned mesh's skin (Float32MultiArray) and bone transforms (PoseArray).

These import only message packages (no rclpy node machinery), so they are used by the node, the viewer, the bench
and the tests alike.
"""
from __future__ import annotations

import array
import struct
import sys

import numba
import numpy as np

__all__ = [
    "JointStateReader",
    "SerializedBones",
    "SerializedCloud",
    "bones_to_transforms",
    "serialized_bones_to_transforms",
    "serialized_cloud_to_vertices",
    "make_skin",
    "skin_to_arrays",
    "cloud_to_vertices",
    "make_marker",
    "make_mesh",
    "make_point_cloud",
    "mesh_to_arrays",
    "set_cloud_vertices",
    "stamp_from_ns",
]

_IS_BIG_ENDIAN = sys.byteorder == "big"


def stamp_from_ns(stamp_ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def make_point_cloud(frame_id: str = "agent"):
    """An empty PointCloud2 with fields x, y, z float32 (point_step 12, unordered: height 1)."""
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = frame_id
    msg.height = 1
    msg.fields = [PointField(name=axis, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, axis in enumerate("xyz")]
    msg.is_bigendian = _IS_BIG_ENDIAN
    msg.point_step = 12
    msg.is_dense = True
    return msg


def set_cloud_vertices(msg, vertices: np.ndarray, stamp=None, frame_id: str | None = None):
    """Fill `msg` (from make_point_cloud) with vertices (V, 3) (cast to float32); ~0.1 ms for 12k vertices.

    The data goes in as array.array('B') (the field's native type), which rclpy keeps without a per-byte check.
    """
    data = np.ascontiguousarray(vertices, dtype=np.float32)
    msg.width = len(data)
    msg.row_step = 12 * len(data)
    msg.data = array.array("B", data.tobytes())
    if stamp is not None:
        msg.header.stamp = stamp
    if frame_id is not None:
        msg.header.frame_id = frame_id
    return msg


class SerializedCloud:
    """A PointCloud2 of a fixed frame_id and vertex count kept serialized (CDR): each frame writes the stamp and
    the vertices into the bytes in place, and `Publisher.publish` takes the bytes as they are. A quarter of the cost
    of publishing the message object, whose fields rclpy converts on every publish (a crowd publishes thousands
    of clouds a second). The bytes are what `serialize_message` makes of the same cloud."""

    def __init__(self, frame_id: str, n_vertices: int):
        from rclpy.serialization import serialize_message

        self.frame_id, self.n_vertices = frame_id, int(n_vertices)
        msg = set_cloud_vertices(make_point_cloud(frame_id), np.zeros((self.n_vertices, 3), dtype=np.float32))
        self._buffer = bytearray(serialize_message(msg))
        # Layout (CDR, little or big endian per the 4-byte encapsulation header): stamp sec and nanosec right
        # after that header; the data sequence (length, bytes) just before the final is_dense byte.
        self._endian = "<" if self._buffer[1] == 1 else ">"
        size = 12 * self.n_vertices
        self._data_offset = len(self._buffer) - 1 - size
        length = int.from_bytes(self._buffer[self._data_offset - 4:self._data_offset],
                                "little" if self._endian == "<" else "big")
        if length != size or self._buffer[-1] != 1:
            raise RuntimeError(f"unexpected PointCloud2 serialization: data length {length}, expected {size}")
        self._vertices = np.frombuffer(self._buffer, dtype=self._endian + "f4", count=3 * self.n_vertices,
                                       offset=self._data_offset).reshape(self.n_vertices, 3)
        self.data = bytes(self._buffer)
        self.stamp_ns = 0

    def vertices(self) -> np.ndarray:
        """(V, 3) float32 copy of the last frame written."""
        return self._vertices.astype(np.float32)

    def set(self, vertices: np.ndarray, stamp_ns: int) -> bytes:
        """Write vertices (V, 3) and the stamp; returns the serialized cloud (also kept as `data`)."""
        np.copyto(self._vertices, vertices, casting="same_kind")
        struct.pack_into(self._endian + "iI", self._buffer, 4, int(stamp_ns // 1_000_000_000),
                         int(stamp_ns % 1_000_000_000))
        self.data = bytes(self._buffer)
        self.stamp_ns = int(stamp_ns)
        return self.data


def _align(offset: int, size: int) -> int:
    """CDR alignment: offsets count from the end of the 4-byte encapsulation header."""
    return 4 + -(-(offset - 4) // size) * size


def _joint_state_positions(frame_id: str, names) -> tuple[int, int]:
    """(offset of the position count, offset of the first position) in a serialized JointState, walked as CDR lays
    out its strings (length including the NUL, then the bytes)."""
    offset = 12 + 4 + len(frame_id.encode()) + 1
    offset = _align(offset, 4) + 4
    for name in names:
        offset = _align(offset, 4) + 4 + len(name.encode()) + 1
    offset = _align(offset, 4)
    return offset, _align(offset + 4, 8)


class SerializedJointState:
    """JointStates of a fixed frame_id and joint names (no velocities or efforts) kept serialized (CDR): each
    message writes its stamp and positions into the bytes, which `Publisher.publish` takes as they are. The
    crowd driver sends thousands a second, and rclpy converts a message object's 96 names on every publish. The
    bytes are what `serialize_message` makes of the same message, up to CDR padding (which rclpy leaves unset)."""

    def __init__(self, frame_id: str, names):
        from rclpy.serialization import serialize_message
        from sensor_msgs.msg import JointState

        msg = JointState()
        msg.header.frame_id, msg.name, msg.position = frame_id, list(names), [0.0] * len(names)
        self._buffer = bytearray(serialize_message(msg))
        self._endian = "<" if self._buffer[1] == 1 else ">"
        count_offset, start = _joint_state_positions(frame_id, msg.name)
        count = struct.unpack_from(self._endian + "I", self._buffer, count_offset)[0]
        if count != len(names) or len(self._buffer) < start + 8 * count:
            raise RuntimeError(f"unexpected JointState serialization: {count} positions at {start}")
        self._positions = np.frombuffer(self._buffer, dtype=self._endian + "f8", count=count, offset=start)

    def set(self, positions, stamp_ns: int) -> bytes:
        """The serialized message with positions (N,) and the stamp (ns)."""
        np.copyto(self._positions, positions, casting="same_kind")
        struct.pack_into(self._endian + "iI", self._buffer, 4, int(stamp_ns // 1_000_000_000),
                         int(stamp_ns % 1_000_000_000))
        return bytes(self._buffer)


class JointStateReader:
    """Names, positions and stamp of serialized JointStates (CDR bytes, as a raw subscription hands them over)
    from one sender, parsed without building the message: a sender repeats its frame_id and joint names, so once
    one message was parsed in full, the next whose bytes up to the positions are the same is read with two slices
    (a few microseconds against ~27 for `deserialize_message` of 96 joints). Anything else is parsed in full."""

    def __init__(self):
        self._prefix = b""  # bytes from frame_id to the end of the names of the last fully parsed message
        self._names: list = []
        self._count_offset = 0  # offset of the position count in those messages

    def read(self, raw: bytes) -> tuple[list, np.ndarray, int]:
        """(names (list of str), positions (N,) float64, stamp ns) of serialized JointState `raw`."""
        endian = "<" if raw[1] == 1 else ">"
        sec, nanosec = struct.unpack_from(endian + "iI", raw, 4)
        stamp_ns = sec * 1_000_000_000 + nanosec
        end = self._count_offset
        if end and raw[12:end] == self._prefix and len(raw) >= end + 4:
            count = struct.unpack_from(endian + "I", raw, end)[0]
            start = _align(end + 4, 8)
            if count == len(self._names) and len(raw) >= start + 8 * count:
                return self._names, np.frombuffer(raw, dtype=endian + "f8", count=count, offset=start), stamp_ns
        return self._parse(raw, endian, stamp_ns)

    def _parse(self, raw: bytes, endian: str, stamp_ns: int):
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState

        msg = deserialize_message(raw, JointState)
        names, positions = list(msg.name), np.asarray(msg.position, dtype=np.float64)
        offset, start = _joint_state_positions(msg.header.frame_id, names)
        known = len(raw) >= start + 8 * len(positions) and len(names) == len(positions) and np.array_equal(
            np.frombuffer(raw, dtype=endian + "f8", count=len(positions), offset=start).view(np.uint64),
            positions.view(np.uint64))
        if known:  # the walk agrees with the parser: later messages with these bytes take the fast path
            self._prefix, self._names, self._count_offset = bytes(raw[12:offset]), names, offset
        return names, positions, stamp_ns


def cloud_to_vertices(msg) -> np.ndarray:
    """A PointCloud2 with float32 x, y, z at any offsets -> (V, 3) float32 (a copy)."""
    offsets = {f.name: f.offset for f in msg.fields}
    missing = [axis for axis in "xyz" if axis not in offsets]
    if missing:
        raise ValueError(f"PointCloud2 has no field(s) {missing}")
    return _xyz_points(bytes(msg.data), 0, msg.width * msg.height, offsets, msg.point_step, msg.is_bigendian)


def _xyz_points(data: bytes, start: int, count: int, offsets: dict, point_step: int, big_endian) -> np.ndarray:
    """(count, 3) float32 copy of the x, y, z float32 fields at `offsets` of `count` points from byte `start`."""
    byte_order = ">" if big_endian else "<"
    if point_step == 12 and [offsets[a] for a in "xyz"] == [0, 4, 8]:  # packed x, y, z: one view
        return np.frombuffer(data, dtype=byte_order + "f4", count=3 * count, offset=start).reshape(count, 3) \
            .astype(np.float32)
    dtype = np.dtype({"names": list("xyz"), "formats": [byte_order + "f4"] * 3,
                      "offsets": [offsets[a] for a in "xyz"], "itemsize": point_step})
    points = np.frombuffer(data, dtype=dtype, count=count, offset=start)
    return np.stack([points["x"], points["y"], points["z"]], axis=1).astype(np.float32)


def make_mesh(vertices: np.ndarray, faces: np.ndarray):
    """shape_msgs/Mesh of vertices (V, 3) and faces (F, 3). Built once per garment (topology topic), ~50 ms at 12k."""
    from geometry_msgs.msg import Point
    from shape_msgs.msg import Mesh, MeshTriangle

    mesh = Mesh()
    mesh.vertices = [Point(x=x, y=y, z=z) for x, y, z in np.asarray(vertices, np.float64).tolist()]
    mesh.triangles = [MeshTriangle(vertex_indices=tri) for tri in np.asarray(faces, dtype=np.uint32)]
    return mesh


def make_skin(rest: np.ndarray, skin_indices: np.ndarray, skin_weights: np.ndarray):
    """std_msgs/Float32MultiArray of a skinned mesh's binding: rest vertices (V, 3), then bone indices (V, K) and
    weights (V, K), row-major; layout dims "vertices" (V) and "rest3_indices_weights" (3 + 2K). With a `bones` frame
    (bones_to_transforms) a client skins vertex v as sum_k weight[v, k] * T[index[v, k]] @ (rest[v], 1), which is
    exactly the published cloud: one small message per frame instead of the cloud."""
    from std_msgs.msg import Float32MultiArray, MultiArrayDimension

    rest = np.asarray(rest, dtype=np.float32).reshape(-1, 3)
    indices = np.asarray(skin_indices).reshape(len(rest), -1)
    weights = np.asarray(skin_weights, dtype=np.float32).reshape(len(rest), -1)
    table = np.concatenate([rest, indices.astype(np.float32), weights], axis=1)
    msg = Float32MultiArray()
    msg.layout.dim = [MultiArrayDimension(label="vertices", size=len(table), stride=table.size),
                      MultiArrayDimension(label="rest3_indices_weights", size=table.shape[1], stride=table.shape[1])]
    msg.data = array.array("f", table.tobytes())
    return msg


def skin_to_arrays(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """make_skin's message -> rest (V, 3) float32, bone indices (V, K) uint16, weights (V, K) float32; ValueError for
    another layout."""
    dims = msg.layout.dim
    if len(dims) != 2 or dims[1].label != "rest3_indices_weights" or (dims[1].size - 3) % 2 or dims[1].size < 5:
        raise ValueError("not a skin message: expected dims vertices x rest3_indices_weights (3 + 2K)")
    table = np.asarray(msg.data, dtype=np.float32)
    if table.size != dims[0].size * dims[1].size:
        raise ValueError(f"skin message holds {table.size} values, its layout says {dims[0].size * dims[1].size}")
    table = table.reshape(dims[0].size, dims[1].size)
    k = (dims[1].size - 3) // 2
    return table[:, :3].copy(), table[:, 3:3 + k].astype(np.uint16), table[:, 3 + k:].copy()


@numba.njit(cache=True)
def _write_poses(transforms, poses):
    """transforms (B, 3, 4) -> poses (B, 7): translation, then the rotation's unit quaternion (x, y, z, w), w >= 0
    (Shepperd: pivot on the largest squared component)."""
    for b in range(transforms.shape[0]):
        m = transforms[b]
        poses[b, 0], poses[b, 1], poses[b, 2] = m[0, 3], m[1, 3], m[2, 3]
        trace = m[0, 0] + m[1, 1] + m[2, 2]
        if trace >= m[0, 0] and trace >= m[1, 1] and trace >= m[2, 2]:
            w = 0.5 * np.sqrt(max(1.0 + trace, 0.0))
            f = 0.25 / w
            x, y, z = (m[2, 1] - m[1, 2]) * f, (m[0, 2] - m[2, 0]) * f, (m[1, 0] - m[0, 1]) * f
        elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
            x = 0.5 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            f = 0.25 / x
            w, y, z = (m[2, 1] - m[1, 2]) * f, (m[0, 1] + m[1, 0]) * f, (m[0, 2] + m[2, 0]) * f
        elif m[1, 1] >= m[2, 2]:
            y = 0.5 * np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
            f = 0.25 / y
            w, x, z = (m[0, 2] - m[2, 0]) * f, (m[0, 1] + m[1, 0]) * f, (m[1, 2] + m[2, 1]) * f
        else:
            z = 0.5 * np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
            f = 0.25 / z
            w, x, y = (m[1, 0] - m[0, 1]) * f, (m[0, 2] + m[2, 0]) * f, (m[1, 2] + m[2, 1]) * f
        norm = np.sqrt(x * x + y * y + z * z + w * w)
        sign = 1.0 if w >= 0.0 else -1.0
        poses[b, 3], poses[b, 4], poses[b, 5], poses[b, 6] = (sign * x / norm, sign * y / norm, sign * z / norm,
                                                              sign * w / norm)


class SerializedBones:
    """geometry_msgs/PoseArray of a skeleton's skinning transforms (one pose per bone: the rigid map of the bone's
    rest frame to its posed frame), kept serialized like SerializedCloud: each frame writes the stamp and the poses
    into the bytes (the quaternions from the transforms' rotation matrices)."""

    def __init__(self, frame_id: str, n_bones: int):
        from geometry_msgs.msg import Pose, PoseArray
        from rclpy.serialization import serialize_message

        self.frame_id, self.n_bones = frame_id, int(n_bones)
        msg = PoseArray()
        msg.header.frame_id = frame_id
        msg.poses = [Pose() for _ in range(self.n_bones)]
        self._buffer = bytearray(serialize_message(msg))
        self._endian = "<" if self._buffer[1] == 1 else ">"
        offset = len(self._buffer) - 56 * self.n_bones  # the poses: 7 float64 each (x y z, qx qy qz qw), at the end
        self._poses = np.frombuffer(self._buffer, dtype=self._endian + "f8", count=7 * self.n_bones,
                                    offset=offset).reshape(self.n_bones, 7)
        if not np.array_equal(self._poses, np.tile([0, 0, 0, 0, 0, 0, 1.0], (self.n_bones, 1))):
            raise RuntimeError("unexpected PoseArray serialization")
        self.data = bytes(self._buffer)

    def set(self, transforms: np.ndarray, stamp_ns: int) -> bytes:
        """Write transforms (B, 3, 4) and the stamp; returns the serialized PoseArray."""
        _write_poses(np.ascontiguousarray(transforms, dtype=np.float64), self._poses)
        struct.pack_into(self._endian + "iI", self._buffer, 4, int(stamp_ns // 1_000_000_000),
                         int(stamp_ns % 1_000_000_000))
        self.data = bytes(self._buffer)
        return self.data


def _read_string_end(data: bytes, endian: str, offset: int) -> int:
    """Offset just past a CDR string (uint32 length incl. the NUL, then the bytes) aligned at `offset`."""
    offset = _align(offset, 4)
    (length,) = struct.unpack_from(endian + "I", data, offset)
    return offset + 4 + length


def serialized_cloud_to_vertices(data: bytes) -> tuple[np.ndarray, float]:
    """A serialized sensor_msgs/PointCloud2 (a raw subscription's bytes) with float32 x, y, z at any offsets ->
    (vertices (V, 3) float32, stamp in seconds), read with numpy from the CDR layout: no message object is built
    (a display bridge takes thousands of clouds a second). ValueError when the bytes are not such a cloud."""
    data = bytes(data)
    if len(data) < 24 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError("not a CDR-serialized message")
    endian = "<" if data[1] == 1 else ">"
    try:
        sec, nanosec = struct.unpack_from(endian + "iI", data, 4)
        offset = _read_string_end(data, endian, 12)  # header.frame_id
        height, width, n_fields = struct.unpack_from(endian + "III", data, _align(offset, 4))
        offset = _align(offset, 4) + 12
        offsets, types = {}, {}
        for _ in range(n_fields):
            start = _align(offset, 4)
            end = _read_string_end(data, endian, start)
            name = data[start + 4:end - 1].decode()
            offset = _align(end, 4)
            field_offset, = struct.unpack_from(endian + "I", data, offset)
            types[name], offsets[name] = data[offset + 4], field_offset
            offset = _align(offset + 5, 4) + 4  # datatype (uint8), then count (uint32)
        is_bigendian = data[offset]
        point_step, _, size = struct.unpack_from(endian + "III", data, _align(offset + 1, 4))
        data_at = _align(offset + 1, 4) + 12
    except (struct.error, IndexError, UnicodeDecodeError) as error:
        raise ValueError(f"truncated or malformed PointCloud2 ({error})") from None
    missing = [axis for axis in "xyz" if types.get(axis) != 7]  # 7: FLOAT32
    if missing:
        raise ValueError(f"PointCloud2 has no float32 field(s) {missing}")
    count = height * width
    if max(offsets[a] for a in "xyz") + 4 > point_step:
        raise ValueError(f"PointCloud2 field offsets {offsets} exceed its point step {point_step}")
    if size < count * point_step or data_at + size > len(data):
        raise ValueError(f"PointCloud2 of {count} points does not fit its {size} data bytes")
    return _xyz_points(data, data_at, count, offsets, point_step, is_bigendian), sec + 1e-9 * nanosec


def _poses_to_transforms(poses: np.ndarray) -> np.ndarray:
    out = np.empty((len(poses), 3, 4), dtype=np.float32)
    from ..motion.rotations import quaternion_to_matrix

    out[:, :, :3] = quaternion_to_matrix(poses[:, 3:])
    out[:, :, 3] = poses[:, :3]
    return out


def serialized_bones_to_transforms(data: bytes) -> tuple[np.ndarray, float]:
    """A serialized geometry_msgs/PoseArray (a raw subscription's bytes) -> (transforms (B, 3, 4) float32, stamp in
    seconds), read with numpy: a tenth of the cost of rclpy's deserializer building 31 Pose objects (a display
    bridge takes thousands a second). ValueError when the bytes are not such a message."""
    data = bytes(data)
    if len(data) < 20 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError("not a CDR-serialized message")
    endian = "<" if data[1] == 1 else ">"
    sec, nanosec, id_length = struct.unpack_from(endian + "iII", data, 4)
    count_at = _align(16 + id_length, 4)
    (count,) = struct.unpack_from(endian + "I", data, count_at)
    poses_at = _align(count_at + 4, 8)
    if poses_at + 56 * count != len(data):
        raise ValueError(f"PoseArray of {count} poses does not fill its {len(data)} bytes")
    poses = np.frombuffer(data, dtype=endian + "f8", count=7 * count, offset=poses_at).reshape(count, 7)
    return _poses_to_transforms(poses), sec + 1e-9 * nanosec


def bones_to_transforms(msg) -> np.ndarray:
    """geometry_msgs/PoseArray (SerializedBones) -> transforms (B, 3, 4) float32."""
    poses = np.array([(p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y,
                       p.orientation.z, p.orientation.w) for p in msg.poses], dtype=np.float64).reshape(-1, 7)
    return _poses_to_transforms(poses)


def mesh_to_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """shape_msgs/Mesh -> vertices (V, 3) float32, faces (F, 3) int32."""
    vertices = np.array([(p.x, p.y, p.z) for p in mesh.vertices], dtype=np.float32).reshape(-1, 3)
    faces = np.array([list(t.vertex_indices) for t in mesh.triangles], dtype=np.int32).reshape(-1, 3)
    return vertices, faces


def make_marker(vertices: np.ndarray, faces: np.ndarray, namespace: str, marker_id: int, frame_id: str, stamp,
                color=(0.25, 0.45, 0.8, 1.0)):
    """visualization_msgs/Marker TRIANGLE_LIST of the triangles (F, 3) of vertices (V, 3): 3F points.

    Costly in rclpy (one Point object per corner: ~15 ms to build and ~60 ms to publish at 12k vertices), so the
    node builds it off the frame path at marker_rate_hz.
    """
    from geometry_msgs.msg import Point
    from visualization_msgs.msg import Marker

    marker = Marker()
    marker.header.frame_id = frame_id
    marker.header.stamp = stamp
    marker.ns, marker.id = namespace, int(marker_id)
    marker.type, marker.action = Marker.TRIANGLE_LIST, Marker.ADD
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = 1.0
    marker.color.r, marker.color.g, marker.color.b, marker.color.a = (float(c) for c in color)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces).reshape(-1)]
    marker.points = [Point(x=x, y=y, z=z) for x, y, z in corners.tolist()]
    return marker
