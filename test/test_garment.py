"""Garments: templates cut from the body, MakeHuman import, bindings that follow the shape, skin weights, regions."""
import numpy as np
import pytest
import trimesh
from trimesh.grouping import group_rows

from agentdress_ros.body import REFERENCE_SHAPE
from agentdress_ros.garment import (
    REGION_NAMES,
    cut_by_field,
    load_mhclo_garment,
    make_garment,
    read_mhclo,
    refine_to_vertex_count,
)
from agentdress_ros.garment.binding import signed_clearance

from .conftest import shared_path

SHAPES = ([0.0, 2 / 3, 0.2, 0.2, 0.3, 0.5], [1.0, 2 / 3, 0.9, 0.9, 0.9, 0.5], [0.3, 0.9, 0.5, 1.0, 0.1, 0.8])


@pytest.fixture(scope="module")
def garments(body):
    return {name: make_garment(name, body, n_vertices=2500) for name in ("tshirt", "longsleeve", "trousers")}


def boundary_loops(faces):
    edges = trimesh.Trimesh(np.zeros((faces.max() + 1, 3)), faces, process=False).edges_sorted
    boundary = edges[group_rows(edges, require_count=1)]
    # count loops: connected components of the boundary edge graph
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids, inverse = np.unique(boundary, return_inverse=True)
    inverse = inverse.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(inverse)), (inverse[:, 0], inverse[:, 1])), shape=(len(ids), len(ids)))
    degree = np.bincount(inverse.reshape(-1), minlength=len(ids))
    return connected_components(graph, directed=False)[0], degree


@pytest.mark.parametrize("name, holes", [("tshirt", 4), ("longsleeve", 4), ("trousers", 3)])
def test_template_is_one_clean_piece_with_its_openings(garments, body, name, holes):
    garment = garments[name]
    loops, degree = boundary_loops(garment.faces)
    assert loops == holes, "neck, hem and two sleeves; or waist and two cuffs"
    assert (degree == 2).all(), "every boundary is a simple closed loop (clean hem, no bow ties)"
    mesh = trimesh.Trimesh(garment.rest_vertices(body, body.shape()), garment.faces, process=False)
    assert mesh.is_winding_consistent
    assert np.degrees(mesh.face_angles.min()) > 0.2, "no degenerate triangles"


def test_template_hits_the_target_vertex_count(body):
    for target in (1800, 4000):
        assert make_garment("tshirt", body, n_vertices=target).n_vertices == target


def test_hems_lie_at_the_anatomical_places(garments, body):
    shape = body.shape()
    joints = dict(zip(body.bone_names, shape.heads))
    shirt = garments["tshirt"].rest_vertices(body, shape)
    assert shirt[:, 2].min() > joints["LeftUpLeg"][2] - 0.15, "the shirt ends around the hips"
    assert shirt[:, 2].max() < joints["Head"][2], "and below the head"
    assert np.abs(shirt[:, 0]).max() < joints["LeftForeArm"][0], "short sleeves end above the elbow"
    long_sleeve = garments["longsleeve"].rest_vertices(body, shape)
    assert np.abs(long_sleeve[:, 0]).max() > joints["LeftForeArm"][0] + 0.05, "long sleeves pass the elbow"
    trousers = garments["trousers"].rest_vertices(body, shape)
    assert trousers[:, 2].min() == pytest.approx(joints["LeftFoot"][2] + 0.05, abs=0.02)


@pytest.mark.parametrize("name", ["tshirt", "trousers"])
def test_garment_keeps_its_offset_from_the_body_after_a_shape_change(garments, body, name):
    garment = garments[name]
    reference = body.shape(REFERENCE_SHAPE)

    def clearance(shape):
        return signed_clearance(garment.rest_vertices(body, shape), shape.vertices, body.body_faces)

    built = clearance(reference)
    assert np.percentile(built, 1) > 0.0, "the garment is built outside the body"
    assert 0.012 < np.median(built) < 0.03, "with a plausible ease"
    for beta in SHAPES:
        change = np.abs(clearance(body.shape(beta)) - built)
        assert np.percentile(change, 99) < 0.004, f"offset drifts for shape {beta}"
        assert np.median(change) < 0.0005
        assert np.percentile(clearance(body.shape(beta)), 0.5) > 0.003, "and stays outside the body"


def test_skin_weights_and_regions(garments, body):
    shirt = garments["tshirt"]
    np.testing.assert_allclose(shirt.skin_weights.sum(axis=1), 1.0)
    assert shirt.skin_indices.max() < body.n_bones and (shirt.skin_weights >= 0).all()
    np.testing.assert_allclose(shirt.regions.sum(axis=1), 1.0)
    assert shirt.regions.shape[1] == len(REGION_NAMES) == 7
    vertices = shirt.rest_vertices(body, body.shape())
    dominant = np.array(REGION_NAMES)[shirt.regions.argmax(axis=1)]
    assert (vertices[dominant == "left_upper_arm", 0] > 0.12).all(), "the left sleeve is on the left (+x)"
    assert set(dominant) >= {"torso", "left_upper_arm", "right_upper_arm"}
    assert "left_leg" in set(np.array(REGION_NAMES)[garments["trousers"].regions.argmax(axis=1)])


