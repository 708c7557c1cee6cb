"""One unit of build work: drape the garment on one body shape in one pose, stored as one file.

Workers (local processes or a Dask cluster) run `run_drape_job`; the builder writes each result atomically under
`<database>.work/drapes/`, so a killed build loses at most the drapes in flight and a rerun skips finished ones.
"""
from __future__ import annotations

import json
import logging
import lzma
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

# Per-process caches: a worker builds the body and each garment once, whatever number of jobs it runs.
_BODY = None
_GARMENTS: dict = {}
LOG = logging.getLogger(__name__)


def key_changes(stored: dict, wanted: dict, prefix: str = "") -> list:
    """['name: stored -> wanted', ...] for every entry in which two (nested, JSON) keys differ."""
    changes = []
    for name in sorted(set(stored) | set(wanted)):
        old, new = stored.get(name, "absent"), wanted.get(name, "absent")
        if isinstance(old, dict) and isinstance(new, dict):
            changes += key_changes(old, new, f"{prefix}{name}.")
        elif old != new:
            changes.append(f"{prefix}{name}: {json.dumps(old)} -> {json.dumps(new)}")
    return changes


@dataclass(frozen=True)
class DrapeJob:
    kind: str  # "anchor", "example" or "sequence"
    index: int  # anchor / example / frame index
    shape_index: int  # index into the training shapes (0 = beta0)
    pose: np.ndarray  # (B, 3) rotation vectors
    beta: np.ndarray  # (6,)
    garment: str
    garment_vertices: int
    settings: dict  # DrapeSettings fields
    # Warm start from a finished drape (another shape in the same pose, or the previous frame of a sequence): the
    # drape's offset from its own skinned garment is added to this job's skinned garment. "" = plain skinning.
    warm_key: str = ""
    warm_pose: np.ndarray | None = None  # (B, 3) the pose of the warm_key drape
    warm_beta: np.ndarray | None = None  # (6,) its shape

    @property
    def key(self) -> str:
        return f"{self.kind}_{self.index:04d}_{self.shape_index:02d}"


def _body_and_garment(name: str, n_vertices: int):
    global _BODY
    from ..body import AnnyBody
    from ..garment import make_garment

    if _BODY is None:
        _BODY = AnnyBody()
    if (name, n_vertices) not in _GARMENTS:
        _GARMENTS[(name, n_vertices)] = make_garment(name, _BODY, n_vertices)
    return _BODY, _GARMENTS[(name, n_vertices)]


def posed_scene(body, garment, beta, pose):
    """(garment rest (V, 3), garment skinned to pose (V, 3), body vertices (N, 3), body faces (G, 3)) at beta."""
    from ..body.kinematics import linear_blend_skinning

    shape = body.shape(beta)
    transforms, _ = body.pose(shape, pose)
    rest = garment.rest_vertices(body, shape)
    warm = linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, transforms, np.empty_like(rest))
    posed_body = body.posed_vertices(shape, transforms)
    ids = body.body_vertex_ids
    remap = np.full(len(posed_body), -1)
    remap[ids] = np.arange(len(ids))
    return rest, warm, posed_body[ids], remap[body.body_faces]


def transferred_warm_start(skinned, source_drape, source_skinned):
    """Warm start (V, 3): this job's skinned garment plus a finished drape's offset from its own skinned garment.

    A drape differs from its skinned garment mostly by how the cloth hangs (sleeves, hem, folds), which a small
    change of body shape or of pose barely alters; starting there instead of from plain skinning halves the frames
    a drape needs to settle (82 instead of 166 for a shape variant of a 2k-vertex T-shirt) and lands within the
    run-to-run spread of the equilibrium (friction makes it path dependent: 2.8 mm mean between the two starts).
    """
    return skinned + (source_drape - source_skinned)


