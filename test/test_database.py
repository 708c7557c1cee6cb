"""The HDF5 database: round trip, atomic write, and errors that name the file and the field."""
import json
import re
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from agentdress_ros.engine.database import (FIELDS, OPTIONAL_FIELDS, Codec, Database, DatabaseError, codecs,
                                            create_dataset, read_database, register_codec, shape_features,
                                            write_database)
from agentdress_ros.engine.pose_models import POSE_MODELS, register_pose_model

SHIPPED = Path(__file__).resolve().parents[1] / "data" / "tshirt_default.h5"


def tiny_database(n_vertices=12, n_anchors=3, n_components=2, seed=0, full=False) -> Database:
    """A small valid database; `full` adds every optional field (sequence, surface binding)."""
    rng = np.random.default_rng(seed)
    v, b, p, k, m, t = n_vertices, 31, 6, 5, 4, 3
    components = rng.normal(size=(n_anchors, n_components, v, 3))
    components /= np.linalg.norm(components.reshape(n_anchors, n_components, -1), axis=2)[:, :, None, None]
    optional = {} if not full else dict(
        sequence_poses=rng.normal(size=(t, b, 3)), sequence_root_translation=rng.normal(size=(t, 3)),
        sequence_drapes=rng.normal(size=(t, v, 3)), sequence_fps=30.0, shape_basis="skinned_residual",
        binding_triangles=rng.integers(0, 1000, size=(v, 3)), binding_barycentric=np.full((v, 3), 1 / 3),
        binding_offset=np.full(v, 0.01), binding_surface="body")
    return Database(
        garment="tshirt",
        faces=np.array([[0, 1, 2], [2, 3, 0]], dtype=np.int32),
        rest=rng.normal(size=(v, 3)),
        skin_indices=rng.integers(0, b, size=(v, 4)),
        skin_weights=np.full((v, 4), 0.25),
        regions=np.full((v, 7), 1 / 7),
        region_names=("torso", "a", "b", "c", "d", "e", "f"),
        bone_names=tuple(f"bone{i}" for i in range(b)),
        parents=np.arange(-1, b - 1),
        beta_names=("gender", "age", "muscle", "weight", "height", "proportions"),
        beta0=np.full(p, 0.5),
        beta_range=np.tile([0.1, 0.9], (p, 1)),
        beta_scale=np.full(p, 0.2),
        joint_weights=rng.uniform(size=3 * b),
        region_dof=rng.uniform(size=(7, 3 * b)),
        anchor_poses=rng.normal(size=(n_anchors, b, 3)),
        training_betas=rng.uniform(size=(k, p)),
        pca_mean=rng.normal(size=(n_anchors, v, 3)),
        pca_components=components,
        ridge=rng.normal(size=(n_anchors, 2 * p + 1, n_components)),
        explained_variance_ratio=np.full((n_anchors, n_components), 0.5),
        example_poses=rng.normal(size=(m, b, 3)),
        example_drapes=rng.normal(size=(m, v, 3)),
        provenance={"note": "test"},
        build_command="agentdress build --anchors 3",
        **optional,
    )


def test_round_trip_keeps_every_field(tmp_path):
    db = tiny_database()
    path = write_database(tmp_path / "db.h5", db)
    back = read_database(path)
    assert back.garment == "tshirt" and back.bone_names == db.bone_names and back.region_names == db.region_names
    np.testing.assert_allclose(back.pca_components, db.pca_components.astype(np.float32))
    np.testing.assert_array_equal(back.faces, db.faces)
    assert back.provenance == {"note": "test"} and back.build_command == db.build_command
    assert back.sequence_drapes is None
    assert not list(tmp_path.glob("*.partial")), "the temporary file is renamed away"


def test_shape_features_are_the_papers_standardised_units():
    beta0, scale = np.full(6, 0.5), np.full(6, 0.2)
    features = shape_features([0.9, 0.5, 0.5, 0.5, 0.5, 0.1], beta0, scale)
    np.testing.assert_allclose(features[0, :6], [2, 0, 0, 0, 0, -2])
    np.testing.assert_allclose(features[0, 6:12], [4, 0, 0, 0, 0, 4])
    assert features[0, 12] == 1.0


