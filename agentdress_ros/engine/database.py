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
| pose_model/regressor/dofs, .../input_mean, .../input_scale | (I,) int32, (I,) f32, (I,) f32 | optional learned pose model (below): input pose dofs (indices into the D = 3B flattened rotation vectors) and their standardisation |
| pose_model/regressor/layer_NN/weights, .../layer_NN/bias | (H_n, H_n+1) f16, (H_n+1,) f32 | the MLP's layers, NN = 00, 01, ... (H_0 = I, the last = G); attrs activation, layers, info (JSON); weights written as float16 (f32 read as well) |
| pose_model/regressor/coefficient_mean, .../coefficient_scale, .../mean, .../basis | (G,), (G,) f32, (V, 3) f32, (G, V, 3) f16 | PCA of the rest-frame garment: position = mean + sum_g (y_g scale_g + mean_g) basis_g for the MLP output y |

| pose_model/kdsm/origin, .../dims, .../vertices, .../tets, .../class_inverse, .../lattice_tets | (3,) f64, (3,) int64, (Nk, 3) f64, (Tk, 4) int32, (12, 3, 3) f64, (Lk,) int32 | optional KDSM (kdsm.mesh.KDSM, below); attrs spacing, settings (JSON), info (JSON) |
| pose_model/kdsm/skin_indices, .../skin_weights, .../body_distance | (Nk, 4) int32, (Nk, 4) f64, (Nk,) f64 | the tet vertices' skinning and rest distance to the body |
| pose_model/kdsm/rest | (V, 3) f32 | u^{m_o}: the rest garment the displacements are learned for (in this file's vertex order) |
| pose_model/kdsm/regressor/... | as pose_model/regressor | the learned d(theta): PCA of the plastic displacements d, MLP from the pose |
| pose_model/recurrent/input_weights, .../state_weights, .../bias, .../output_weights, .../output_bias | (I, 3H), (H, 3H), (3H,), (H, G), (G,) f32 | optional recurrent correction of pose_model/regressor (engine.pose_models.RecurrentPoseModel): a GRU over the regressor's standardised inputs (gates z, r, n in that order) whose state adds output_weights h + output_bias to the regressor's standardised outputs; attrs hidden (H), info (JSON) |
| shape_model/residual/... | as pose_model/regressor, dofs in [0, D + 6) | optional learned correction of synthesis at other body shapes (EngineConfig.shape_residual, offline.shape_residual): inputs the D pose dofs followed by the 6 phenotypes, output a rest-frame displacement added to the blended shape delta; info (JSON) names the engine configuration it was trained against |
| garment_model/santesteban/fit/..., .../wrinkles/... | as pose_model/regressor, dofs in [0, D + 6) | optional garment model of Santesteban et al. 2019 (engine.santesteban): its inputs are the D pose dofs followed by the 6 phenotypes; fit R_G(beta) and wrinkles R_L(beta, theta), both rest-frame displacements of the garment; attrs info (JSON) |

The regressor (Santesteban et al. 2019, Sec. 3-4) is f(beta0, theta) in the rest frame: the garment unposed with
beta0's bones (their Eq. 5), reduced by PCA, regressed from the pose by an MLP (hidden layers `activation`, the last
linear). Trained offline (`agentdress lab regressor`, offline.regressor); evaluated with numpy (engine.pose_models). A
parts regressor (info "parts") is the same arrays holding one PCA and MLP per garment region side by side: no weight
joins two parts, and each part's basis rows are its own PCA times its blend weight on its own vertices (so they are
orthonormal only within one part).

