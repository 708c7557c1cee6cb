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
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
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


# (h5 path, Database attribute, dtype, shape spec). Letters in the spec must agree across fields.
FIELDS = (
    ("garment/faces", "faces", np.int32, ("F", 3)),
    ("garment/rest", "rest", np.float32, ("V", 3)),
    ("garment/skin_indices", "skin_indices", np.int32, ("V", N_INFLUENCES)),
    ("garment/skin_weights", "skin_weights", np.float32, ("V", N_INFLUENCES)),
    ("garment/regions", "regions", np.float32, ("V", N_REGIONS)),
    ("body/parents", "parents", np.int32, ("B",)),
    ("body/beta0", "beta0", np.float64, ("P",)),
    ("body/beta_range", "beta_range", np.float64, ("P", 2)),
    ("body/beta_scale", "beta_scale", np.float64, ("P",)),
    ("sensitivity/joint_weights", "joint_weights", np.float32, ("D",)),
    ("sensitivity/region_dof", "region_dof", np.float32, (N_REGIONS, "D")),
    ("anchors/poses", "anchor_poses", np.float32, ("N", "B", 3)),
    ("anchors/training_betas", "training_betas", np.float64, ("K", "P")),
    ("anchors/mean", "pca_mean", np.float32, ("N", "V", 3)),
    ("anchors/components", "pca_components", np.float32, ("N", "C", "V", 3)),
    ("anchors/ridge", "ridge", np.float64, ("N", "Q", "C")),
    ("anchors/explained_variance_ratio", "explained_variance_ratio", np.float64, ("N", "C")),
    ("pose_model/examples/poses", "example_poses", np.float32, ("M", "B", 3)),
    ("pose_model/examples/drapes", "example_drapes", np.float32, ("M", "V", 3)),
)
OPTIONAL_FIELDS = (
    ("pose_model/sequence/poses", "sequence_poses", np.float32, ("T", "B", 3)),
    ("pose_model/sequence/root_translation", "sequence_root_translation", np.float32, ("T", 3)),
    ("pose_model/sequence/drapes", "sequence_drapes", np.float32, ("T", "V", 3)),
    ("garment/binding/triangles", "binding_triangles", np.int32, ("V", 3)),
    ("garment/binding/barycentric", "binding_barycentric", np.float64, ("V", 3)),
    ("garment/binding/offset", "binding_offset", np.float64, ("V",)),
)
SHAPE_BASES = ("absolute", "skinned_residual")
STRING_FIELDS = (("body/bone_names", "bone_names"), ("body/beta_names", "beta_names"))


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
        for name, attr, dtype, _ in FIELDS + OPTIONAL_FIELDS:
            value = getattr(db, attr)
            if value is None:
                continue
            array = np.ascontiguousarray(value, dtype=dtype)
            big = array.size > 4096
            h5.create_dataset(name, data=array, compression="gzip" if big else None, compression_opts=4 if big else None,
                              shuffle=big)
        for name, attr in STRING_FIELDS:
            h5.create_dataset(name, data=np.array(getattr(db, attr), dtype=h5py.string_dtype()))
        h5["garment/regions"].attrs["region_names"] = json.dumps(list(db.region_names))
        if db.sequence_poses is not None:
            h5["pose_model/sequence"].attrs["fps"] = float(db.sequence_fps)
        h5["anchors"].attrs["shape_basis"] = db.shape_basis
        if db.binding_triangles is not None:
            h5["garment/binding"].attrs["surface"] = db.binding_surface
    partial.replace(path)
    return path


def _check_shape(path, name, array, spec, sizes):
    if array.ndim != len(spec):
        raise DatabaseError(f"{path}: field '{name}' has {array.ndim} dimensions, expected {len(spec)} {spec}")
    for axis, (want, got) in enumerate(zip(spec, array.shape)):
        if isinstance(want, int):
            if got != want:
                raise DatabaseError(f"{path}: field '{name}' axis {axis} has size {got}, expected {want}")
        elif sizes.setdefault(want, got) != got:
            raise DatabaseError(f"{path}: field '{name}' axis {axis} ({want}) has size {got}, but other fields "
                                f"say {want} = {sizes[want]}")


