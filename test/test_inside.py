"""Inside-the-body test by generalised winding number (agentdress_ros.garment.inside), against analytic truth."""
import numpy as np
import trimesh

from agentdress_ros.garment.inside import inside_report, self_overlapping_vertices, winding_numbers


def _sphere(centre, radius=1.0):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return mesh.vertices + np.asarray(centre, dtype=float), mesh.faces


def arms_down(body) -> np.ndarray:
    """(B, 3) rotation vectors: Anny's arms pressed down into the torso (the skinned body overlaps itself there)."""
    pose = np.zeros((body.n_bones, 3))
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        pose[body.bone_index(f"{side}Arm")] = (0.0, sign * 0.9, 0.0)
    return pose


def test_winding_number_is_one_inside_and_zero_outside_a_sphere():
    vertices, faces = _sphere((0.0, 0.0, 0.0))
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, -0.3], [0.0, 0.0, 0.95], [1.05, 0.0, 0.0], [3.0, 2.0, 1.0]])
    w = winding_numbers(points, vertices, faces, exact=True)
    np.testing.assert_allclose(w[:3], 1.0, atol=1e-6)
    np.testing.assert_allclose(w[3:], 0.0, atol=1e-6)
    np.testing.assert_allclose(winding_numbers(points, vertices, faces), w, atol=0.02)  # far clusters as dipoles


