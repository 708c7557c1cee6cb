"""The AgentDress database: one HDF5 file per garment (schema below), its writer and its validating reader.

Shapes: V garment vertices, F triangles, B bones (31), N anchors, K training shapes (17), C PCA components,
P = 6 phenotypes, M pose-model examples, T sequence frames, R = 7 regions, D = 3B pose degrees of freedom.
Poses are per-bone rotation vectors (B, 3) in the body's convention (agentdress_ros.body.kinematics);
anchor and example poses have a zero root rotation and translation (drapes are simulated upright).
Drapes are garment vertex positions in world metres, posed, on the body of the stated shape.

Shape basis. "absolute": each anchor's PCA models its drapes f(beta, theta_s) themselves (Eq. 5), so the regression
(Eq. 6, additive in the phenotypes) has to carry the whole size change of the body. "skinned_residual": it models
the drapes minus the garment fitted to that body shape (the binding below) and skinned to theta_s, i.e. only how
the cloth hangs differently; the fitted, skinned garment (exact for any combination of phenotypes) is added back
at run time. A held-out shape that changes four phenotypes at once is reproduced 5x better this way (README).

| path | shape, dtype | meaning |
|---|---|---|
| attrs schema_version, garment, body_model, build_command, provenance (JSON) | | identity and how it was made |
| garment/faces | (F, 3) int32 | topology |
| garment/rest | (V, 3) f32 | garment at beta0, rest pose (the skinning rest) |
| garment/skin_indices, garment/skin_weights | (V, 4) int32, f32 | LBS binding |
| garment/regions | (V, R) f32 | region weights w_{g,y}; attrs region_names |
| body/bone_names, body/parents | (B,) str, int32 | rig identity |
| body/beta_names, body/beta0, body/beta_range | (P,) str, (P,) f64, (P, 2) f64 | shape space |
| body/beta_scale | (P,) f64 | shape units: the models see z = (beta - beta0) / beta_scale (see shape_features) |
| sensitivity/joint_weights | (D,) f32 | s^L per pose dof (Eq. 11), for the weighted k-means |
| sensitivity/region_dof | (R, D) f32 | Q_{g,m} (Eq. 7) |
| anchors/poses | (N, B, 3) f32 | anchor poses theta_s |
| anchors/training_betas | (K, P) f64 | the shapes each anchor was draped on |
| anchors/mean, anchors/components | (N, V, 3), (N, C, V, 3) f32 | PCA of each anchor's drapes (Eq. 5) |
| anchors/ridge | (N, 2P+1, C) f64 | shape_features (z, z^2, 1) -> PCA coefficients (Eq. 6) |
| anchors/explained_variance_ratio | (N, C) f64 | |
| anchors attr shape_basis | "absolute" or "skinned_residual" | what the PCA models (below) |
| garment/binding/triangles, .../barycentric, .../offset; attr surface | (V, 3) int32, (V, 3) f64, (V,) f64 | the garment on any body shape: a point of an hm08 triangle (vertex ids) plus an offset along the normal of the `surface` face group; required by the skinned_residual basis |
| pose_model/examples/poses, .../drapes | (M, B, 3) f32, (M, V, 3) f32 | drapes at beta0 |
| pose_model/sequence/poses, .../root_translation, .../drapes | (T, B, 3), (T, 3), (T, V, 3) f32; attr fps | a simulated sequence at beta0 |

Optional models (a pose model's learned arrays, another garment model) are stored in groups of their own by the
`Codec` their module registers beside its code (`register_codec`; engine.codecs lists those modules, and each
codec's docstring gives its group's layout). A group carries the attribute format_version (absent: 1, the format
before versions were written); a group of another version is migrated by the codec or refused with the command that
rewrites it. The regressor group's arrays are the building block of several of them:

| path | shape, dtype | meaning |
|---|---|---|
| <group>/dofs, .../input_mean, .../input_scale | (I,) int32, (I,) f32, (I,) f32 | input pose dofs (indices into the D = 3B flattened rotation vectors, or D + 6 with the phenotypes) and their standardisation |
| <group>/layer_NN/weights, .../layer_NN/bias | (H_n, H_n+1) f16, (H_n+1,) f32 | the MLP's layers, NN = 00, 01, ... (H_0 = I, the last = G); attrs activation, layers, info (JSON); weights written as float16 (f32 read as well) |
| <group>/coefficient_mean, .../coefficient_scale, .../mean, .../basis | (G,), (G,) f32, (V, 3) f32, (G, V, 3) f16 | PCA of the rest-frame garment: position = mean + sum_g (y_g scale_g + mean_g) basis_g for the MLP output y |

The regressor (Santesteban et al. 2019, Sec. 3-4) is f(beta0, theta) in the rest frame: the garment unposed with
beta0's bones (their Eq. 5), reduced by PCA, regressed from the pose by an MLP (hidden layers `activation`, the last
linear). Trained offline (`agentdress lab regressor`, offline.regressor); evaluated with numpy (engine.pose_models). A
parts regressor (info "parts") is the same arrays holding one PCA and MLP per garment region side by side: no weight
joins two parts, and each part's basis rows are its own PCA times its blend weight on its own vertices (so they are
orthonormal only within one part).
"""
from __future__ import annotations