def read_database(path) -> Database:
    """Load and validate a database; raises DatabaseError naming the file and the offending field."""
    path = Path(path)
    if not path.is_file():
        raise DatabaseError(f"{path}: database file not found (build one with `agentdress build`)")
    try:
        h5 = h5py.File(path, "r")
    except OSError as error:
        raise DatabaseError(f"{path}: not a readable HDF5 file ({error})") from None
    with h5:
        version = h5.attrs.get("schema_version")
        if version != SCHEMA_VERSION:
            raise DatabaseError(f"{path}: schema_version is {version}, this reader understands {SCHEMA_VERSION}")
        values, sizes = {}, {}
        for fields, required in ((FIELDS, True), (OPTIONAL_FIELDS, False)):
            for name, attr, dtype, spec in fields:
                if name not in h5:
                    if required:
                        raise DatabaseError(f"{path}: required field '{name}' is missing")
                    continue
                try:
                    array = np.asarray(h5[name][()], dtype=dtype)
                except (OSError, ValueError, TypeError) as error:
                    raise DatabaseError(f"{path}: field '{name}' cannot be read ({error})") from None
                _check_shape(path, name, array, spec, sizes)
                if array.dtype.kind == "f" and not np.isfinite(array).all():
                    raise DatabaseError(f"{path}: field '{name}' contains non-finite values")
                values[attr] = array
        for name, attr in STRING_FIELDS:
            if name not in h5:
                raise DatabaseError(f"{path}: required field '{name}' is missing")
            values[attr] = tuple(s.decode() if isinstance(s, bytes) else str(s) for s in h5[name][()])
        if len(values["bone_names"]) != sizes["B"] or sizes["D"] != 3 * sizes["B"]:
            raise DatabaseError(f"{path}: field 'body/bone_names' has {len(values['bone_names'])} bones, "
                                f"other fields say B = {sizes['B']}, D = {sizes['D']}")
        if sizes["Q"] != 2 * sizes["P"] + 1:
            raise DatabaseError(f"{path}: field 'anchors/ridge' has {sizes['Q']} features, expected 2P+1 = "
                                f"{2 * sizes['P'] + 1}")
        if values["faces"].min() < 0 or values["faces"].max() >= sizes["V"]:
            raise DatabaseError(f"{path}: field 'garment/faces' indexes outside the {sizes['V']} vertices")
        if values["skin_indices"].min() < 0 or values["skin_indices"].max() >= sizes["B"]:
            raise DatabaseError(f"{path}: field 'garment/skin_indices' names bones outside 0..{sizes['B'] - 1}")
        extras = dict(
            garment=str(h5.attrs.get("garment", "")),
            body_model=str(h5.attrs.get("body_model", "")),
            build_command=str(h5.attrs.get("build_command", "")),
            provenance=json.loads(h5.attrs.get("provenance", "{}")),
            region_names=tuple(json.loads(h5["garment/regions"].attrs.get("region_names", "[]"))),
        )
        if "pose_model/sequence" in h5:
            extras["sequence_fps"] = float(h5["pose_model/sequence"].attrs.get("fps", 30.0))
        basis = str(h5["anchors"].attrs.get("shape_basis", "absolute"))
        if basis not in SHAPE_BASES:
            raise DatabaseError(f"{path}: attribute 'anchors/shape_basis' is {basis!r}, expected one of {SHAPE_BASES}")
        extras["shape_basis"] = basis
        if basis == "skinned_residual":
            for name in ("garment/binding/triangles", "garment/binding/barycentric", "garment/binding/offset"):
                if name not in h5:
                    raise DatabaseError(f"{path}: field '{name}' is missing (required by the skinned_residual basis)")
            extras["binding_surface"] = str(h5["garment/binding"].attrs.get("surface", ""))
            if not extras["binding_surface"]:
                raise DatabaseError(f"{path}: attribute 'garment/binding/surface' is missing")
    return Database(**values, **extras)