def test_winding_number_counts_overlapping_parts_and_flags_the_overlap():
    """Two interpenetrating spheres in one mesh (a skinned arm inside the torso): w = 2 in the overlap, and exactly
    the vertices of each sphere that lie inside the other are self-overlapping."""
    va, fa = _sphere((0.0, 0.0, 0.0))
    vb, fb = _sphere((1.5, 0.0, 0.0))
    vertices = np.vstack([va, vb])
    faces = np.vstack([fa, fb + len(va)])
    points = [[0.75, 0.0, 0.0], [-0.5, 0.0, 0.0], [2.0, 0.0, 0.0], [0.75, 0.0, 3.0]]
    np.testing.assert_allclose(winding_numbers(points, vertices, faces, exact=True), [2.0, 1.0, 1.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(winding_numbers(points, vertices, faces), [2.0, 1.0, 1.0, 0.0], atol=0.02)
    overlap = self_overlapping_vertices(vertices, faces)
    expected = np.concatenate([np.linalg.norm(va - (1.5, 0.0, 0.0), axis=1) < 1.0,
                               np.linalg.norm(vb, axis=1) < 1.0])
    # vertices within the lift distance (1 mm) of the other surface may go either way
    near = np.abs(np.concatenate([np.linalg.norm(va - (1.5, 0.0, 0.0), axis=1),
                                  np.linalg.norm(vb, axis=1)]) - 1.0) < 2e-3
    assert np.array_equal(overlap[~near], expected[~near])
    assert expected.sum() > 20


def test_inside_report_separates_trapped_from_truly_inside_points():
    va, fa = _sphere((0.0, 0.0, 0.0))
    vb, fb = _sphere((1.5, 0.0, 0.0))
    vertices = np.vstack([va, vb])
    faces = np.vstack([fa, fb + len(va)])
    points = np.array([[0.75, 0.3, 0.0],  # in the overlap, next to overlapping surface: trapped
                       [-0.6, 0.0, 0.0],  # deep in the left sphere, far from the overlap: truly inside
                       [0.0, 0.0, 1.2]])  # outside
    report = inside_report(points, vertices, faces, radius=0.3)  # unit spheres: vertices ~0.15 apart
    assert report["inside"].tolist() == [True, True, False]
    assert report["truly_inside"].tolist() == [False, True, False]
    assert (report["inside_count"], report["overlap_count"], report["truly_inside_count"]) == (2, 1, 1)


def test_anny_at_rest_does_not_overlap_itself_where_garments_go_but_arms_down_it_does(body):
    from agentdress_ros.body import visible_body

    ids, faces = visible_body(body)
    shape = body.shape()
    rest = body.posed_vertices(shape, body.pose(shape, np.zeros((body.n_bones, 3)))[0])[ids]
    # The template itself overlaps only where no garment goes (inside the mouth, between the toes).
    garment_bones = [i for i, name in enumerate(body.bone_names) if "Toe" not in name and name != "Head"]
    on_garment_bones = np.isin(body.skin_indices[ids, 0], garment_bones)
    assert (self_overlapping_vertices(rest, faces) & on_garment_bones).sum() == 0
    pose = arms_down(body)
    posed = body.posed_vertices(shape, body.pose(shape, pose)[0])[ids]
    assert (self_overlapping_vertices(posed, faces) & on_garment_bones).sum() > 20


def test_clustered_winding_numbers_classify_like_the_exact_sum_on_a_self_overlapping_body(body):
    """Cloth-like points around Anny in an arms-down pose (arm passing into the torso) and random points in its
    box: the dipole far field stays within 0.02 of the exact sum, so no point changes side of 0.5 (or of 1.5)."""
    from agentdress_ros.garment.inside import BodyInside
    from agentdress_ros.body import visible_body

    ids, faces = visible_body(body)
    shape = body.shape()
    pose = arms_down(body)
    posed = body.posed_vertices(shape, body.pose(shape, pose)[0])[ids]
    rng = np.random.default_rng(0)
    surface = posed[rng.choice(len(posed), 600)] + rng.normal(0.0, 0.02, (600, 3))
    points = np.vstack([surface, rng.uniform(posed.min(axis=0) - 0.1, posed.max(axis=0) + 0.1, (200, 3))])
    exact = winding_numbers(points, posed, faces, exact=True)
    fast = winding_numbers(points, posed, faces)
    assert np.abs(fast - exact).max() < 0.02
    assert np.array_equal(fast > 0.5, exact > 0.5) and np.array_equal(fast > 1.5, exact > 1.5)
    assert (exact > 1.5).sum() > 0 and (exact > 0.5).sum() > 50  # the overlap and the inside are both sampled
    test = BodyInside(posed, faces)  # reused across point sets: the same answer as a fresh report
    for chunk in (points[:300], points[300:]):
        assert {k: v for k, v in test.report(chunk).items() if k.endswith("count")} == \
            {k: v for k, v in inside_report(chunk, posed, faces).items() if k.endswith("count")}


def _two_spheres():
    va, fa = _sphere((0.0, 0.0, 0.0))
    vb, fb = _sphere((1.5, 0.0, 0.0))
    return np.vstack([va, vb]), np.vstack([fa, fb + len(va)])


def test_the_split_is_part_aware_inside_one_part_near_the_overlap_is_truly_inside():
    """Unit spheres centred 1.5 apart (an arm sunk into the torso): their overlap is the lens 0.5 < x < 1 on the
    axis. A point inside the left sphere only is truly inside unless it sits within `radius` of the surface of the
    overlap (the part of the right sphere's surface inside the left, whose tip is x = 0.5); a point inside both is
    in the overlap wherever it is."""
    vertices, faces = _two_spheres()
    points = np.array([[0.75, 0.0, 0.0],  # the lens' centre: inside both parts
                       [0.48, 0.0, 0.0],  # inside the left sphere only, 2 cm from the lens' tip (x = 0.5)
                       [0.45, 0.0, 0.0],  # inside the left sphere only, 5 cm from the lens
                       [0.30, 0.0, 0.0]])  # 20 cm from the lens
    # the old rule (any overlapping body vertex within 3 cm) would have called the first three trapped; with the
    # radius at 1 cm (the spheres' scale is a body's x 10 here) only the lens and its 1 cm shell are
    report = inside_report(points, vertices, faces, radius=0.01)
    assert report["inside"].all()
    np.testing.assert_allclose(report["winding"], [2.0, 1.0, 1.0, 1.0], atol=0.02)
    # (the facetted spheres put the lens' tip up to ~5 mm right of 0.5, so the distances are 2-2.5 and 5-5.5 cm)
    assert report["in_overlap"].tolist() == [True, False, False, False]
    wider = inside_report(points, vertices, faces, radius=0.08)
    assert wider["in_overlap"].tolist() == [True, True, True, False]  # within 8 cm of the overlap's surface


def test_the_split_on_anny_arms_down(body):
    """Anny with the arms pressed into the torso, where the overlap is known: points on the arm's sunken surface
    (inside the torso) are trapped; points 1.5 cm under the skin of the belly, of the back and of the outer upper
    arm (inside one part, far from the overlap) went through the skin."""
    from agentdress_ros.garment.binding import vertex_normals
    from agentdress_ros.garment.inside import BodyInside
    from agentdress_ros.body.model import visible_body

    ids, faces = visible_body(body)
    shape = body.shape()
    pose = arms_down(body)
    posed = body.posed_vertices(shape, body.pose(shape, pose)[0])[ids]
    normals = vertex_normals(posed, faces)
    sunk = np.flatnonzero(self_overlapping_vertices(posed, faces))
    test = BodyInside(posed, faces)
    # on the sunken surface itself, 1 mm out along its own normal (still inside the other part): trapped
    trapped = test.report(posed[sunk] + 1e-3 * normals[sunk])
    assert trapped["inside_count"] >= 0.95 * len(sunk)
    assert trapped["overlap_count"] == trapped["inside_count"]
    # 1.5 cm under the skin, at vertices 10 cm or more from any sunken vertex
    from scipy.spatial import cKDTree

    far = cKDTree(posed[sunk]).query(posed, k=1)[0] > 0.10
    bone = body.skin_indices[ids, 0]
    picks = []
    for name in ("Spine1", "LeftArm", "RightArm"):
        candidates = np.flatnonzero(far & (bone == body.bone_index(name)))
        picks.append(candidates[:: max(1, len(candidates) // 20)])
    picks = np.concatenate(picks)
    under = test.report(posed[picks] - 0.015 * normals[picks])
    assert under["inside_count"] >= 0.9 * len(picks)
    assert under["overlap_count"] == 0  # none of them is called trapped