import importlib
import json
import threading
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

SCHEMA_VERSION = 1
N_REGIONS = 7
N_INFLUENCES = 4


def shape_features(betas, beta0, beta_scale) -> np.ndarray:
    """(K, 2P+1) features (z, z^2, 1) of Eq. 6 with z = (beta - beta0) / beta_scale, for shapes (K, P) or (P,).

    The paper regresses on SMPL betas measured in standard deviations (training levels -2, -1, 1, 2); Anny's
    phenotypes live in [0, 1], so they are put in the same units: the training levels become z = +-1, +-2 and the
    ridge penalty (alpha 0.2) weighs them as in the paper.
    """
    z = (np.atleast_2d(betas) - beta0) / beta_scale
    return np.hstack([z, z**2, np.ones((len(z), 1))])


class DatabaseError(ValueError):
    """A database file is missing, unreadable or does not follow the schema; the message names file and field."""


REGRESSOR_GROUP = "pose_model/regressor"
REGRESSOR_ACTIVATIONS = ("tanh", "relu")
MAX_LAYERS = 16



@dataclass(frozen=True)
class Regressor:
    """The learned pose model's arrays (group pose_model/regressor; shapes in the module docstring)."""

    dofs: np.ndarray  # (I,) int32
    input_mean: np.ndarray  # (I,) f32
    input_scale: np.ndarray  # (I,) f32
    weights: tuple  # of (H_n, H_n+1) f32
    biases: tuple  # of (H_n+1,) f32
    coefficient_mean: np.ndarray  # (G,) f32
    coefficient_scale: np.ndarray  # (G,) f32
    mean: np.ndarray  # (V, 3) f32 rest-frame garment
    basis: np.ndarray  # (G, V, 3) f32 unit rows
    activation: str = "tanh"
    info: dict = field(default_factory=dict)  # how it was trained and what it scored (JSON); info["key"] identifies it

    def vertex_rows(self, ids) -> "Regressor":
        """The regressor restricted to (or reordered by) vertex indices `ids`."""
        return replace(self, mean=self.mean[ids], basis=self.basis[:, ids])


def as_stored(regressor: Regressor) -> Regressor:
    """The regressor as write_regressor stores it and the reader returns it: weights and basis rounded to float16."""
    def rounded(a):
        return np.asarray(a).astype(np.float16).astype(np.float32)

    return replace(regressor, weights=tuple(rounded(w) for w in regressor.weights), basis=rounded(regressor.basis))


def write_regressor(h5, regressor: Regressor, name: str = REGRESSOR_GROUP) -> None:
    """Write (or replace) the regressor arrays as group `name` in an open, writable HDF5 file (the building block of
    several models' groups; a model's whole group is written by write_model)."""
    if name in h5:
        del h5[name]
    group = h5.require_group(name)
    arrays = {"dofs": (regressor.dofs, np.int32), "input_mean": (regressor.input_mean, np.float32),
              "input_scale": (regressor.input_scale, np.float32),
              "coefficient_mean": (regressor.coefficient_mean, np.float32),
              "coefficient_scale": (regressor.coefficient_scale, np.float32),
              "mean": (regressor.mean, np.float32), "basis": (regressor.basis, np.float16)}
    # weights and basis stored as float16 (read back as float32): half the bytes, outputs moved by 0.01 mm on average
    # (at most 0.1 mm; README "Region parts"); means and biases stay float32, where the garment's metres are
    for n, (w, b) in enumerate(zip(regressor.weights, regressor.biases)):
        arrays[f"layer_{n:02d}/weights"] = (w, np.float16)
        arrays[f"layer_{n:02d}/bias"] = (b, np.float32)
    for name, (value, dtype) in arrays.items():
        create_dataset(group, name, np.ascontiguousarray(value, dtype=dtype))
    group.attrs["activation"] = regressor.activation
    group.attrs["layers"] = len(regressor.weights)
    group.attrs["info"] = json.dumps(regressor.info)


def create_dataset(parent, name: str, array: np.ndarray) -> None:
    """A dataset, compressed when it is big."""
    big = array.size > 4096
    parent.create_dataset(name, data=array, compression="gzip" if big else None, compression_opts=4 if big else None,
                          shuffle=big)