def test_missing_file_is_named(tmp_path):
    with pytest.raises(DatabaseError, match="nowhere.h5: database file not found"):
        read_database(tmp_path / "nowhere.h5")


def test_non_hdf5_file_is_named(tmp_path):
    path = tmp_path / "junk.h5"
    path.write_bytes(b"not an hdf5 file at all")
    with pytest.raises(DatabaseError, match="junk.h5: not a readable HDF5 file"):
        read_database(path)


def _replace(h5, name, data=None, **create):
    """Put `data` (or an empty dataset made with `create`) where field `name` was, keeping its attributes."""
    attrs = dict(h5[name].attrs) if name in h5 else {}
    if name in h5:
        del h5[name]
    dataset = h5.create_dataset(name, data=data, **create)
    dataset.attrs.update(attrs)


def _set(name, index, value, dtype=None):
    def mutate(h5):
        data = h5[name][()].astype(dtype or h5[name].dtype)
        data[index] = value
        _replace(h5, name, data)
    return mutate


def _field(name):
    return f"field '{re.escape(name)}'"


def _broken_fields():
    """(id, mutate(h5), message) for every dataset: wrong dtype kind, wrong shape, out of range, non-finite,
    oversized, missing."""
    good = tiny_database(full=True)
    cases = []
    for name, attr, dtype, spec, (low, high) in FIELDS + OPTIONAL_FIELDS:
        value = np.asarray(getattr(good, attr), dtype=dtype)
        integer = value.dtype.kind == "i"
        field = _field(name)
        first = (0,) * value.ndim
        other = value.astype(np.float64 if integer else np.int32)
        cases += [
            (f"{name}:dtype", lambda h5, n=name, d=other: _replace(h5, n, d), f"{field} has dtype"),
            (f"{name}:strings", lambda h5, n=name, v=value: _replace(h5, n, np.full(v.shape, "x", dtype=object),
                                                                     dtype=h5py.string_dtype()), f"{field} has dtype"),
            (f"{name}:extra-axis", lambda h5, n=name, v=value: _replace(h5, n, v[..., None]),
             f"{field} has {value.ndim + 1} dimensions"),
            (f"{name}:short-axis", lambda h5, n=name, v=value: _replace(h5, n, v[..., :-1]), f".*{field}"),
            (f"{name}:oversized", lambda h5, n=name, v=value: _replace(
                h5, n, shape=(2**31 // v[0].nbytes + 1,) + v.shape[1:], dtype=v.dtype, chunks=True),
             f"{field} declares shape .* MiB"),
        ]
        if integer:
            if high is not None:  # an index: one past the last
                cases.append((f"{name}:range", _set(name, first, 10**6),
                              f"{field} has values outside"))
            cases += [(f"{name}:below", _set(name, first, low - 1), f"{field} has values outside"),
                      # an int64 that an int32 cast would wrap onto a valid index
                      (f"{name}:wraps", _set(name, first, 2**32 + 1, np.int64), f"{field} has values outside")]
        else:
            bad = low - 1.0 if high is None else 2.0 * high + 1.0
            cases += [(f"{name}:range", _set(name, first, bad), f"{field} has values outside")]
            cases += [(f"{name}:{v}", _set(name, first, v), f"{field} contains non-finite")
                      for v in (np.nan, np.inf, -np.inf)]
        if any(name == f[0] for f in FIELDS):
            cases.append((f"{name}:missing", lambda h5, n=name: h5.__delitem__(n),
                          f"required field '{re.escape(name)}' is missing"))
        elif name.startswith("garment/binding"):  # required by the database's skinned_residual basis
            cases.append((f"{name}:missing", lambda h5, n=name: h5.__delitem__(n),
                          f"{field} is missing \\(required by the skinned_residual basis"))
    return cases


def _set_attr(owner, key, value):
    def mutate(h5):
        (h5[owner] if owner else h5).attrs[key] = value
    return mutate


def _del_attr(owner, key):
    def mutate(h5):
        del (h5[owner] if owner else h5).attrs[key]
    return mutate


BROKEN_RELATIONS = [
    ("skin weights sum", _set("garment/skin_weights", (0, 0), 0.5), "field 'garment/skin_weights' rows must sum to 1"),
    ("barycentric sum", _set("garment/binding/barycentric", (3, 1), 0.9),
     "field 'garment/binding/barycentric' rows must sum to 1: row 3"),
    ("region sum", _set("garment/regions", (2, slice(None)), 0.5),
     "field 'garment/regions' rows must sum to at most 1"),
    ("variance sum", _set("anchors/explained_variance_ratio", (1, slice(None)), 0.9),
     "field 'anchors/explained_variance_ratio' rows must sum to at most 1: anchor 1"),
    ("root parent", _set("body/parents", 0, 0), "field 'body/parents' must list the root first"),
    ("parent after child", _set("body/parents", 5, 7), "field 'body/parents' .* bone 5 has parent 7"),
    ("beta_scale zero", _set("body/beta_scale", 2, 0.0), "field 'body/beta_scale' must be > 0"),
    ("beta_range order", _set("body/beta_range", 3, [0.8, 0.2]), "field 'body/beta_range' row 3 has low 0.8 > high"),
    ("beta0 outside range", _set("body/beta_range", 1, [0.6, 0.9]), "field 'body/beta0' value 0.5 at index 1 lies "
                                                                    "outside beta_range"),
    ("float32 overflow", _set("sensitivity/joint_weights", 4, 1e300, np.float64),
     "field 'sensitivity/joint_weights' has values beyond the float32 range"),
    ("pose dofs", lambda h5: (_replace(h5, "sensitivity/joint_weights", h5["sensitivity/joint_weights"][:90]),
                              _replace(h5, "sensitivity/region_dof", h5["sensitivity/region_dof"][:, :90])),
     "field 'sensitivity/joint_weights' has 90 pose dofs, expected 3 per bone = 93"),
    ("ridge features", lambda h5: _replace(h5, "anchors/ridge", h5["anchors/ridge"][:, :12]),
     "field 'anchors/ridge' has 12 features, expected 2P\\+1 = 13"),
    ("faces index", _set("garment/faces", (0, 0), 12), "field 'garment/faces' has values outside \\[0, 11\\]: 12"),
    ("group for a dataset", lambda h5: (h5.__delitem__("garment/rest"), h5.create_group("garment/rest")),
     "field 'garment/rest' is a group, not a dataset"),
    ("bone names numbers", lambda h5: _replace(h5, "body/bone_names", np.arange(31)),
     "field 'body/bone_names' has dtype"),
    ("bone names repeated", lambda h5: _replace(h5, "body/bone_names", np.array(["b"] * 31, dtype=object),
                                                dtype=h5py.string_dtype()),
     "field 'body/bone_names' has empty or repeated"),
    ("beta names count", lambda h5: _replace(h5, "body/beta_names", h5["body/beta_names"][:5]),
     "field 'body/beta_names' has 5 names, but field 'body/beta0' says P = 6"),
    ("beta names missing", lambda h5: h5.__delitem__("body/beta_names"), "required field 'body/beta_names' is missing"),
    ("bone names as a matrix", lambda h5: _replace(h5, "body/bone_names", np.array([["a"] * 31] * 2, dtype=object),
                                                   dtype=h5py.string_dtype()), "field 'body/bone_names' has shape"),
    ("provenance JSON", _set_attr("", "provenance", "{not json"), "attribute 'provenance' is not valid JSON"),
    ("provenance list", _set_attr("", "provenance", "[1, 2]"), "attribute 'provenance' is JSON list, expected dict"),
    ("provenance number", _set_attr("", "provenance", 3), "attribute 'provenance' is int64 3, expected text"),
    ("region names JSON", _set_attr("garment/regions", "region_names", "[\"a\""),
     "attribute 'garment/regions/region_names' is not valid JSON"),
    ("region count", _set_attr("garment/regions", "region_names", json.dumps(list("abcdef"))),
     "attribute 'garment/regions/region_names' has .* expected the names of the 7 regions"),
    ("schema text", _set_attr("", "schema_version", "1"), "schema_version is 1, this reader understands"),
    ("schema array", _set_attr("", "schema_version", [1, 1]), "schema_version is \\[1 1\\]"),
    ("schema missing", _del_attr("", "schema_version"), "schema_version is None"),
    ("garment name missing", _del_attr("", "garment"), "attribute 'garment' is missing"),
    ("garment name empty", _set_attr("", "garment", ""), "attribute 'garment' is empty"),
    ("garment name bytes", _set_attr("", "garment", np.void(b"\xff\xfe")), "attribute 'garment' is void"),
    ("shape basis", _set_attr("anchors", "shape_basis", "other"), "attribute 'anchors/shape_basis' is 'other'"),
    ("binding surface", _del_attr("garment/binding", "surface"), "attribute 'garment/binding/surface' is missing"),
    ("fps negative", _set_attr("pose_model/sequence", "fps", -30.0), "attribute 'pose_model/sequence/fps' is -30"),
    ("fps NaN", _set_attr("pose_model/sequence", "fps", np.nan), "attribute 'pose_model/sequence/fps' is nan"),
    ("fps text", _set_attr("pose_model/sequence", "fps", "fast"), "attribute 'pose_model/sequence/fps' is 'fast'"),
]


@pytest.fixture(scope="module")
def good_file(tmp_path_factory):
    return write_database(tmp_path_factory.mktemp("good") / "db.h5", tiny_database(full=True))


@pytest.mark.parametrize("mutate, message", [case[1:] for case in _broken_fields() + BROKEN_RELATIONS],
                         ids=[case[0] for case in _broken_fields() + BROKEN_RELATIONS])
def test_broken_database_corpus_gives_named_errors(good_file, tmp_path, mutate, message):
    """Each broken copy of a good database (every optional field present) fails with a DatabaseError that names the
    file, the field and what is wrong; nothing else escapes (no crash, no silent cast)."""
    path = tmp_path / "db.h5"
    path.write_bytes(good_file.read_bytes())
    with h5py.File(path, "r+") as h5:
        mutate(h5)
    assert path.stat().st_size < 2**20, "oversized datasets are declared, not written"
    with pytest.raises(DatabaseError, match=f"db.h5: {message}"):
        read_database(path)


def test_the_good_database_of_the_corpus_reads(good_file):
    db = read_database(good_file)
    assert db.shape_basis == "skinned_residual" and db.sequence_drapes.shape == (3, 12, 3)
    assert db.binding_surface == "body" and db.sequence_fps == 30.0


@pytest.mark.parametrize("fraction", [0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99])
def test_truncated_file_is_named(tmp_path, fraction):
    path = write_database(tmp_path / "db.h5", tiny_database(n_vertices=3000, full=True))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(DatabaseError, match="db.h5: "):
        read_database(path)


def test_dataset_cap_is_a_parameter(tmp_path):
    path = write_database(tmp_path / "db.h5", tiny_database())
    with pytest.raises(DatabaseError, match="field 'garment/faces' declares shape \\(2, 3\\) .* more than"):
        read_database(path, max_dataset_bytes=16)


# ---------------------------------------------------------------- a pose model that stores a group of its own

TOY_GROUP = "pose_model/toy"


class ToyShiftPoseModel:
    """The garment's rest shape moved by one stored rest-frame vector (3,): the smallest pose model with arrays of
    its own. It and its codec live in this file alone; registering them is all it takes."""

    name = "toy"
    skinned = True

    def __init__(self, context):
        if context.db.toy is None:
            raise ValueError("pose model 'toy' needs a database with pose_model/toy")
        self.rest = np.ascontiguousarray((context.db.rest + context.db.toy).T, dtype=context.dtype)

    def evaluate(self, theta, root, frame):
        return self.rest


def _write_toy(h5, shift):
    create_dataset(h5.require_group(TOY_GROUP), "shift", np.asarray(shift, dtype=np.float32))


def _read_toy(reader):
    array = reader.numeric(TOY_GROUP + "/shift", np.float32, (3,))
    reader.check_range(TOY_GROUP + "/shift", array, (-1.0, 1.0), np.float32)
    return reader.cast(array, np.float32)


def _read_toy_v1(reader):
    """Format version 1 stored the shift in centimetres."""
    array = reader.numeric(TOY_GROUP + "/shift_cm", np.float32, (3,))
    reader.check_range(TOY_GROUP + "/shift_cm", array, (-100.0, 100.0), np.float32)
    return reader.cast(array / 100.0, np.float32)


@pytest.fixture
def toy_model():
    codec = register_codec(Codec("toy", TOY_GROUP, 2, _write_toy, _read_toy, upgrade="agentdress toy --database FILE",
                                 migrations={1: _read_toy_v1}))
    register_pose_model("toy")(ToyShiftPoseModel)
    yield codec
    codecs().pop("toy")
    POSE_MODELS.pop("toy")


SHIFT = np.array([0.01, -0.02, 0.03], dtype=np.float32)


def test_a_pose_model_registers_its_own_storage(tmp_path, toy_model):
    """write_database and read_database carry the toy group through its codec, with its format version, and a
    database without it reads None."""
    path = write_database(tmp_path / "db.h5", replace(tiny_database(), toy=SHIFT))
    with h5py.File(path, "r") as h5:
        assert h5[TOY_GROUP].attrs["format_version"] == 2
    np.testing.assert_array_equal(read_database(path).toy, SHIFT)
    assert read_database(write_database(tmp_path / "plain.h5", tiny_database())).toy is None
    with pytest.raises(TypeError, match="no field or stored model \\['tooy'\\]"):
        replace(tiny_database(), tooy=SHIFT)


def test_the_toy_pose_model_runs_in_the_engine(toy_model):
    from agentdress_ros.body import AnnyBody
    from agentdress_ros.engine import Engine, EngineConfig
    from agentdress_ros.engine.synthetic import make_synthetic_database

    body = AnnyBody()
    db = replace(make_synthetic_database(1200, 12, n_examples=6, n_sequence=5, seed=3, body=body), toy=SHIFT)
    rest_pose = np.zeros((len(db.bone_names), 3))
    outputs = {name: Engine(db, body, EngineConfig(pose_model=name, shape_model=False)).pose_model_output(rest_pose)
               for name in ("toy", "lbs")}
    np.testing.assert_allclose(outputs["toy"] - outputs["lbs"], np.broadcast_to(SHIFT, outputs["lbs"].shape),
                               atol=1e-6)


def test_an_older_format_version_is_migrated(tmp_path, toy_model):
    path = write_database(tmp_path / "db.h5", tiny_database())
    with h5py.File(path, "r+") as h5:
        group = h5.create_group(TOY_GROUP)
        group.create_dataset("shift_cm", data=SHIFT * 100)
        group.attrs["format_version"] = 1
    np.testing.assert_allclose(read_database(path).toy, SHIFT, rtol=1e-6)


@pytest.mark.parametrize("version", [3, 0])
def test_an_unknown_format_version_is_refused_with_the_upgrade(tmp_path, toy_model, version):
    path = write_database(tmp_path / "db.h5", replace(tiny_database(), toy=SHIFT))
    with h5py.File(path, "r+") as h5:
        h5[TOY_GROUP].attrs["format_version"] = version
    with pytest.raises(DatabaseError, match=f"db.h5: group '{TOY_GROUP}' has format version {version}, this reader "
                                            "reads version 2 \\(and migrates version 1\\): rewrite it with "
                                            "`agentdress toy --database FILE`"):
        read_database(path)


def test_a_shipped_group_of_another_version_names_its_command(tmp_path):
    """The shipped databases' groups carry no format_version (version 1, what they read as); one marked 2 is refused
    naming the command that retrains it."""
    path = tmp_path / "tshirt.h5"
    path.write_bytes(SHIPPED.read_bytes())
    with h5py.File(path, "r+") as h5:
        assert "format_version" not in h5["pose_model/regressor"].attrs
        h5["pose_model/regressor"].attrs["format_version"] = 2
    with pytest.raises(DatabaseError, match="group 'pose_model/regressor' has format version 2, this reader reads "
                                            "version 1: rewrite it with `agentdress lab regressor --database FILE"):
        read_database(path)