The KDSM group (KDSM paper, Sec. 3-6) is the `kdsm` pose model: a skinned tet mesh of the air around the body at
beta0 and an MLP of the same kind learning the plastic displacements d(theta) of the garment in it; at run time
rest + d is re-embedded in the lattice and the parent tet skinned (world positions). Trained offline
(`python -m agentdress_ros.evaluate.kdsm_comparison`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

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


KDSM_GROUP = "pose_model/kdsm"
SANTESTEBAN_GROUP = "garment_model/santesteban"
SHAPE_RESIDUAL_GROUP = "shape_model/residual"
RECURRENT_GROUP = "pose_model/recurrent"
RECURRENT_ARRAYS = ("input_weights", "state_weights", "bias", "output_weights", "output_bias")
KDSM_ARRAYS = ("origin", "dims", "vertices", "tets", "class_inverse", "lattice_tets", "skin_indices", "skin_weights",
               "body_distance")


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
    """Write (or replace) the regressor group `name` in an open, writable HDF5 file. A new pose_model/regressor drops
    the groups trained on the one it replaces: pose_model/recurrent, and shape_model/residual (the residual of a
    synthesis that ran it)."""
    if name in h5:
        del h5[name]
    for trained_on_it in (RECURRENT_GROUP, SHAPE_RESIDUAL_GROUP) if name == REGRESSOR_GROUP else ():
        if trained_on_it in h5:
            del h5[trained_on_it]
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
        _create(group, name, np.ascontiguousarray(value, dtype=dtype))
    group.attrs["activation"] = regressor.activation
    group.attrs["layers"] = len(regressor.weights)
    group.attrs["info"] = json.dumps(regressor.info)


@dataclass(frozen=True)
class Recurrent:
    """The recurrent pose model's GRU (group pose_model/recurrent; shapes in the module docstring): its input is the
    regressor's standardised input x (I,), its state h (H,); the regressor's standardised output y (G,) becomes
    y + output_weights h + output_bias."""

    input_weights: np.ndarray  # (I, 3H) f32: gates z, r, n
    state_weights: np.ndarray  # (H, 3H) f32
    bias: np.ndarray  # (3H,) f32
    output_weights: np.ndarray  # (H, G) f32
    output_bias: np.ndarray  # (G,) f32
    info: dict = field(default_factory=dict)

    @property
    def hidden(self) -> int:
        return self.state_weights.shape[0]


def write_recurrent(h5, recurrent: Recurrent) -> None:
    """Write (or replace) the pose_model/recurrent group in an open, writable HDF5 file."""
    if RECURRENT_GROUP in h5:
        del h5[RECURRENT_GROUP]
    group = h5.require_group(RECURRENT_GROUP)
    for name in RECURRENT_ARRAYS:
        _create(group, name, np.ascontiguousarray(getattr(recurrent, name), dtype=np.float32))
    group.attrs["hidden"] = recurrent.hidden
    group.attrs["info"] = json.dumps(recurrent.info)


@dataclass(frozen=True)
class SantestebanArrays:
    """The garment model of Santesteban et al. 2019 (group garment_model/santesteban): two regressors whose input is
    the pose's D dofs followed by the 6 phenotypes (their `dofs` index that vector), each predicting a rest-frame
    displacement (V, 3) of the garment: `fit` R_G(beta) and `wrinkles` R_L(beta, theta)."""

    fit: Regressor
    wrinkles: Regressor
    info: dict = field(default_factory=dict)

    def vertex_rows(self, ids) -> "SantestebanArrays":
        return replace(self, fit=self.fit.vertex_rows(ids), wrinkles=self.wrinkles.vertex_rows(ids))


def write_santesteban(h5, arrays: SantestebanArrays) -> None:
    """Write (or replace) the garment_model/santesteban group in an open, writable HDF5 file."""
    if SANTESTEBAN_GROUP in h5:
        del h5[SANTESTEBAN_GROUP]
    write_regressor(h5, arrays.fit, SANTESTEBAN_GROUP + "/fit")
    write_regressor(h5, arrays.wrinkles, SANTESTEBAN_GROUP + "/wrinkles")
    h5[SANTESTEBAN_GROUP].attrs["info"] = json.dumps(arrays.info)


@dataclass(frozen=True)
class KdsmModel:
    """The `kdsm` pose model's arrays (group pose_model/kdsm): the KDSM (kdsm.mesh.KDSM), the rest garment its
    displacements belong to, and the regressor of d(theta) (rest-frame displacements instead of positions)."""

    kdsm: object  # kdsm.mesh.KDSM
    rest: np.ndarray  # (V, 3) f32
    regressor: Regressor
    info: dict = field(default_factory=dict)

    def vertex_rows(self, ids) -> "KdsmModel":
        """The model restricted to (or reordered by) garment vertex indices `ids`."""
        return replace(self, rest=self.rest[ids], regressor=self.regressor.vertex_rows(ids))


def write_kdsm_model(h5, model: KdsmModel) -> None:
    """Write (or replace) the KDSM group in an open, writable HDF5 file."""
    if KDSM_GROUP in h5:
        del h5[KDSM_GROUP]
    group = h5.require_group(KDSM_GROUP)
    kdsm = model.kdsm
    for name in KDSM_ARRAYS:
        _create(group, name, np.ascontiguousarray(getattr(kdsm, name)))
    _create(group, "rest", np.ascontiguousarray(model.rest, dtype=np.float32))
    group.attrs["spacing"] = float(kdsm.spacing)
    group.attrs["settings"] = json.dumps(_settings_dict(kdsm.settings))
    group.attrs["kdsm_info"] = json.dumps(kdsm.info)
    group.attrs["info"] = json.dumps(model.info)
    write_regressor(h5, model.regressor, KDSM_GROUP + "/regressor")


def _settings_dict(settings) -> dict:
    from dataclasses import asdict

    return asdict(settings)


def _create(parent, name: str, array: np.ndarray) -> None:
    """A dataset, compressed when it is big."""
    big = array.size > 4096
    parent.create_dataset(name, data=array, compression="gzip" if big else None, compression_opts=4 if big else None,
                          shuffle=big)


@dataclass
class Database:
    """All arrays of a database, in memory (names and shapes as in the module docstring)."""

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
    regressor: "Regressor | None" = None
    kdsm_model: "KdsmModel | None" = None
    santesteban: "SantestebanArrays | None" = None
    recurrent: "Recurrent | None" = None
    shape_residual: "Regressor | None" = None
    shape_basis: str = "absolute"
    binding_triangles: np.ndarray | None = None
    binding_barycentric: np.ndarray | None = None
    binding_offset: np.ndarray | None = None
    binding_surface: str = ""
    body_model: str = "anny/cmu_mb"
    build_command: str = ""
    provenance: dict = field(default_factory=dict)

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
            _create(h5, name, np.ascontiguousarray(value, dtype=dtype))
        for name, attr, _ in STRING_FIELDS:
            h5.create_dataset(name, data=np.array(getattr(db, attr), dtype=h5py.string_dtype()))
        h5["garment/regions"].attrs["region_names"] = json.dumps(list(db.region_names))
        if db.sequence_poses is not None:
            h5["pose_model/sequence"].attrs["fps"] = float(db.sequence_fps)
        h5["anchors"].attrs["shape_basis"] = db.shape_basis
        if db.binding_triangles is not None:
            h5["garment/binding"].attrs["surface"] = db.binding_surface
        if db.regressor is not None:
            write_regressor(h5, db.regressor)
        if db.kdsm_model is not None:
            write_kdsm_model(h5, db.kdsm_model)
        if db.santesteban is not None:
            write_santesteban(h5, db.santesteban)
        if db.recurrent is not None:
            write_recurrent(h5, db.recurrent)
        if db.shape_residual is not None:
            write_regressor(h5, db.shape_residual, SHAPE_RESIDUAL_GROUP)
    partial.replace(path)
    return path


def _shown(value):
    """An attribute's value as Python shows it (a numpy scalar as its plain number)."""
    return value.item() if isinstance(value, np.generic) else value


class _Reader:
    """One validating read of an open database file. Every check fails with a DatabaseError naming the file, the
    field (or attribute) and what is wrong; `where` names what is being read when h5py itself fails."""

    def __init__(self, path: Path, h5, max_dataset_bytes: int):
        self.path, self.h5, self.max_dataset_bytes = path, h5, max_dataset_bytes
        self.where = "the file"
        self.sizes: dict = {}  # letter -> (size, field that set it)
        self.total_bytes = 0

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
            self.fail(f"is {type(value).__name__} {_shown(value)!r}, expected text")
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
                self.fail(f"is {_shown(fps)!r}, expected a frame rate in (0, 10000]")
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
        extras["regressor"] = self.regressor()
        extras["kdsm_model"] = self.kdsm_model()
        extras["santesteban"] = self.santesteban()
        extras["recurrent"] = self.recurrent(extras["regressor"])
        extras["shape_residual"] = self.with_phenotype_inputs(SHAPE_RESIDUAL_GROUP)
        return Database(**values, **extras)

    def recurrent(self, regressor) -> Recurrent | None:
        """The optional pose_model/recurrent group (None when absent): its sizes tied to pose_model/regressor's
        inputs (I) and outputs (G), which it needs."""
        self.where = f"group '{RECURRENT_GROUP}'"
        group = self.h5.get(RECURRENT_GROUP)
        if group is None:
            return None
        if not isinstance(group, h5py.Group):
            self.fail("is a dataset, not a group")
        if regressor is None:
            self.fail(f"needs the group '{REGRESSOR_GROUP}', which is missing")
        hidden = self.attribute(RECURRENT_GROUP, "hidden")
        if not (np.ndim(hidden) == 0 and np.asarray(hidden).dtype.kind in "iu" and 1 <= hidden <= 4096):
            self.fail(f"is {_shown(hidden)!r}, expected a state size in [1, 4096]")
        info = self.json(RECURRENT_GROUP, "info", "{}", dict)
        h, i, g = int(hidden), len(regressor.dofs), len(regressor.coefficient_scale)  # tied to the regressor
        shapes = {"input_weights": (i, 3 * h), "state_weights": (h, 3 * h), "bias": (3 * h,),
                  "output_weights": (h, g), "output_bias": (g,)}
        values = {}
        for name in RECURRENT_ARRAYS:
            field_name = f"{RECURRENT_GROUP}/{name}"
            array = self.numeric(field_name, np.float32, shapes[name])
            self.check_range(field_name, array, (-1.0e6, 1.0e6), np.float32)
            values[name] = self.cast(array, np.float32)
        return Recurrent(**values, info=info)

    def santesteban(self) -> SantestebanArrays | None:
        """The optional garment_model/santesteban group (None when absent), its regressors checked like
        pose_model/regressor with inputs the D pose dofs and the 6 phenotypes."""
        self.where = f"group '{SANTESTEBAN_GROUP}'"
        group = self.h5.get(SANTESTEBAN_GROUP)
        if group is None:
            return None
        if not isinstance(group, h5py.Group):
            self.fail("is a dataset, not a group")
        info = self.json(SANTESTEBAN_GROUP, "info", "{}", dict)
        fit = self.with_phenotype_inputs(SANTESTEBAN_GROUP + "/fit", required=True)
        wrinkles = self.with_phenotype_inputs(SANTESTEBAN_GROUP + "/wrinkles", required=True)
        return SantestebanArrays(fit=fit, wrinkles=wrinkles, info=info)

    def with_phenotype_inputs(self, group_name: str, required: bool = False) -> Regressor | None:
        """A regressor group checked like pose_model/regressor, whose inputs are the D pose dofs followed by the 6
        phenotypes (None when absent and not required)."""
        self.sizes["D"], pose_dofs = (self.sizes["D"][0] + 6, self.sizes["D"][1]), self.sizes["D"]
        try:
            return self.regressor(group_name, required=required)
        finally:
            self.sizes["D"] = pose_dofs

    def kdsm_model(self) -> KdsmModel | None:
        """The optional KDSM group (None when absent): the mesh's arrays checked for shapes, index ranges and
        weights, its rest garment against V, its regressor like pose_model/regressor."""
        from ..kdsm.mesh import KDSM, KDSMSettings

        self.where = f"group '{KDSM_GROUP}'"
        group = self.h5.get(KDSM_GROUP)
        if group is None:
            return None
        if not isinstance(group, h5py.Group):
            self.fail("is a dataset, not a group")
        spacing = self.attribute(KDSM_GROUP, "spacing")
        if not (np.ndim(spacing) == 0 and np.asarray(spacing).dtype.kind == "f" and 1e-4 <= spacing <= 1.0):
            self.fail(f"is {_shown(spacing)!r}, expected a lattice step in [1e-4, 1] m")
        settings = self.json(KDSM_GROUP, "settings", "{}", dict)
        kdsm_info = self.json(KDSM_GROUP, "kdsm_info", "{}", dict)
        info = self.json(KDSM_GROUP, "info", "{}", dict)
        g = KDSM_GROUP + "/"
        fields = [("origin", np.float64, (3,), POINTS), ("dims", np.int64, (3,), (1, 100_000)),
                  ("vertices", np.float64, ("Nk", 3), POINTS), ("tets", np.int32, ("Tk", 4), (0, "Nk")),
                  ("class_inverse", np.float64, (12, 3, 3), (None, None)),
                  ("lattice_tets", np.int32, ("Lk",), (-1, "Tk")),
                  ("skin_indices", np.int32, ("Nk", N_INFLUENCES), (0, "B")),
                  ("skin_weights", np.float64, ("Nk", N_INFLUENCES), (0.0, 1.0)),
                  ("body_distance", np.float64, ("Nk",), (-1.0e3, 1.0e3)), ("rest", np.float32, ("V", 3), POINTS)]
        values = {}
        for name, dtype, spec, bounds in fields:
            array = self.numeric(g + name, dtype, spec)
            if name != "class_inverse":  # NaN-free is all: classes not meshed are never read
                self.check_range(g + name, array, bounds, dtype)
            values[name] = self.cast(array, dtype)
        self.where = f"field '{g}lattice_tets'"
        if int(np.prod(values["dims"])) * 12 != len(values["lattice_tets"]):
            self.fail(f"has {len(values['lattice_tets'])} entries, expected 12 per cube of dims "
                      f"{values['dims'].tolist()}")
        self.where = f"field '{g}skin_weights'"
        if np.abs(values["skin_weights"].sum(axis=1) - 1.0).max() > 1e-4:
            self.fail("has rows that do not sum to 1")
        for name in ("Nk", "Tk", "Lk"):
            self.sizes.pop(name, None)
        regressor = self.regressor(KDSM_GROUP + "/regressor", required=True)
        rest = values.pop("rest")
        try:
            kdsm_settings = KDSMSettings(**settings)
        except TypeError as error:
            self.where = f"attribute '{KDSM_GROUP}/settings'"
            self.fail(f"does not hold KDSM settings ({error})")
        kdsm = KDSM(spacing=float(spacing), settings=kdsm_settings, info=kdsm_info, **values)
        return KdsmModel(kdsm=kdsm, rest=rest, regressor=regressor, info=info)

    def regressor(self, group_name: str = REGRESSOR_GROUP, required: bool = False) -> Regressor | None:
        """The optional learned pose model's group (`group_name`: pose_model/regressor, or the KDSM's), checked like
        every other field (None when absent)."""
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
            self.fail(f"is {_shown(layers)!r}, expected a layer count in [1, {MAX_LAYERS}]")
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