@dataclass(frozen=True)
class Codec:
    """How an optional model is stored: the Database attribute `name` it is read into, its HDF5 `group`, its format
    `version` (the group's attribute format_version; absent means 1), write(h5, value) creating the group,
    read(reader) -> value validating it (the reader's `stored` holds the models read before it),
    migrations {older version: read function for that version}, `upgrade` the command that rewrites the group at
    `version`, and `trained_on` the model whose replacement drops this one (it was trained on its outputs)."""

    name: str
    group: str
    version: int
    write: Callable
    read: Callable
    upgrade: str
    migrations: dict = field(default_factory=dict)
    trained_on: str = ""


_CODECS: dict[str, Codec] = {}
_CODECS_LOADED = False
_CODECS_LOCK = threading.RLock()  # the first read may come from two threads (the node's model worker and a tick)


def register_codec(codec: Codec) -> Codec:
    """Register (or replace) the codec of one optional model; models are read and written in registration order."""
    if codec.name in _TABLE_FIELDS or codec.name == "stored":
        raise ValueError(f"codec name {codec.name!r} is a field of the database itself")
    if codec.version < 1 or codec.version in codec.migrations:
        raise ValueError(f"codec {codec.name!r}: version {codec.version} must be >= 1 and not one it migrates from")
    _CODECS[codec.name] = codec
    return codec


def codecs() -> dict[str, Codec]:
    """Every registered codec by name, the modules of engine.codecs imported first (they register theirs)."""
    global _CODECS_LOADED
    if not _CODECS_LOADED:
        with _CODECS_LOCK:
            if not _CODECS_LOADED:
                from .codecs import CODEC_MODULES

                for module in CODEC_MODULES:
                    importlib.import_module(module)
                _CODECS_LOADED = True
    return _CODECS


def write_model(h5, name: str, value) -> None:
    """Write (or replace) the group of optional model `name` in an open, writable HDF5 file, with its format version;
    the groups trained on the one replaced (Codec.trained_on) are dropped."""
    codec = codecs()[name]
    for other in _CODECS.values():
        if other.trained_on == name and other.group in h5:
            del h5[other.group]
    if codec.group in h5:
        del h5[codec.group]
    codec.write(h5, value)
    h5[codec.group].attrs["format_version"] = codec.version


@dataclass
class _Tables:
    """The schema core's arrays and attributes (names and shapes as in the module docstring)."""

    garment: str
    faces: np.ndarray
    rest: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    regions: np.ndarray
    region_names: tuple
    bone_names: tuple
    parents: np.ndarray
    beta_names: tuple
    beta0: np.ndarray
    beta_range: np.ndarray
    beta_scale: np.ndarray
    joint_weights: np.ndarray
    region_dof: np.ndarray
    anchor_poses: np.ndarray
    training_betas: np.ndarray
    pca_mean: np.ndarray
    pca_components: np.ndarray
    ridge: np.ndarray
    explained_variance_ratio: np.ndarray
    example_poses: np.ndarray
    example_drapes: np.ndarray
    sequence_poses: np.ndarray | None = None
    sequence_root_translation: np.ndarray | None = None
    sequence_drapes: np.ndarray | None = None
    sequence_fps: float = 30.0
    shape_basis: str = "absolute"
    binding_triangles: np.ndarray | None = None
    binding_barycentric: np.ndarray | None = None
    binding_offset: np.ndarray | None = None
    binding_surface: str = ""
    body_model: str = "anny/cmu_mb"
    build_command: str = ""
    provenance: dict = field(default_factory=dict)
    stored: dict = field(default_factory=dict)  # optional models by codec name (register_codec)


_TABLE_FIELDS = frozenset(f.name for f in fields(_Tables))


class Database(_Tables):
    """All arrays of a database, in memory. The optional models are attributes by their codec's name (`db.regressor`,
    None when the file has none) and keywords of the constructor and of dataclasses.replace
    (`replace(db, regressor=r)`, None removes one); they live in `stored`."""

    def __init__(self, *args, stored: dict | None = None, **kwargs):
        models = {name: kwargs.pop(name) for name in list(kwargs) if name not in _TABLE_FIELDS}
        unknown = sorted(set(models) - set(codecs())) if models else []
        if unknown:
            raise TypeError(f"Database has no field or stored model {unknown}; stored models: {sorted(codecs())}")
        merged = {**(stored or {}), **models}
        super().__init__(*args, stored={name: value for name, value in merged.items() if value is not None}, **kwargs)

    def __getattr__(self, name):  # only for names that are not fields: the optional models
        if name.startswith("__") or name == "stored" or name not in codecs():
            raise AttributeError(f"'Database' object has no attribute {name!r}")
        return self.__dict__.get("stored", {}).get(name)

    @property
    def n_vertices(self) -> int:
        return len(self.rest)

    @property
    def n_anchors(self) -> int:
        return len(self.anchor_poses)

    @property
    def n_components(self) -> int:
        return self.pca_components.shape[1]