def run_drape_job(job: DrapeJob, warm_drape: np.ndarray | None = None) -> dict:
    """Drape one job (in any process); returns the drape (V, 3) float64 and its diagnostics.

    `warm_drape` (V, 3) is the finished drape named by `job.warm_key` (required when the job has one).
    """
    from ..sim import DrapeSettings, drape
    from ..sim.posing import posed_surfaces, ramp_between, ramp_poses

    body, garment = _body_and_garment(job.garment, job.garment_vertices)
    rest, skinned, body_vertices, body_faces = posed_scene(body, garment, job.beta, job.pose)
    settings = DrapeSettings(**job.settings)
    if job.warm_key and warm_drape is None:
        raise ValueError(f"job {job.key} starts from drape {job.warm_key}, which was not given")
    keyframes = None  # (shapes, poses) the animated collider passes through before the target
    if job.warm_key and settings.warm_ramp_frames > 0:
        # the body changes from the source drape's shape and pose into this job's and carries the settled source
        # drape along; a transferred offset would put cloth inside a larger body (between the thighs), where
        # lifting it out to the nearest surface can pick the wrong side
        betas, poses = ramp_between(job.warm_beta, job.warm_pose, job.beta, job.pose, settings.warm_ramp_frames)
        keyframes = ([body.shape(b) for b in betas], poses)
        warm = np.asarray(warm_drape, dtype=np.float64)
    elif job.warm_key:
        source_skinned = posed_scene(body, garment, job.warm_beta, job.warm_pose)[1]
        warm = transferred_warm_start(skinned, warm_drape, source_skinned)
    elif settings.ramp_frames > 0:
        # the garment starts at rest on the body at rest, where it is clean, and the body carries it into the pose
        # (a skinned start would already sit folded into the armpit)
        keyframes = (body.shape(job.beta), ramp_poses(job.pose, settings.ramp_frames))
        warm = rest
    else:
        warm = skinned
    path = {}
    if keyframes is not None:
        bodies, garments = posed_surfaces(body, garment, *keyframes)
        pinned_path = np.concatenate([garments[:, garment.pinned], skinned[None, garment.pinned]])
        path = {"body_path": bodies, "pinned_path": pinned_path}
    result = drape(warm, garment.faces, body_vertices, body_faces, settings, rest_vertices=rest,
                   pinned=garment.pinned, **path)
    stats = {k: v for k, v in asdict(result).items() if k != "vertices" and np.isscalar(v)}
    return {"key": job.key, "vertices": np.asarray(result.vertices, dtype=np.float64), "stats": stats}


