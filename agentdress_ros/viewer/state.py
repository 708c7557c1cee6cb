"""What a display client is shown: every mesh (agent, garment) with its topology and latest vertices, and the
nodes' status; thread-safe (the ROS thread writes, the server's event loop reads) and ROS-free.

Binary messages for the client (web/src/frames.js reads them): uint32 little-endian header length H, H bytes of
JSON padded with spaces to a multiple of 4, then the payload.
  mesh:  {"type": "mesh", "key", "agent", "garment", "color", "faces": F, "vertices": V}; F*3 uint32, V*3 float32
         a skinned mesh (the body: its skin and bones topics) adds "skin": K, "bones": B and, after the vertices
         (its rest), V*K uint16 bone indices (zero-padded to 4 bytes) and V*K float32 weights
  frame: {"type": "frame", "seq", "meshes": [{"key", "vertices": V | "bones": B, "offset", "stamp"}]} (stamp: the
         frame's ROS stamp in seconds, or null; an agent's meshes at the newest stamp all of them have reached);
         at each offset the mesh's V*3 float32 vertices, or a skinned mesh's B*12 float32 bone transforms (3x4,
         row-major): the client skins the rest itself, so a 13,380-vertex body costs 1.5 kB a frame, not 160 kB
"""
from __future__ import annotations

import json
import threading

import numpy as np

__all__ = ["COLORS", "DisplayScene", "mesh_key", "pack"]

COLORS = {"body": [0.85, 0.66, 0.55], "tshirt": [0.2, 0.42, 0.85], "longsleeve": [0.2, 0.65, 0.45],
          "trousers": [0.3, 0.3, 0.38]}
OTHER_COLOR = [0.6, 0.6, 0.6]


def mesh_key(agent: str, garment: str) -> str:
    return f"{agent}/{garment}"


def pack(header: dict, *blobs: bytes) -> bytes:
    """One binary message: length-prefixed JSON header padded to 4 bytes, then the blobs."""
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # keeps the float32 payload 4-byte aligned for the browser's Float32Array
    return len(text).to_bytes(4, "little") + text + b"".join(blobs)


#: Frames kept per mesh, so that the meshes of one agent can be sent at a stamp all of them have reached.
IN_STEP_FRAMES = 4


class _Mesh:
    __slots__ = ("agent", "garment", "faces", "vertices", "frames", "generation", "stamp", "bones", "recent")

    def __init__(self, agent, garment, faces, vertices, generation):
        self.agent, self.garment, self.faces, self.vertices = agent, garment, faces, vertices
        self.frames, self.generation, self.stamp = 0, generation, None
        self.bones = None  # (B, 12) float32 of the last frame of a skinned mesh
        self.recent: list[tuple] = []  # (stamp, frame number, vertices or bones) of the last few frames

    def add_frame(self, data: np.ndarray, stamp) -> None:
        self.stamp = stamp
        self.frames += 1
        self.recent = ([] if stamp is None else self.recent[-(IN_STEP_FRAMES - 1):] + [(stamp, self.frames, data)])