# (h5 path, Database attribute, dtype, shape spec, (low, high)). Letters in the spec must agree across fields. The
# range is inclusive; None leaves a side open; a letter as the upper bound means an index below that size.
COORDINATE = 100.0  # metres: garment and drape coordinates, the shape models' means
ANGLE = 4 * np.pi  # radians: a rotation-vector component
POSES = (-ANGLE, ANGLE)
POINTS = (-COORDINATE, COORDINATE)
FIELDS = (
    ("garment/faces", "faces", np.int32, ("F", 3), (0, "V")),
    ("garment/rest", "rest", np.float32, ("V", 3), POINTS),
    ("garment/skin_indices", "skin_indices", np.int32, ("V", N_INFLUENCES), (0, "B")),
    ("garment/skin_weights", "skin_weights", np.float32, ("V", N_INFLUENCES), (0.0, 1.0)),
    ("garment/regions", "regions", np.float32, ("V", N_REGIONS), (0.0, 1.0)),
    ("body/parents", "parents", np.int32, ("B",), (-1, "B")),
    ("body/beta0", "beta0", np.float64, ("P",), (0.0, 1.0)),
    ("body/beta_range", "beta_range", np.float64, ("P", 2), (0.0, 1.0)),
    ("body/beta_scale", "beta_scale", np.float64, ("P",), (0.0, 1.0e3)),
    ("sensitivity/joint_weights", "joint_weights", np.float32, ("D",), (0.0, None)),
    ("sensitivity/region_dof", "region_dof", np.float32, (N_REGIONS, "D"), (0.0, None)),
    ("anchors/poses", "anchor_poses", np.float32, ("N", "B", 3), POSES),
    ("anchors/training_betas", "training_betas", np.float64, ("K", "P"), (0.0, 1.0)),
    ("anchors/mean", "pca_mean", np.float32, ("N", "V", 3), POINTS),
    ("anchors/components", "pca_components", np.float32, ("N", "C", "V", 3), (-1.001, 1.001)),  # unit vectors
    ("anchors/ridge", "ridge", np.float64, ("N", "Q", "C"), (-1.0e6, 1.0e6)),
    ("anchors/explained_variance_ratio", "explained_variance_ratio", np.float64, ("N", "C"), (0.0, 1.0 + 1e-6)),
    ("pose_model/examples/poses", "example_poses", np.float32, ("M", "B", 3), POSES),
    ("pose_model/examples/drapes", "example_drapes", np.float32, ("M", "V", 3), POINTS),
)
OPTIONAL_FIELDS = (
    ("pose_model/sequence/poses", "sequence_poses", np.float32, ("T", "B", 3), POSES),
    ("pose_model/sequence/root_translation", "sequence_root_translation", np.float32, ("T", 3), (-1.0e4, 1.0e4)),
    ("pose_model/sequence/drapes", "sequence_drapes", np.float32, ("T", "V", 3), POINTS),
    ("garment/binding/triangles", "binding_triangles", np.int32, ("V", 3), (0, None)),  # the engine checks the body's
    ("garment/binding/barycentric", "binding_barycentric", np.float64, ("V", 3), (-1e-6, 1.0 + 1e-6)),
    ("garment/binding/offset", "binding_offset", np.float64, ("V",), (-1.0, 1.0)),
)
SHAPE_BASES = ("absolute", "skinned_residual")
STRING_FIELDS = (("body/bone_names", "bone_names", "B"), ("body/beta_names", "beta_names", "P"))
#: The most bytes one dataset may take in memory, and all of them together: a file that declares more (a corrupt
#: or hostile header) is refused before anything is read. The largest database measured (12k vertices, 150
#: anchors, 10 components) holds 216 MB in its largest dataset.
MAX_DATASET_BYTES = 2**30
MAX_TOTAL_BYTES = 4 * 2**30
MAX_NAMES = 4096  # entries of a string dataset
SUM_TOLERANCE = 1e-3  # rows of skin weights and barycentric coordinates sum to 1 within this


def write_database(path, db: Database) -> Path:
    """Write `db` atomically (to a temporary file renamed over `path`), float arrays compressed."""
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    with h5py.File(partial, "w") as h5:
        h5.attrs["schema_version"] = SCHEMA_VERSION
        h5.attrs["garment"] = db.garment
        h5.attrs["body_model"] = db.body_model
        h5.attrs["build_command"] = db.build_command
        h5.attrs["provenance"] = json.dumps(db.provenance)
        for name, attr, dtype, _, _ in FIELDS + OPTIONAL_FIELDS:
            value = getattr(db, attr)
            if value is None:
                continue
            create_dataset(h5, name, np.ascontiguousarray(value, dtype=dtype))
        for name, attr, _ in STRING_FIELDS:
            h5.create_dataset(name, data=np.array(getattr(db, attr), dtype=h5py.string_dtype()))
        h5["garment/regions"].attrs["region_names"] = json.dumps(list(db.region_names))
        if db.sequence_poses is not None:
            h5["pose_model/sequence"].attrs["fps"] = float(db.sequence_fps)
        h5["anchors"].attrs["shape_basis"] = db.shape_basis
        if db.binding_triangles is not None:
            h5["garment/binding"].attrs["surface"] = db.binding_surface
        for name in codecs():  # registration order: a model before those trained on it
            if db.stored.get(name) is not None:
                write_model(h5, name, db.stored[name])
    partial.replace(path)
    return path