class DrapeStore:
    """Finished drapes of one build, one `.npz` per job under `folder`, written atomically."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.npz"

    def has(self, key: str) -> bool:
        return self.path(key).is_file()

    def save(self, result: dict) -> None:
        final = self.path(result["key"])
        partial = final.with_name(final.name + f".{os.getpid()}.partial")
        with open(partial, "wb") as handle:
            np.savez(handle, vertices=result["vertices"], **{f"stat_{k}": v for k, v in result["stats"].items()})
        os.replace(partial, final)  # a reader never sees half a drape

    def load(self, key: str) -> np.ndarray:
        try:
            with np.load(self.path(key)) as data:
                return data["vertices"]
        except (OSError, ValueError, KeyError) as error:
            raise ValueError(f"{self.path(key)}: unreadable drape ({error}); delete it and rerun the build") from None

    def stats(self, key: str) -> dict:
        with np.load(self.path(key)) as data:
            return _stats_of(data)

    def pack(self, path, plan_key: str, environment: dict | None = None) -> int:
        """Write every finished drape (vertices and stats) into one compressed .npz, tagged with the build's plan
        key and drape environment (versions, garment template hash); returns the count. A build is resumable
        across machines from this one file (`unpack`).

        The drapes go in as one (K, V, 3) array beside their keys and a JSON table of their stats: float32 when that
        holds them exactly (newton simulates in float32, so its drapes always do), byte-shuffled and compressed with
        lzma (a quarter smaller than under the npz's zlib), and float64 otherwise. Bit-exact either way, and
        `read_drape_pack` still reads the older layouts.
        """
        files = sorted(self.folder.glob("*.npz"))
        keys, vertices, stats = [], [], []
        for file in files:
            with np.load(file) as data:
                keys.append(file.stem)
                vertices.append(data["vertices"])
                stats.append(_stats_of(data))
        write_drape_pack(path, keys, vertices, stats, plan_key, environment)
        return len(files)

    def unpack(self, path, plan_key: str, environment: dict | None = None) -> int:
        """Add the drapes of a pack that this store lacks; returns the count.

        Refuses a pack of another build (plan key) or, given `environment`, one whose drapes were made under
        another drape environment, naming what differs. A pack from before environments were recorded is taken
        as made under `environment`, with a warning that says so (the shipped packs are such packs).
        """
        pack = read_drape_pack(path)
        if pack["plan_key"] != plan_key:
            changes = key_changes(json.loads(pack["plan_key"]), json.loads(plan_key))
            raise ValueError(f"{path}: these drapes belong to a build with other parameters (pack -> this build): "
                             f"{'; '.join(changes)}")
        if environment is not None:
            self._check_environment(path, pack["environment"], environment)
        added = 0
        for key, (vertices, stats) in pack["drapes"].items():
            if not self.has(key):
                self.save({"key": key, "vertices": vertices, "stats": stats})
                added += 1
        return added

    @staticmethod
    def _check_environment(path, stored: dict | None, environment: dict):
        wanted = json.loads(json.dumps(environment, sort_keys=True))
        if stored is None:
            LOG.warning("%s: this pack records no drape environment (packed before it was part of the key); its "
                        "drapes are taken as made under this build's: %s", path, json.dumps(wanted, sort_keys=True))
            return
        changes = key_changes(stored, wanted)
        if changes:
            raise ValueError(f"{path}: these drapes were made under another drape environment, so they are not "
                             f"reused (pack -> this build): {'; '.join(changes)}")


def _stats_of(data) -> dict:
    """The stats of one stored drape (its `stat_<name>` entries) as plain Python values."""
    return {k[5:]: data[k].item() for k in data.files if k.startswith("stat_")}


def write_drape_pack(path, keys: list, vertices: list, stats: list, plan_key: str, environment: dict | None = None):
    """One compressed .npz of drapes (see DrapeStore.pack), written atomically. vertices: K arrays (V, 3)."""
    arrays = {"__plan_key__": np.array(plan_key), "__keys__": np.array(keys, dtype=str),
              "__stats__": np.array(json.dumps(stats))}
    if environment is not None:
        arrays["__environment__"] = np.array(json.dumps(environment, sort_keys=True))
    if keys:
        stacked = np.stack([np.asarray(v, dtype=np.float64) for v in vertices])
        single = stacked.astype(np.float32)
        if np.array_equal(single, stacked):
            arrays["__vertices_shape__"] = np.array(single.shape, dtype=np.int64)
            arrays["__vertices_xz__"] = np.frombuffer(lzma.compress(_shuffled(single)), dtype=np.uint8)
        else:
            arrays["__vertices__"] = stacked
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as handle:
        np.savez_compressed(handle, **arrays)
    os.replace(partial, path)


def _shuffled(single: np.ndarray) -> bytes:
    """(K, V, 3) float32 as bytes grouped by coordinate, then by byte of the float: the sign-and-exponent bytes of
    neighbouring values sit together, which lzma packs a quarter smaller than the plain drapes under zlib."""
    planes = np.ascontiguousarray(single.transpose(2, 0, 1)).view(np.uint8).reshape(-1, 4)
    return np.ascontiguousarray(planes.T).tobytes()


def _unshuffled(data: bytes, shape) -> np.ndarray:
    """The inverse of _shuffled: (K, V, 3) float32."""
    k, v, c = (int(n) for n in shape)
    planes = np.frombuffer(data, dtype=np.uint8).reshape(4, -1).T
    return np.ascontiguousarray(planes).view(np.float32).reshape(c, k, v).transpose(1, 2, 0)


def read_drape_pack(path) -> dict:
    """{"plan_key", "environment" (dict or None), "drapes": {job key: ((V, 3) float64, stats dict)}} of a pack,
    in the stacked format DrapeStore.pack writes or the older one entry per drape and field."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: not a readable drape pack ({error})") from None
    with data:
        if "__plan_key__" not in data.files:
            raise ValueError(f"{path}: not a drape pack (no __plan_key__ entry)")
        environment = json.loads(str(data["__environment__"])) if "__environment__" in data.files else None
        drapes = {}
        if "__keys__" in data.files:
            keys = [str(k) for k in data["__keys__"]]
            stats = json.loads(str(data["__stats__"]))
            if not keys:
                vertices = np.zeros((0, 0, 3))
            elif "__vertices_xz__" in data.files:
                try:
                    vertices = _unshuffled(lzma.decompress(data["__vertices_xz__"].tobytes()),
                                           data["__vertices_shape__"])
                except (lzma.LZMAError, ValueError) as error:
                    raise ValueError(f"{path}: corrupt drapes ({error})") from None
            else:
                vertices = data["__vertices__"]
            if len(vertices) != len(keys) or len(stats) != len(keys):
                raise ValueError(f"{path}: {len(keys)} keys, {len(vertices)} drapes and {len(stats)} stats differ")
            drapes = {k: (np.asarray(v, dtype=np.float64), s) for k, v, s in zip(keys, vertices, stats)}
        else:
            fields: dict = {}
            for name in data.files:
                key, _, field = name.partition("/")
                if field:
                    fields.setdefault(key, []).append(field)
            for key, names in fields.items():
                stats = {f[5:]: data[f"{key}/{f}"].item() for f in names if f.startswith("stat_")}
                drapes[key] = (np.asarray(data[f"{key}/vertices"], dtype=np.float64), stats)
        return {"plan_key": str(data["__plan_key__"]), "environment": environment, "drapes": drapes}