def test_refine_to_vertex_count_is_conforming_and_exact():
    square = trimesh.creation.box().subdivide()
    vertices, faces = refine_to_vertex_count(square.vertices, square.faces, 500)
    assert len(vertices) == 500
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and np.isclose(mesh.area, square.area), "splits add no cracks and keep the surface"


def test_cut_by_field_follows_the_level_set_exactly():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    height = 0.3
    vertices, faces = cut_by_field(sphere.vertices, sphere.faces, sphere.vertices[:, 2] - height)
    assert vertices[:, 2].max() == pytest.approx(height, abs=1e-12)
    loops, degree = boundary_loops(faces)
    assert loops == 1 and (degree == 2).all()
    rim = np.unique(trimesh.Trimesh(vertices, faces, process=False).edges_sorted[
        group_rows(trimesh.Trimesh(vertices, faces, process=False).edges_sorted, require_count=1)])
    np.testing.assert_allclose(vertices[rim, 2], height, atol=1e-12)


def test_mhclo_garments_follow_the_body(body):
    folder = shared_path("garments", "makehuman")
    for path in sorted(folder.glob("*/*.mhclo")):
        garment = load_mhclo_garment(path, body)
        for beta in (REFERENCE_SHAPE, SHAPES[1]):
            shape = body.shape(beta)
            clearance = signed_clearance(garment.rest_vertices(body, shape), shape.vertices, body.body_faces)
            assert 0.002 < np.median(clearance) < 0.03, f"{path.name} sits on the body at {beta}"
        np.testing.assert_allclose(garment.skin_weights.sum(axis=1), 1.0)


def test_mhclo_errors_name_the_file_and_the_problem(tmp_path):
    source = shared_path("garments", "makehuman", "male_casualsuit04")
    text = (source / "male_casualsuit04.mhclo").read_text()
    obj = (source / "male_casualsuit04.obj").read_text()
    (tmp_path / "male_casualsuit04.obj").write_text(obj)
    broken = tmp_path / "broken.mhclo"
    broken.write_text(text.replace("verts 0\n", "verts 0\n1 2 three\n", 1))
    with pytest.raises(ValueError, match=r"broken.mhclo:\d+: expected"):
        read_mhclo(broken)
    short = tmp_path / "short.mhclo"
    short.write_text(text.rsplit("delete_verts", 1)[0].rsplit("\n", 3)[0] + "\n")
    with pytest.raises(ValueError, match="short.mhclo: .* bound vertices but male_casualsuit04.obj has 1696"):
        read_mhclo(short)
    with pytest.raises(FileNotFoundError, match="missing.mhclo"):
        read_mhclo(tmp_path / "missing.mhclo")


def test_dressing_poses_body_and_garments_together(body, garments):
    from agentdress_ros.garment.dressing import Dressing

    dressing = Dressing(body, [garments["tshirt"], garments["trousers"]], dtype=np.float64)
    dressing.pose(np.zeros((body.n_bones, 3)))
    for rest, posed in zip(dressing.garment_rest, dressing.garment_vertices):
        np.testing.assert_allclose(posed, rest, atol=1e-12)
    # a rotated forearm carries the long-sleeve cuff with it, rigidly where the sleeve is bound to it alone
    sleeve = Dressing(body, [garments["longsleeve"]], dtype=np.float64)
    forearm = body.bone_index("LeftForeArm")
    rotvecs = np.zeros((body.n_bones, 3))
    rotvecs[forearm] = [0.0, 0.0, 1.2]
    transforms = sleeve.pose(rotvecs)
    garment = garments["longsleeve"]
    rigid = (garment.skin_indices[:, 0] == forearm) & (garment.skin_weights[:, 0] == 1.0)
    assert rigid.sum() > 20
    rest = sleeve.garment_rest[0][rigid]
    expected = rest @ transforms[forearm, :, :3].T + transforms[forearm, :, 3]
    np.testing.assert_allclose(sleeve.garment_vertices[0][rigid], expected, atol=1e-12)
    # a new shape refits the garments and keeps the buffers' sizes
    sleeve.set_shape([1.0, 0.7, 0.9, 0.9, 0.9, 0.5])
    assert sleeve.garment_vertices[0].shape == (garment.n_vertices, 3)


def test_largest_face_corners_give_each_vertex_its_largest_faces_outward_normal():
    """On a closed convex mesh, (p_next - p) x (p_previous - p) of every vertex's corners points outward and is the
    normal of the largest face at that vertex, stretched or not (the body projection poses these corners)."""
    from agentdress_ros.garment.binding import largest_face_corners

    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices = mesh.vertices * [1.0, 2.0, 0.5]  # unequal faces
    faces = np.asarray(mesh.faces)
    corners = largest_face_corners(vertices, faces)
    normals = np.cross(vertices[corners[:, 0]] - vertices, vertices[corners[:, 1]] - vertices)
    assert ((normals * vertices).sum(axis=1) > 0).all()  # outward
    areas = np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                    vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    for v in range(len(vertices)):
        incident = np.flatnonzero((faces == v).any(axis=1))
        assert set(corners[v]) | {v} == set(faces[incident[areas[incident].argmax()]])
    lonely = largest_face_corners(np.vstack([vertices, [[9.0, 9.0, 9.0]]]), faces)
    assert (lonely[-1] == len(vertices)).all()  # a vertex of no face names itself: a zero normal
