"""Message packing with numpy (the PyPI wheels ship no sensor_msgs_py): PointCloud2, shape_msgs/Mesh, Marker.

These import only message packages (no rclpy node machinery), so they are used by the node, the viewer, the bench
and the tests alike.
"""
from __future__ import annotations

import array
import struct
import sys

import numpy as np

__all__ = [
    "JointStateReader",
    "SerializedCloud",
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
        # Where the position count sits, walked as CDR lays out the strings (length incl. the NUL, then bytes).
        offset = 12 + 4 + len(msg.header.frame_id.encode()) + 1
        offset = _align(offset, 4) + 4
        for name in names:
            offset = _align(offset, 4) + 4 + len(name.encode()) + 1
        offset = _align(offset, 4)
        start = _align(offset + 4, 8)
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
    count = msg.width * msg.height
    dtype = np.dtype({"names": list("xyz"), "formats": [">f4" if msg.is_bigendian else "<f4"] * 3,
                      "offsets": [offsets[a] for a in "xyz"], "itemsize": msg.point_step})
    raw = np.frombuffer(bytes(msg.data), dtype=dtype, count=count)
    return np.stack([raw["x"], raw["y"], raw["z"]], axis=1).astype(np.float32)


def make_mesh(vertices: np.ndarray, faces: np.ndarray):
    """shape_msgs/Mesh of vertices (V, 3) and faces (F, 3). Built once per garment (topology topic), ~50 ms at 12k."""
    from geometry_msgs.msg import Point
    from shape_msgs.msg import Mesh, MeshTriangle

    mesh = Mesh()
    mesh.vertices = [Point(x=x, y=y, z=z) for x, y, z in np.asarray(vertices, np.float64).tolist()]
    mesh.triangles = [MeshTriangle(vertex_indices=tri) for tri in np.asarray(faces, dtype=np.uint32)]
    return mesh


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