class DisplayScene:
    """Meshes keyed "agent/garment". `set_mesh` (topology + vertices) and `set_vertices` (a frame) come from the
    ROS side; listeners (callables, e.g. an event loop's wake-up) are called after every change."""

    def __init__(self):
        self._lock = threading.Lock()
        self._meshes: dict[str, _Mesh] = {}
        self._status: dict[str, tuple[int, dict]] = {}  # source -> (version, status)
        self._generation = 0
        self._skins: dict[str, tuple] = {}  # key -> (rest (V, 3) f4, indices (V, K) u2, weights (V, K) f4)
        self.seq = 0
        self._listeners: list = []

    # ---- writers (any thread) ------------------------------------------------------------------------------------
    def add_listener(self, callback):
        with self._lock:
            self._listeners.append(callback)

    def remove_listener(self, callback):
        with self._lock:
            if callback in self._listeners:
                self._listeners.remove(callback)

    def _changed(self):
        for callback in list(self._listeners):
            callback()

    def set_mesh(self, agent: str, garment: str, vertices, faces):
        """A (new) topology faces (F, 3) with its vertices (V, 3) for mesh agent/garment."""
        faces = np.ascontiguousarray(faces, dtype="<u4")
        vertices = np.ascontiguousarray(vertices, dtype="<f4").reshape(-1, 3)
        with self._lock:
            self._generation += 1
            self._meshes[mesh_key(agent, garment)] = _Mesh(agent, garment, faces, vertices, self._generation)
            self.seq += 1
        self._changed()

    def set_skin(self, agent: str, garment: str, rest, indices, weights):
        """The binding of a skinned mesh: rest (V, 3), bone indices (V, K), weights (V, K). From then on its frames
        are bone transforms (set_bones); a client gets the mesh again with it, and with it the last bone transforms
        (a new body shape rebinds the body once a second in the demo: without a pose, the client drew it in its
        rest pose until the next frame, feet on the floor under posed trousers)."""
        rest = np.ascontiguousarray(rest, dtype="<f4").reshape(-1, 3)
        indices = np.ascontiguousarray(indices, dtype="<u2").reshape(len(rest), -1)
        weights = np.ascontiguousarray(weights, dtype="<f4").reshape(indices.shape)
        key = mesh_key(agent, garment)
        with self._lock:
            self._skins[key] = (rest, indices, weights)
            mesh = self._meshes.get(key)
            if mesh is not None:
                self._generation += 1
                mesh.generation = self._generation
                if mesh.bones is not None and int(indices.max()) >= len(mesh.bones):
                    mesh.bones, mesh.recent = None, []  # another skeleton: its pose comes with its next frame
            self.seq += 1
        self._changed()

    def set_bones(self, agent: str, garment: str, transforms, stamp: float | None = None) -> bool:
        """A frame of a skinned mesh: its bone transforms (B, 3, 4); False while the mesh or its skin is missing."""
        bones = np.ascontiguousarray(transforms, dtype="<f4").reshape(-1, 12)
        key = mesh_key(agent, garment)
        with self._lock:
            mesh = self._meshes.get(key)
            skin = self._skins.get(key)
            if mesh is None or skin is None or len(skin[0]) != len(mesh.vertices) or int(skin[1].max()) >= len(bones):
                return False
            mesh.bones = bones
            mesh.add_frame(bones, stamp)
            self.seq += 1
        self._changed()
        return True

    def set_vertices(self, agent: str, garment: str, vertices, stamp: float | None = None) -> bool:
        """A frame (V, 3) of a known mesh; held back (False) when it does not fit the topology (a garment rebuilt
        at another vertex count whose new mesh has not arrived yet), or for a skinned mesh (its frames are bones)."""
        vertices = np.ascontiguousarray(vertices, dtype="<f4").reshape(-1, 3)
        with self._lock:
            key = mesh_key(agent, garment)
            mesh = self._meshes.get(key)
            if mesh is None or len(vertices) != len(mesh.vertices) or key in self._skins:
                return False
            mesh.vertices = vertices
            mesh.add_frame(vertices, stamp)
            self.seq += 1
        self._changed()
        return True

    def remove_agent(self, agent: str):
        with self._lock:
            for key in [k for k, m in self._meshes.items() if m.agent == agent]:
                del self._meshes[key]
                self._skins.pop(key, None)
            self.seq += 1
        self._changed()

    def set_status(self, source: str, status: dict):
        with self._lock:
            version = self._status.get(source, (0, None))[0] + 1
            self._status[source] = (version, status)
        self._changed()

    # ---- readers -------------------------------------------------------------------------------------------------
    def summary(self) -> dict:
        """{key: {"agent", "garment", "vertices", "faces", "frames", "stamp", "skinned"}} (tests, status lines)."""
        with self._lock:
            return {k: {"agent": m.agent, "garment": m.garment, "vertices": len(m.vertices), "faces": len(m.faces),
                        "frames": m.frames, "stamp": m.stamp, "skinned": k in self._skins}
                    for k, m in sorted(self._meshes.items())}

    def _in_step(self) -> dict:
        """{key: (stamp, frame number, data)}: for each agent whose stamped meshes (its garments, its body's bones:
        separate topics that reach this process one by one) share a stamp among their last IN_STEP_FRAMES frames,
        each one's frame at the newest such stamp. A client shown each mesh's newest frame drew the trousers of one
        node tick under the shirt of the tick before, which let them through at the waist. Agents without a shared
        stamp (a mesh that stopped, or unstamped frames) get each mesh's newest frame."""
        by_agent: dict[str, list] = {}
        for key, mesh in self._meshes.items():
            if mesh.recent:
                by_agent.setdefault(mesh.agent, []).append((key, mesh))
        chosen = {}
        for members in by_agent.values():
            if len(members) < 2:
                continue
            shared = set.intersection(*({entry[0] for entry in mesh.recent} for _, mesh in members))
            if shared:
                stamp = max(shared)
                for key, mesh in members:
                    chosen[key] = next(entry for entry in mesh.recent if entry[0] == stamp)
        return chosen

    def updates(self, seen: dict) -> tuple[list[bytes], list[str], bytes | None, list[dict]]:
        """What a client that has seen `seen` still lacks: (mesh messages, removed keys, one frame message or None,
        status messages). `seen` (the client's own dict) is updated in place."""
        topology = seen.setdefault("topology", {})
        frames = seen.setdefault("frames", {})
        status_seen = seen.setdefault("status", {})
        meshes, frame_parts, frame_meshes, statuses = [], [], [], []
        with self._lock:
            in_step = self._in_step()
            removed = [k for k in topology if k not in self._meshes]
            for key in removed:
                del topology[key]
                frames.pop(key, None)
            offset = 0
            for key, mesh in self._meshes.items():
                skin = self._skins.get(key)
                if skin is not None and len(skin[0]) != len(mesh.vertices):
                    skin = None  # a skin of another topology: the mesh's new skin is on the way
                if topology.get(key) != mesh.generation:
                    topology[key], frames[key] = mesh.generation, mesh.frames
                    header = {"type": "mesh", "key": key, "agent": mesh.agent, "garment": mesh.garment,
                              "color": COLORS.get(mesh.garment, OTHER_COLOR), "faces": len(mesh.faces),
                              "vertices": len(mesh.vertices)}
                    blobs = [mesh.faces.tobytes(), mesh.vertices.tobytes()]
                    if skin is not None:
                        rest, indices, weights = skin
                        header.update(skin=indices.shape[1], bones=int(indices.max()) + 1)
                        blobs = [mesh.faces.tobytes(), rest.tobytes(), indices.tobytes(),
                                 b"\0" * (-indices.nbytes % 4), weights.tobytes()]
                    meshes.append(pack(header, *blobs))
                    if skin is not None and mesh.bones is not None:
                        frames[key] = -1  # its last pose follows in this update's frame
                # a mesh's recent frames are bones while it has a skin: not while that skin awaits its new topology
                entry = in_step.get(key) if (skin is not None) == (key in self._skins) else None
                newest = (mesh.stamp, mesh.frames, mesh.bones if skin is not None else mesh.vertices)
                stamp, number, data = entry or newest
                if frames.get(key) != number and (skin is None or mesh.bones is not None):
                    frames[key] = number
                    blob = data.tobytes()
                    frame_meshes.append({"key": key, "bones" if skin is not None else "vertices": len(data),
                                         "offset": offset, "stamp": stamp})
                    frame_parts.append(blob)
                    offset += len(blob)
            for source, (version, status) in self._status.items():
                if status_seen.get(source) != version:
                    status_seen[source] = version
                    statuses.append({"type": "status", "source": source, "status": status})
            seq = self.seq
        frame = pack({"type": "frame", "seq": seq, "meshes": frame_meshes}, *frame_parts) if frame_meshes else None
        return meshes, removed, frame, statuses
