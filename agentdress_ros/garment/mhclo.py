"""Import MakeHuman clothes (`.mhclo` + `.obj`) bound to the hm08 base mesh, so they follow any Anny shape.

Each garment vertex is `w1 v_i + w2 v_j + w3 v_k + (dx sx, dy sy, dz sz)` on the hm08 vertices v, in MakeHuman's
own frame (Y up, decimetres), where the scales s = |coordinate difference of two reference vertices| / reference
value adapt the offset to the body's size (MakeHuman's proxy fitting rule). A line with one index pins the vertex.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..body import AnnyBody
from ..body.assets import OBJ_TO_WORLD
from .binding import interpolate_skin_weights, region_weights
from .garment import Garment

WORLD_TO_OBJ = np.linalg.inv(OBJ_TO_WORLD)


@dataclass(frozen=True)
class MhcloBinding:
    """V garment vertices bound to hm08 vertices."""

    refs: np.ndarray  # (V, 3) int32 hm08 vertex ids
    weights: np.ndarray  # (V, 3) float64
    offsets: np.ndarray  # (V, 3) float64 in scale units, MakeHuman axes
    scale_refs: np.ndarray  # (3, 2) int hm08 vertex pairs for the x, y, z scales
    scale_values: np.ndarray  # (3,) reference distances
    delete_verts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (D,) hidden hm08 ids

    def evaluate(self, body_vertices: np.ndarray) -> np.ndarray:
        """Garment vertices (V, 3) in world metres for hm08 body vertices (N, 3) in world metres."""
        obj = body_vertices @ WORLD_TO_OBJ.T
        axis = np.arange(3)
        scales = np.abs(obj[self.scale_refs[:, 0], axis] - obj[self.scale_refs[:, 1], axis]) / self.scale_values
        points = (obj[self.refs] * self.weights[:, :, None]).sum(axis=1) + self.offsets * scales
        return points @ OBJ_TO_WORLD.T


def _read_obj_faces(path: Path) -> tuple[int, np.ndarray]:
    n_vertices, triangles = 0, []
    with open(path) as handle:
        for line in handle:
            if line.startswith("v "):
                n_vertices += 1
            elif line.startswith("f "):
                ids = [int(p.split("/")[0]) - 1 for p in line.split()[1:]]
                triangles += [(ids[0], ids[k], ids[k + 1]) for k in range(1, len(ids) - 1)]  # fan
    return n_vertices, np.asarray(triangles, dtype=np.int32)


def _parse_ranges(parts) -> list[int]:
    """Tokens like ['12', '-', '15', '20'] -> [12, 13, 14, 15, 20]."""
    ids, k = [], 0
    while k < len(parts):
        if k + 2 < len(parts) and parts[k + 1] == "-":
            ids += range(int(parts[k]), int(parts[k + 2]) + 1)
            k += 3
        else:
            ids.append(int(parts[k]))
            k += 1
    return ids


def read_mhclo(path) -> tuple[str, MhcloBinding, np.ndarray]:
    """Parse a `.mhclo` file and its `.obj`: (name, binding, faces (F, 3)). Raises ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such .mhclo file")
    header: dict = {}
    refs, weights, offsets, deleted = [], [], [], []
    section = None
    for number, raw in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if parts[0] == "verts":
            section = "verts"
            continue
        if parts[0].isalpha() or "_" in parts[0]:
            section = None if parts[0] != "delete_verts" else "delete"
            header[parts[0]] = parts[1:]
            continue
        if section == "delete":  # "i", "i - j" (inclusive ranges) of hm08 vertices the garment hides
            try:
                deleted += _parse_ranges(parts)
            except ValueError:
                raise ValueError(f"{path}:{number}: expected vertex ids and 'i - j' ranges, got {raw!r}") from None
            continue
        if section != "verts":
            continue
        try:
            if len(parts) == 1:
                refs.append((int(parts[0]),) * 3)
                weights.append((1.0, 0.0, 0.0))
                offsets.append((0.0, 0.0, 0.0))
            elif len(parts) >= 9:
                refs.append(tuple(int(p) for p in parts[:3]))
                weights.append(tuple(float(p) for p in parts[3:6]))
                offsets.append(tuple(float(p) for p in parts[6:9]))
            else:
                raise ValueError
        except ValueError:
            raise ValueError(f"{path}:{number}: expected 'i j k w1 w2 w3 dx dy dz' or 'i', got {raw!r}") from None
    for key in ("name", "obj_file", "x_scale", "y_scale", "z_scale"):
        if key not in header:
            raise ValueError(f"{path}: missing '{key}' header line")
    if header.get("basemesh", ["hm08"])[0] != "hm08":
        raise ValueError(f"{path}: base mesh {header['basemesh'][0]!r} is not hm08 (the Anny topology)")
    scale_refs = np.array([[int(header[k][0]), int(header[k][1])] for k in ("x_scale", "y_scale", "z_scale")])
    scale_values = np.array([float(header[k][2]) for k in ("x_scale", "y_scale", "z_scale")])
    n_obj, faces = _read_obj_faces(path.parent / header["obj_file"][0])
    if n_obj != len(refs):
        raise ValueError(f"{path}: {len(refs)} bound vertices but {header['obj_file'][0]} has {n_obj}")
    binding = MhcloBinding(
        np.asarray(refs, dtype=np.int32), np.asarray(weights), np.asarray(offsets), scale_refs, scale_values,
        np.unique(np.asarray(deleted, dtype=np.int64)),
    )
    return header["name"][0], binding, faces


def load_mhclo_garment(path, body: AnnyBody | None = None) -> Garment:
    """A Garment from a MakeHuman `.mhclo`: fitted by its own binding, skinned through its reference vertices."""
    body = body if body is not None else AnnyBody()
    name, binding, faces = read_mhclo(path)
    if binding.refs.max() >= len(body.assets.template):
        raise ValueError(f"{path}: vertex index {binding.refs.max()} outside the hm08 mesh")
    skin_indices, skin_weights = interpolate_skin_weights(
        binding.refs, binding.weights, body.assets.skin_indices, body.assets.skin_weights, body.n_bones
    )
    return Garment(
        name=name,
        faces=faces,
        binding=binding,
        surface="body",
        skin_indices=skin_indices,
        skin_weights=skin_weights,
        regions=region_weights(skin_indices, skin_weights, body.bone_names),
    )
