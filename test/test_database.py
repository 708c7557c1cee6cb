"""The HDF5 database: round trip, atomic write, and errors that name the file and the field."""
import h5py
import numpy as np
import pytest

from agentdress_ros.engine.database import Database, DatabaseError, read_database, shape_features, write_database


def tiny_database(n_vertices=12, n_anchors=3, n_components=2, seed=0) -> Database:
    rng = np.random.default_rng(seed)
    v, b, p, k, m = n_vertices, 31, 6, 5, 4
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
        pca_components=rng.normal(size=(n_anchors, n_components, v, 3)),
        ridge=rng.normal(size=(n_anchors, 2 * p + 1, n_components)),
        explained_variance_ratio=np.full((n_anchors, n_components), 0.5),
        example_poses=rng.normal(size=(m, b, 3)),
        example_drapes=rng.normal(size=(m, v, 3)),
        provenance={"note": "test"},
        build_command="agentdress build --anchors 3",
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


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda h5: h5.__delitem__("anchors/ridge"), "required field 'anchors/ridge' is missing"),
        (lambda h5: h5.attrs.__setitem__("schema_version", 99), "schema_version is 99"),
        (lambda h5: (h5.__delitem__("anchors/mean"), h5.create_dataset("anchors/mean", data=np.zeros((3, 11, 3)))),
         "field 'anchors/mean' axis 1 \\(V\\) has size 11"),
        (lambda h5: h5["garment/rest"].__setitem__((0, 0), np.nan), "field 'garment/rest' contains non-finite"),
        (lambda h5: h5["garment/faces"].__setitem__((0, 0), 99), "field 'garment/faces' indexes outside"),
    ],
)
def test_corrupt_fields_are_named(tmp_path, mutate, message):
    path = write_database(tmp_path / "db.h5", tiny_database())
    with h5py.File(path, "r+") as h5:
        mutate(h5)
    with pytest.raises(DatabaseError, match=f"db.h5: {message}"):
        read_database(path)


def test_truncated_file_is_named(tmp_path):
    path = write_database(tmp_path / "db.h5", tiny_database(n_vertices=3000))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatabaseError, match="db.h5"):
        read_database(path)