def shown(value):
    """An attribute's value as Python shows it (a numpy scalar as its plain number)."""
    return value.item() if isinstance(value, np.generic) else value


class _Reader:
    """One validating read of an open database file. Every check fails with a DatabaseError naming the file, the
    field (or attribute) and what is wrong; `where` names what is being read when h5py itself fails. A codec reads
    its group through the same checks (numeric, check_range, cast, attribute, text, json, regressor,
    with_phenotype_inputs, fail)."""

    def __init__(self, path: Path, h5, max_dataset_bytes: int):
        self.path, self.h5, self.max_dataset_bytes = path, h5, max_dataset_bytes
        self.where = "the file"
        self.sizes: dict = {}  # letter -> (size, field that set it)
        self.total_bytes = 0
        self.stored: dict = {}  # optional models read so far, by codec name

    def fail(self, what: str):
        raise DatabaseError(f"{self.path}: {self.where} {what}")

    # ---------------------------------------------------------------- datasets
    def dataset(self, name: str, required: bool = True):
        self.where = f"field '{name}'"
        obj = self.h5.get(name)
        if obj is None:
            if required:
                raise DatabaseError(f"{self.path}: required field '{name}' is missing")
            return None
        if not isinstance(obj, h5py.Dataset):
            self.fail("is a group, not a dataset")
        return obj

    def reserve(self, shape, itemsize: int):
        """Refuse a dataset whose declared size passes the caps, before reading any of it."""
        nbytes = int(np.prod(shape, dtype=object)) * itemsize
        if nbytes > self.max_dataset_bytes:
            self.fail(f"declares shape {tuple(shape)} ({nbytes / 2**20:.0f} MiB), more than the "
                      f"{self.max_dataset_bytes / 2**20:.0f} MiB one dataset may hold")
        self.total_bytes += nbytes
        if self.total_bytes > MAX_TOTAL_BYTES:
            self.fail(f"brings the database past {MAX_TOTAL_BYTES / 2**30:.0f} GiB")

    def check_shape(self, name: str, shape, spec):
        if len(shape) != len(spec):
            self.fail(f"has {len(shape)} dimensions {tuple(shape)}, expected {len(spec)} {spec}")
        for axis, (want, got) in enumerate(zip(spec, shape)):
            if isinstance(want, int):
                if got != want:
                    self.fail(f"axis {axis} has size {got}, expected {want}")
            elif got == 0:
                self.fail(f"axis {axis} ({want}) is empty")
            else:
                size, owner = self.sizes.setdefault(want, (got, name))
                if size != got:
                    self.fail(f"axis {axis} ({want}) has size {got}, but field '{owner}' says {want} = {size}")

    def numeric(self, name: str, dtype, spec, required: bool = True):
        """The dataset in its stored dtype, checked for kind, shape, size and finiteness (ranges come later)."""
        obj = self.dataset(name, required)
        if obj is None:
            return None
        integer = np.dtype(dtype).kind == "i"
        if obj.dtype.kind not in ("iu" if integer else "f"):
            self.fail(f"has dtype {obj.dtype}, expected {'integers' if integer else 'floating-point numbers'} "
                      f"({np.dtype(dtype).name})")
        if len(obj.shape) != len(spec):
            self.check_shape(name, obj.shape, spec)
        self.reserve(obj.shape, max(obj.dtype.itemsize, np.dtype(dtype).itemsize))
        self.check_shape(name, obj.shape, spec)
        array = obj[()]
        if not integer and not np.isfinite(array).all():
            self.fail(f"contains non-finite values (NaN or Inf) at index {self.first(~np.isfinite(array))}")
        return array

    @staticmethod
    def first(mask) -> tuple:
        return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))

    def check_range(self, name: str, array, bounds, dtype):
        self.where = f"field '{name}'"
        low, high = bounds
        if isinstance(high, str):  # an index into something of that size
            high = self.sizes[high][0] - 1
        if np.dtype(dtype).kind == "i":  # whatever the bounds, nothing a cast to dtype would wrap around
            limits = np.iinfo(dtype)
            low, high = max(limits.min, low), limits.max if high is None else min(limits.max, high)
        lowest, highest = array.min().item(), array.max().item()
        if (low is not None and lowest < low) or (high is not None and highest > high):
            outside = np.zeros(array.shape, dtype=bool)
            if low is not None and lowest < low:
                outside |= array < low
            if high is not None and highest > high:
                outside |= array > high
            index = self.first(outside)
            self.fail(f"has values outside [{'-inf' if low is None else low}, {'inf' if high is None else high}]: "
                      f"{array[index]} at index {index}")

    def cast(self, array, dtype):
        with np.errstate(over="ignore"):  # reported below, naming the field
            out = np.ascontiguousarray(array, dtype=dtype)
        if out.dtype.kind == "f" and not np.isfinite(out).all():
            self.fail(f"has values beyond the {np.dtype(dtype).name} range at index {self.first(~np.isfinite(out))}")
        return out

    def names(self, name: str, letter: str) -> tuple:
        obj = self.dataset(name)
        if obj.dtype.kind not in "OSU" or (obj.dtype.kind == "O" and h5py.check_string_dtype(obj.dtype) is None):
            self.fail(f"has dtype {obj.dtype}, expected strings")
        if len(obj.shape) != 1 or not 0 < obj.shape[0] <= MAX_NAMES:
            self.fail(f"has shape {obj.shape}, expected 1 to {MAX_NAMES} names")
        try:
            values = tuple(s.decode() if isinstance(s, bytes) else str(s) for s in obj[()])
        except UnicodeDecodeError as error:
            self.fail(f"is not UTF-8 text ({error})")
        if len(values) != self.sizes[letter][0]:
            self.fail(f"has {len(values)} names, but field '{self.sizes[letter][1]}' says {letter} = "
                      f"{self.sizes[letter][0]}")
        if "" in values or len(set(values)) != len(values):
            self.fail("has empty or repeated names")
        return values

    # ---------------------------------------------------------------- attributes
    def attribute(self, owner: str, key: str, default=None):
        self.where = f"attribute '{owner + '/' if owner else ''}{key}'"
        obj = self.h5[owner] if owner else self.h5
        return obj.attrs.get(key, default)

    def text(self, owner: str, key: str, default: str | None = None, allow_empty: bool = True) -> str:
        value = self.attribute(owner, key, default)
        if value is None:
            self.fail("is missing")
        if isinstance(value, bytes):
            try:
                value = value.decode()
            except UnicodeDecodeError as error:
                self.fail(f"is not UTF-8 text ({error})")
        if not isinstance(value, str):
            self.fail(f"is {type(value).__name__} {shown(value)!r}, expected text")
        if not allow_empty and not value:
            self.fail("is empty")
        return value

    def json(self, owner: str, key: str, default: str, kind: type):
        text = self.text(owner, key, default)
        try:
            value = json.loads(text)
        except ValueError as error:
            self.fail(f"is not valid JSON ({error})")
        if not isinstance(value, kind):
            self.fail(f"is JSON {type(value).__name__}, expected {kind.__name__}")
        return value

    # ---------------------------------------------------------------- the whole file
    def read(self) -> Database:
        self.where = "attribute 'schema_version'"
        version = self.h5.attrs.get("schema_version")
        if not (np.ndim(version) == 0 and np.asarray(version).dtype.kind in "iu" and version == SCHEMA_VERSION):
            raise DatabaseError(f"{self.path}: schema_version is {version}, this reader understands "
                                f"{SCHEMA_VERSION}")
        raw, specs = {}, {}
        for fields, required in ((FIELDS, True), (OPTIONAL_FIELDS, False)):
            for name, attr, dtype, spec, bounds in fields:
                array = self.numeric(name, dtype, spec, required)
                if array is not None:
                    raw[name], specs[name] = array, (attr, dtype, bounds)
        values = {}
        for name, array in raw.items():
            attr, dtype, bounds = specs[name]
            self.check_range(name, array, bounds, dtype)
            values[attr] = self.cast(array, dtype)
        for name, attr, letter in STRING_FIELDS:
            values[attr] = self.names(name, letter)
        self.check_relations(values)
        extras = dict(
            garment=self.text("", "garment", allow_empty=False),
            body_model=self.text("", "body_model", ""),
            build_command=self.text("", "build_command", ""),
            provenance=self.json("", "provenance", "{}", dict),
            region_names=tuple(self.json("garment/regions", "region_names", "[]", list)),
        )
        if len(extras["region_names"]) != N_REGIONS or not all(isinstance(n, str) for n in extras["region_names"]):
            self.fail(f"has {extras['region_names']!r}, expected the names of the {N_REGIONS} regions")
        if "pose_model/sequence/poses" in raw:
            fps = self.attribute("pose_model/sequence", "fps", 30.0)
            if not (np.ndim(fps) == 0 and np.asarray(fps).dtype.kind in "iuf" and 0 < fps <= 1e4):
                self.fail(f"is {shown(fps)!r}, expected a frame rate in (0, 10000]")
            extras["sequence_fps"] = float(fps)
        basis = self.text("anchors", "shape_basis", "absolute")
        if basis not in SHAPE_BASES:
            self.fail(f"is {basis!r}, expected one of {SHAPE_BASES}")
        extras["shape_basis"] = basis
        if basis == "skinned_residual":
            for name in ("garment/binding/triangles", "garment/binding/barycentric", "garment/binding/offset"):
                if name not in raw:
                    raise DatabaseError(f"{self.path}: field '{name}' is missing (required by the skinned_residual "
                                        "basis)")
            extras["binding_surface"] = self.text("garment/binding", "surface", allow_empty=False)
        for codec in codecs().values():
            value = self.stored_model(codec)
            if value is not None:
                self.stored[codec.name] = value
        return Database(**values, **extras, stored=self.stored)

    def stored_model(self, codec: Codec):
        """The optional model of `codec` (None when its group is absent), read by the codec at the group's format
        version: the current one, one it migrates, else refused naming the version and the command that rewrites
        it."""
        self.where = f"group '{codec.group}'"
        group = self.h5.get(codec.group)
        if group is None:
            return None
        if not isinstance(group, h5py.Group):
            self.fail("is a dataset, not a group")
        version = self.attribute(codec.group, "format_version", 1)
        if not (np.ndim(version) == 0 and np.asarray(version).dtype.kind in "iu"):
            self.fail(f"is {shown(version)!r}, expected a format version number")
        read = codec.read if version == codec.version else codec.migrations.get(int(version))
        self.where = f"group '{codec.group}'"
        if read is None:
            migrated = f" (and migrates version {', '.join(map(str, sorted(codec.migrations)))})" \
                if codec.migrations else ""
            self.fail(f"has format version {int(version)}, this reader reads version {codec.version}{migrated}: "
                      f"rewrite it with `{codec.upgrade}`")
        return read(self)

    def with_phenotype_inputs(self, group_name: str, required: bool = False) -> Regressor | None:
        """A regressor group checked like pose_model/regressor, whose inputs are the D pose dofs followed by the 6
        phenotypes (None when absent and not required)."""
        self.sizes["D"], pose_dofs = (self.sizes["D"][0] + 6, self.sizes["D"][1]), self.sizes["D"]
        try:
            return self.regressor(group_name, required=required)
        finally:
            self.sizes["D"] = pose_dofs

    def regressor(self, group_name: str = REGRESSOR_GROUP, required: bool = False) -> Regressor | None:
        """The regressor arrays of group `group_name` (pose_model/regressor, or a part of another model's group),
        checked like every other field (None when absent and not required)."""
        self.where = f"group '{group_name}'"
        group = self.h5.get(group_name)
        if group is None and required:
            raise DatabaseError(f"{self.path}: required group '{group_name}' is missing")
        if group is None:
            return None
        if not isinstance(group, h5py.Group):
            self.fail("is a dataset, not a group")
        layers = self.attribute(group_name, "layers")
        if not (np.ndim(layers) == 0 and np.asarray(layers).dtype.kind in "iu" and 1 <= layers <= MAX_LAYERS):
            self.fail(f"is {shown(layers)!r}, expected a layer count in [1, {MAX_LAYERS}]")
        activation = self.text(group_name, "activation", allow_empty=False)
        if activation not in REGRESSOR_ACTIVATIONS:
            self.fail(f"is {activation!r}, expected one of {REGRESSOR_ACTIVATIONS}")
        info = self.json(group_name, "info", "{}", dict)
        g = group_name + "/"
        sizes = ["I"] + [f"H{n + 1}" for n in range(int(layers) - 1)] + ["G"]  # widths: input, hidden..., output
        fields = [("dofs", np.int32, ("I",), (0, "D")), ("input_mean", np.float32, ("I",), (-1.0e3, 1.0e3)),
                  ("input_scale", np.float32, ("I",), (1.0e-9, 1.0e3))]
        for n in range(int(layers)):
            fields += [(f"layer_{n:02d}/weights", np.float32, (sizes[n], sizes[n + 1]), (-1.0e6, 1.0e6)),
                       (f"layer_{n:02d}/bias", np.float32, (sizes[n + 1],), (-1.0e6, 1.0e6))]
        fields += [("coefficient_mean", np.float32, ("G",), (-1.0e6, 1.0e6)),
                   ("coefficient_scale", np.float32, ("G",), (1.0e-12, 1.0e6)),
                   ("mean", np.float32, ("V", 3), POINTS), ("basis", np.float32, ("G", "V", 3), (-1.001, 1.001))]
        values = {}
        for name, dtype, spec, bounds in fields:
            array = self.numeric(g + name, dtype, spec)
            self.check_range(g + name, array, bounds, dtype)
            values[name] = self.cast(array, dtype)
        self.where = f"field '{g}dofs'"
        if len(np.unique(values["dofs"])) != len(values["dofs"]):
            self.fail("has repeated pose dofs")
        for name in ("I", "G") + tuple(sizes[1:-1]):  # layer widths belong to this group only
            self.sizes.pop(name, None)
        return Regressor(
            dofs=values["dofs"], input_mean=values["input_mean"], input_scale=values["input_scale"],
            weights=tuple(values[f"layer_{n:02d}/weights"] for n in range(int(layers))),
            biases=tuple(values[f"layer_{n:02d}/bias"] for n in range(int(layers))),
            coefficient_mean=values["coefficient_mean"], coefficient_scale=values["coefficient_scale"],
            mean=values["mean"], basis=values["basis"], activation=activation, info=info)

    def check_relations(self, values: dict):
        """What no single field's range says: sums, orderings, counts that tie fields together."""
        def field(name):
            self.where = f"field '{name}'"

        p, b = self.sizes["P"][0], self.sizes["B"][0]
        field("sensitivity/joint_weights")
        if self.sizes["D"][0] != 3 * b:
            self.fail(f"has {self.sizes['D'][0]} pose dofs, expected 3 per bone = {3 * b}")
        field("anchors/ridge")
        if self.sizes["Q"][0] != 2 * p + 1:
            self.fail(f"has {self.sizes['Q'][0]} features, expected 2P+1 = {2 * p + 1}")
        for name, attr in (("garment/skin_weights", "skin_weights"), ("garment/binding/barycentric",
                                                                        "binding_barycentric")):
            if values.get(attr) is not None:
                field(name)
                error = np.abs(values[attr].sum(axis=1, dtype=np.float64) - 1.0)
                if error.max() > SUM_TOLERANCE:
                    row = int(np.argmax(error))
                    self.fail(f"rows must sum to 1: row {row} sums to {values[attr][row].sum(dtype=np.float64)}")
        field("garment/regions")
        sums = values["regions"].sum(axis=1, dtype=np.float64)
        if sums.max() > 1.0 + SUM_TOLERANCE:
            self.fail(f"rows must sum to at most 1: row {int(np.argmax(sums))} sums to {sums.max()}")
        field("anchors/explained_variance_ratio")
        sums = values["explained_variance_ratio"].sum(axis=1)
        if sums.max() > 1.0 + 1e-6:
            self.fail(f"rows must sum to at most 1: anchor {int(np.argmax(sums))} sums to {sums.max()}")
        field("body/parents")
        parents = values["parents"]
        later = [j for j in range(b) if (parents[j] != -1 if j == 0 else not 0 <= parents[j] < j)]
        if later:
            self.fail(f"must list the root first (parent -1) and every other bone after its parent: bone {later[0]} "
                      f"has parent {parents[later[0]]}")
        field("body/beta_scale")
        if values["beta_scale"].min() <= 0:
            self.fail(f"must be > 0, has {values['beta_scale'].min()} at index {int(np.argmin(values['beta_scale']))}")
        field("body/beta_range")
        low, high = values["beta_range"].T
        if (low > high).any():
            i = int(np.argmax(low > high))
            self.fail(f"row {i} has low {low[i]} > high {high[i]}")
        field("body/beta0")
        outside = (values["beta0"] < low - 1e-9) | (values["beta0"] > high + 1e-9)
        if outside.any():
            i = int(np.argmax(outside))
            self.fail(f"value {values['beta0'][i]} at index {i} lies outside beta_range [{low[i]}, {high[i]}]")


def read_database(path, max_dataset_bytes: int = MAX_DATASET_BYTES) -> Database:
    """Load and validate a database; raises DatabaseError naming the file, the offending field and what is wrong.

    Every dataset is checked for its dtype kind (no silent float -> int truncation or int64 wrap-around), shape,
    size (against `max_dataset_bytes`, before it is read), finiteness and range; then the relations between fields
    (skin weights and barycentric coordinates summing to 1, the bone order, beta_range order, beta_scale > 0, the
    region and feature counts) and the attributes (text, JSON). A truncated or corrupt file is a DatabaseError too.
    """
    path = Path(path)
    if not path.is_file():
        raise DatabaseError(f"{path}: database file not found (build one with `agentdress build`)")
    try:
        h5 = h5py.File(path, "r")
    except (OSError, ValueError) as error:
        raise DatabaseError(f"{path}: not a readable HDF5 file ({error})") from None
    reader = _Reader(path, h5, max_dataset_bytes)
    with h5:
        try:
            return reader.read()
        except DatabaseError:
            raise
        except (OSError, KeyError, ValueError, TypeError, RuntimeError, OverflowError, MemoryError) as error:
            raise DatabaseError(f"{path}: {reader.where} cannot be read ({type(error).__name__}: {error})") from None
