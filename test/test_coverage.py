"""No skin through the cloth: the body faces a garment covers, the band kept under its edges, MakeHuman delete_verts."""
import numpy as np
import pytest

from agentdress_ros.garment import make_garment, read_mhclo
from agentdress_ros.garment.binding import region_weights
from agentdress_ros.garment.coverage import (
    body_part_labels,
    boundary_distance,
    cloth_over,
    cover_depth,
    covered_faces,
    garment_covered_faces,
    poke_through,
    sloped,
    surface_side,
    tuck_depth,
)

from .conftest import shared_path


def grid(n: int, size: float, z: float = 0.0, flip: bool = False):
    """A flat square (n x n vertices, side `size`, centred at the origin, at height z) of triangles facing +z."""
    u = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.full(n * n, z)], axis=1)
    ids = np.arange(n * n).reshape(n, n)
    a, b, c, d = ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return vertices, (faces[:, ::-1] if flip else faces)


def test_boundary_distance_of_a_flat_square_is_the_distance_to_its_nearest_side():
    vertices, faces = grid(11, 1.0)
    expected = 0.5 - np.abs(vertices[:, :2]).max(axis=1)
    np.testing.assert_allclose(boundary_distance(vertices, faces), expected, atol=1e-12)


def test_a_garment_over_a_flat_body_covers_what_lies_under_it_minus_the_margin():
    body, body_faces = grid(41, 1.0)  # 2.5 cm spacing
    cloth, cloth_faces = grid(21, 0.5, z=0.01)  # a 50 cm square 1 cm above the skin
    margin = 0.04  # between grid lines: no float tie at the threshold
    depth = cover_depth(body, body_faces, cloth, cloth_faces, max_gap=0.03)
    inside = np.abs(body[:, :2]).max(axis=1)
    under = inside <= 0.25 + 1e-9
    np.testing.assert_allclose(depth[under], 0.25 - inside[under], atol=1e-9)  # the distance to the cloth's edge
    assert (depth[~under] == 0).all() or (depth[~under] <= 1e-9).all()  # beyond the edge: closest point on it
    hidden = covered_faces(body, body_faces, cloth, cloth_faces, margin=margin, max_gap=0.03)
    corners = np.abs(body[body_faces][:, :, :2]).max(axis=2).max(axis=1)
    np.testing.assert_array_equal(hidden, corners <= 0.25 - margin + 1e-9)
    # cloth too far off the skin, or behind it, covers nothing
    assert not covered_faces(body, body_faces, cloth + [0, 0, 0.2], cloth_faces, max_gap=0.03).any()
    assert not covered_faces(body, body_faces, cloth - [0, 0, 0.02], cloth_faces, max_gap=0.03).any()


def test_tuck_rises_from_the_edge_to_the_margin():
    depth = np.array([-1.0, 0.0, 0.005, 0.01, 0.02, 0.5])
    np.testing.assert_allclose(tuck_depth(depth, margin=0.01, tuck=0.004), [0, 0, 0.002, 0.004, 0.004, 0.004])


def test_poke_through_counts_skin_outside_the_cloth_away_from_its_edges():
    body, body_faces = grid(41, 1.0)
    cloth, cloth_faces = grid(21, 0.5, z=-0.005)  # the skin is 5 mm outside the cloth
    poking = poke_through(body, body_faces, cloth, cloth_faces, max_gap=0.03, edge_band=0.05)
    centres = np.abs(body[body_faces].mean(axis=1)[:, :2]).max(axis=1)
    assert poking[centres < 0.19].all() and not poking[centres > 0.21].any()
    assert not poke_through(body, body_faces, cloth + [0, 0, 0.01], cloth_faces, 0.03, 0.05).any()
    side = surface_side(np.array([[0, 0, 0.01], [0, 0, -0.01], [0, 0, 0.5], [0.249, 0, 0.0]]), cloth + [0, 0, 0.005],
                        cloth_faces, max_gap=0.03, edge_band=0.01)
    np.testing.assert_array_equal(side, [1, -1, 0, 0])


def test_skin_of_another_body_part_outside_the_cloth_is_not_poking_through_it():
    """A torso under its shirt panel (1 cm below it) and an arm patch 4 cm outside that panel, facing the same way:
    the arm is outside the garment, not through it (the panel belongs to the torso, 1 cm from it). The same arm
    5 mm outside the panel with no torso near it does poke through."""
    torso, torso_faces = grid(41, 1.0)
    panel, panel_faces = grid(21, 0.5, z=0.01)
    arm, arm_faces = grid(5, 0.1, z=0.05)
    body = np.concatenate([torso, arm])
    faces = np.concatenate([torso_faces, arm_faces + len(torso)])
    poking = poke_through(body, faces, panel, panel_faces, max_gap=0.06, edge_band=0.05)
    arm_rows = np.arange(len(torso_faces), len(faces))
    assert not poking.any()
    before = poke_through(body, faces, panel, panel_faces, max_gap=0.06, edge_band=0.05, owner_tolerance=np.inf)
    assert before[arm_rows].all()  # what the count said without the rule
    near, near_faces = grid(5, 0.1, z=0.015)
    assert poke_through(near, near_faces, panel, panel_faces, max_gap=0.06, edge_band=0.05).all()


def test_a_panel_floating_nearer_another_body_part_is_that_parts_cloth():
    """The armpit of a heavy body: a shirt panel floating 4.8 cm outside the torso and an arm patch 5.2 cm outside
    the panel. Within a centimetre of each other, the distances alone cannot tell whose cloth it is (the arm counts
    as poking through); with the body's parts the torso, nearer by however little, owns it. Skin of the same part
    just outside the panel still pokes through."""
    torso, torso_faces = grid(41, 1.0)
    panel, panel_faces = grid(21, 0.5, z=0.048)
    arm, arm_faces = grid(5, 0.1, z=0.1)
    body = np.concatenate([torso, arm])
    faces = np.concatenate([torso_faces, arm_faces + len(torso)])
    parts = np.concatenate([np.zeros(len(torso), int), np.ones(len(arm), int)])
    arm_rows = np.arange(len(torso_faces), len(faces))
    assert poke_through(body, faces, panel, panel_faces, max_gap=0.06, edge_band=0.05)[arm_rows].all()
    assert not poke_through(body, faces, panel, panel_faces, max_gap=0.06, edge_band=0.05, vertex_parts=parts).any()
    near, near_faces = grid(5, 0.1, z=0.053)
    body = np.concatenate([torso, near])
    assert poke_through(body, faces, panel, panel_faces, max_gap=0.06, edge_band=0.05,
                        vertex_parts=np.zeros(len(body), int))[arm_rows].all()


def test_body_parts_are_the_skinning_regions(body):
    parts = body_part_labels(body)
    assert parts.shape == (len(body.skin_indices),) and set(np.unique(parts)) <= set(range(7))
    assert len(np.unique(parts)) == 7  # torso, two upper arms, two forearms, two legs


def test_skin_is_judged_against_the_cloth_facing_its_way_not_a_panel_it_meets_face_to_face():
    """The inner arm in an armpit: its skin (outward normal -z) lies just outside the shirt's side panel, which faces
    it (+z), and inside the sleeve's lower panel, which faces its way (-z) further off. It is under the sleeve."""
    side_panel, side_faces = grid(11, 0.5, z=-0.005)  # faces +z, towards the skin
    sleeve, sleeve_faces = grid(11, 0.5, z=-0.03, flip=True)  # faces -z, the skin's way
    cloth = np.concatenate([side_panel, sleeve])
    faces = np.concatenate([side_faces, sleeve_faces + len(side_panel)])
    skin, down = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, -1.0]])
    assert surface_side(skin, cloth, faces, max_gap=0.05, edge_band=0.05)[0] == 1  # the nearest panel alone: "out"
    assert surface_side(skin, cloth, faces, max_gap=0.05, edge_band=0.05, directions=down)[0] == -1
    through = np.array([[0.0, 0.0, -0.04]])  # past the sleeve: out of the cloth that lies over it
    assert surface_side(through, cloth, faces, max_gap=0.05, edge_band=0.05, directions=down)[0] == 1
    alone = surface_side(skin, side_panel, side_faces, max_gap=0.05, edge_band=0.05, directions=down)
    assert alone[0] == 0  # no cloth facing its way: nothing lies over it


@pytest.fixture(scope="module")
def tshirt(body):
    return make_garment("tshirt", body, n_vertices=1500)


def test_the_tshirt_hides_torso_and_upper_arms_but_not_head_hands_or_legs(body, tshirt):
    hidden = garment_covered_faces(tshirt, body)
    regions = region_weights(body.skin_indices, body.skin_weights, body.bone_names)[body.body_faces[:, 0]]
    region = regions.argmax(axis=1)
    torso = region == 0
    assert 0.15 < hidden[torso].mean() < 0.6  # under the shirt; head (dense), neck and hips stay
    assert hidden[(region == 1) | (region == 3)].mean() > 0.1  # upper arms: under the short sleeves
    height = body.shape().vertices[body.body_faces].mean(axis=1)[:, 2]
    assert not hidden[(region == 2) | (region == 4)].any()  # forearms and hands
    assert not hidden[(height > 1.6) | (height < 0.9)].any()  # head; legs below the hem


def test_no_hidden_face_touches_skin_that_shows_at_rest(body, tshirt):
    """Every hidden face lies under the cloth at rest, at least the margin inside its edges."""
    shape = body.shape()
    rest = tshirt.rest_vertices(body, shape)
    hidden = garment_covered_faces(tshirt, body)
    depth = cover_depth(shape.vertices, body.body_faces, rest, tshirt.faces)
    assert hidden.any() and (depth[body.body_faces[hidden]] >= 0.015).all()


def test_mhclo_delete_verts_are_read_and_hide_the_faces_they_touch(body, tmp_path):
    path = shared_path("garments", "makehuman", "male_casualsuit04", "male_casualsuit04.mhclo")
    _, binding, _ = read_mhclo(path)
    deleted = binding.delete_verts
    assert 1355 in deleted and 1394 in deleted and 1395 not in deleted and 1399 in deleted  # "1355 - 1394 1399 - ..."
    assert len(deleted) > 1000 and deleted.max() < 19158

    class Garment:  # only what garment_covered_faces reads of a MakeHuman garment
        faces = np.zeros((0, 3), dtype=np.int32)

    Garment.binding = binding
    hidden = garment_covered_faces(Garment(), body)
    touches = np.isin(body.body_faces, deleted).any(axis=1)
    np.testing.assert_array_equal(hidden, touches)


def test_faces_under_the_cloth_in_every_pose_of_a_range_are_hidden_and_no_others(body, tshirt):
    """always_covered: the body faces inside the T-shirt's footprint in every pose of a range. Each of them lies under
    cloth facing its way in each pose (no gap opens); a longer range hides no more."""
    from agentdress_ros.body import REFERENCE_SHAPE
    from agentdress_ros.display.models import always_covered, pose_range
    from agentdress_ros.models.garment_models import BodyModel, SkinnedGarmentModel

    model = SkinnedGarmentModel(tshirt, body)
    poses = pose_range(("walk",), every=12)
    hidden = always_covered([model], body, poses[:1])
    fewer = always_covered([model], body, poses)
    assert fewer.sum() > 100 and not (fewer & ~hidden).any()
    plain = BodyModel(body, REFERENCE_SHAPE)
    for rotvecs in poses:
        skin = np.asarray(plain.synthesize(rotvecs, np.zeros(3)), dtype=np.float64)
        corners = skin[plain.faces[fewer]]
        directions = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        cloth = np.asarray(model.synthesize(rotvecs, np.zeros(3)), dtype=np.float64)
        under = surface_side(corners.mean(axis=1), cloth, model.faces, edge_band=0.0, directions=directions)
        assert (under != 0).all()  # cloth over every hidden face: no gap opens
    height = body.shape().vertices[body.body_faces].mean(axis=1)[:, 2]
    assert not fewer[(height > 1.6) | (height < 0.9)].any()  # head; legs below the hem


def test_closest_points_on_a_mesh_match_a_brute_force_search_over_every_triangle():
    """The closest-point kernel behind every coverage test: on a bumpy open surface, each point's closest point,
    distance and barycentric weights equal the best over all triangles (Ericson's Voronoi-region test per triangle,
    checked against trimesh's triangle kernel); a point's direction keeps only the triangles facing it."""
    import trimesh

    from agentdress_ros.garment.coverage import _closest_facing

    rng = np.random.default_rng(3)
    vertices, faces = grid(9, 0.4)
    vertices[:, 2] = 0.03 * np.sin(9 * vertices[:, 0]) * np.cos(7 * vertices[:, 1])
    points = rng.uniform([-0.25, -0.25, -0.08], [0.25, 0.25, 0.08], size=(300, 3))
    closest, barycentric, distance, face_ids = _closest_facing(points, vertices, faces, reach=0.2)
    corners = vertices[faces]
    every = np.stack([trimesh.triangles.closest_point(corners, np.repeat(p[None], len(faces), 0)) for p in points])
    best = np.linalg.norm(every - points[:, None], axis=2).min(axis=1)
    np.testing.assert_allclose(distance, best, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), distance, atol=1e-12)
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", barycentric, corners[face_ids]), closest, atol=1e-12)
    normals = trimesh.Trimesh(vertices, faces, process=False).face_normals
    down = np.tile([0.0, 0.0, -1.0], (len(points), 1))  # every triangle faces up: none faces down
    assert (_closest_facing(points, vertices, faces, 0.2, down, normals)[3] == -1).all()


def test_cloth_over_a_point_must_lie_along_its_normal_not_beside_it():
    """cloth_over: a panel 2 cm above a skin point covers it; the same panel moved 15 cm to the side (its edge 5 cm
    off the point's normal line, still within max_gap) does not, although surface_side finds it within reach."""
    cloth, faces = grid(11, 0.2, z=0.02)
    point, up = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    assert cloth_over(point, up, cloth, faces, edge_band=0.0)[0]
    aside = cloth + [0.15, 0.0, 0.0]
    assert surface_side(point, aside, faces, edge_band=0.0, directions=up)[0] != 0
    assert not cloth_over(point, up, aside, faces, edge_band=0.0)[0]


def test_faces_hidden_over_a_range_of_shapes_are_those_under_cloth_on_each(body, tshirt):
    """always_covered over shapes: a subset of what one shape hides, and each face it hides lies under cloth on
    every shape of the range (checked at the extremes of weight, where a T-shirt sits loosest and tightest)."""
    from agentdress_ros.body import REFERENCE_SHAPE
    from agentdress_ros.display.models import always_covered, garment_rest, pose_range, shape_range
    from agentdress_ros.models.garment_models import BodyModel, SkinnedGarmentModel

    model = SkinnedGarmentModel(tshirt, body)
    edges = boundary_distance(garment_rest(model, body), model.faces)  # the open edges' distances it judges by
    poses = pose_range(("walk",), every=12)[:1]
    shapes = shape_range()
    assert len(shapes) == 9 and np.allclose(shapes[0], REFERENCE_SHAPE)
    reference = always_covered([model], body, poses)
    ranged = always_covered([model], body, poses, shapes=shapes)
    assert ranged.sum() > 100 and not (ranged & ~reference).any()
    for shape in shapes:
        plain, twin = BodyModel(body, shape), model.clone()
        twin.set_shape(shape)
        skin = np.asarray(plain.synthesize(poses[0], np.zeros(3)), dtype=np.float64)
        corners = skin[plain.faces[ranged]]
        directions = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        cloth = np.asarray(twin.synthesize(poses[0], np.zeros(3)), dtype=np.float64)
        assert cloth_over(corners.mean(axis=1), directions, cloth, twin.faces, edges=edges).all()


def test_a_sink_that_steps_becomes_a_ramp_of_the_given_slope_and_never_deepens():
    """sloped: 1.5 cm of sink on one half of a flat sheet, none on the other, becomes min(1.5 cm, slope x distance
    to the unsunk half along the edges); a sink that already rises that gently is left as it is."""
    vertices, faces = grid(21, 1.0)  # 5 cm spacing, rows along x
    step = np.where(vertices[:, 0] > 0, 0.015, 0.0)
    ramp = sloped(step, vertices, faces, slope=0.5)
    np.testing.assert_allclose(ramp, np.minimum(0.015, 0.5 * np.maximum(vertices[:, 0], 0.0)), atol=1e-9)
    gentle = np.clip(0.1 * vertices[:, 0], 0.0, None)
    np.testing.assert_allclose(sloped(gentle, vertices, faces, slope=0.5), gentle, atol=1e-9)


def test_a_hole_is_seen_from_outside_unless_something_drawn_lies_in_front_of_it():
    """display_check.seen_from_outside on analytic geometry: a point in a hole of a wall, facing the viewer (-y), is
    seen; a panel 5 cm in front of another hole hides it; a point behind the wall, or facing away, is not seen."""
    from agentdress_ros.evaluate.display_check import seen_from_outside

    wall, wall_faces = grid(21, 1.0)
    wall = wall[:, [0, 2, 1]]  # the xz plane at y = 0, seen from -y
    centres = wall[wall_faces].mean(axis=1)
    wall_faces = wall_faces[np.abs(centres - [0.1, 0.0, 0.1]).max(axis=1) > 0.06]  # a hole at (0.1, 0, 0.1)
    wall_faces = wall_faces[np.abs(wall[wall_faces].mean(axis=1)).max(axis=1) > 0.06]  # and one at the origin
    panel, panel_faces = grid(5, 0.2)
    panel = panel[:, [0, 2, 1]] - [0.0, 0.05, 0.0]
    hole = np.array([[0.1, 0.0, 0.1], [0.0, 0.0, 0.0], [0.3, 0.02, 0.3], [-0.3, 0.0, -0.3]])
    normals = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    front = np.array([[0.0, 1.0, 0.0]])  # looking along +y, at the wall's -y side
    seen = seen_from_outside([(wall, wall_faces), (panel, panel_faces)], hole, normals, directions=front)
    np.testing.assert_array_equal(seen, [True, False, False, False])  # beside the panel; under it; behind; away


def _rotation_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def test_an_edge_dipping_under_the_skin_is_pushed_to_the_clearance_along_the_posed_normal():
    """A flat skin (z = 0, normals +z) on one bone, and a garment edge band over it: a vertex 1 cm under the skin
    comes out to 2 mm above it, one already 1 cm above stays, one 5 cm under (beyond the 2 cm a vertex may lie under
    the skin it is kept off: across a fold of the body) stays, a vertex outside the band is never touched; with the
    bone turned 90 degrees about x the same holds along the turned normal (+z becomes -y)."""
    from agentdress_ros.engine.skin_clearance import EDGE_CLEARANCE, MAX_PUSH, bind_edges_to_skin, push_off_skin

    skin, _ = grid(11, 0.5)
    normals = np.tile([0.0, 0.0, 1.0], (len(skin), 1))
    bones, weights = np.zeros((len(skin), 2), dtype=np.int64), np.tile([1.0, 0.0], (len(skin), 1))
    garment = np.array([[0.0, 0.0, -0.01], [0.05, 0.0, 0.01], [0.1, 0.1, -0.05], [-0.1, 0.0, -0.01]])
    edge = np.array([0.0, 0.01, 0.02, 0.05])  # the last is 5 cm inside the edges, outside the 3 cm band
    binding = bind_edges_to_skin(garment, edge, skin, normals, bones, weights)
    assert binding.band.tolist() == [0, 1, 2] and binding.neighbors.shape == (3, 4)
    assert len(binding.rest) <= 12  # only the bound skin vertices are skinned each frame
    for angle in (0.0, np.pi / 2):
        rotation = _rotation_x(angle)
        transforms = np.concatenate([rotation, np.zeros((3, 1))], axis=1)[None]
        points = garment @ rotation.T  # the garment as posed with the bone
        assert push_off_skin(points, binding, transforms) == 1
        height = (points @ rotation)[:, 2]  # back in the bone's frame: the height over the skin
        np.testing.assert_allclose(height, [EDGE_CLEARANCE, 0.01, -0.05, -0.01], atol=1e-12)
        deep = np.array([[0.0, 0.0, -MAX_PUSH + EDGE_CLEARANCE + 0.001]]) @ rotation.T  # just within reach
        push_off_skin(deep, bind_edges_to_skin(deep @ rotation, [0.0], skin, normals, bones, weights), transforms)
        np.testing.assert_allclose((deep @ rotation)[0, 2], EDGE_CLEARANCE, atol=1e-12)
        np.testing.assert_allclose((points @ rotation)[:, :2], garment[:, :2], atol=1e-12)  # along the normal only


def test_the_edge_push_blends_the_bones_of_the_bound_skin_like_the_body_does():
    """Skin vertices weighted half and half between a still bone and one lifted 10 cm along z: the bound skin lies
    5 cm up, so an edge vertex at 4 cm is pushed to 5.4 cm."""
    from agentdress_ros.engine.skin_clearance import EDGE_CLEARANCE, bind_edges_to_skin, push_off_skin

    skin, _ = grid(5, 0.2)
    normals = np.tile([0.0, 0.0, 1.0], (len(skin), 1))
    bones, weights = np.tile([0, 1], (len(skin), 1)), np.tile([0.5, 0.5], (len(skin), 1))
    binding = bind_edges_to_skin(np.array([[0.0, 0.0, 0.01]]), np.zeros(1), skin, normals, bones, weights)
    transforms = np.stack([np.eye(3, 4), np.eye(3, 4)])
    transforms[1, 2, 3] = 0.1
    points = np.array([[0.0, 0.0, 0.04]])
    push_off_skin(points, binding, transforms)
    np.testing.assert_allclose(points, [[0.0, 0.0, 0.05 + EDGE_CLEARANCE]], atol=1e-12)


def test_with_the_body_drawn_each_garments_edge_band_is_kept_off_the_posed_skin(body):
    """Each shipped garment dressed as `make run` dresses it (one Loop round, body drawn), alone so that no layering
    mixes in: its display model carries its edge band's skin binding, and along a walk the push moves only band
    vertices, never more than its cap; without the body there is nothing to keep the cloth off (no binding)."""
    from pathlib import Path

    from agentdress_ros.engine.config import EngineKnobs
    from agentdress_ros.engine.skin_clearance import MAX_PUSH
    from agentdress_ros.motion.procedural import make_motion
    from agentdress_ros.ros.params import default_engine
    from agentdress_ros.ros.runtime import SceneSpec, build_model_set
    from agentdress_ros.scene.garments import GarmentSpec

    data = Path(__file__).resolve().parents[1] / "data"
    beta = (0.5, 0.5, 0.5, 0.5, 0.5, 0.5)
    motion = make_motion("walk", fps=30.0)
    for name in ("tshirt", "trousers"):
        spec = (GarmentSpec(name, None, str(data / f"{name}_default.h5"), EngineKnobs.of(**default_engine(name))),)
        drawn = build_model_set(SceneSpec(spec, True, beta, display_subdivision=1), body).models[name]
        bare = build_model_set(SceneSpec(spec, False, beta, display_subdivision=1), body).models[name]
        band = drawn.skin.band
        assert 100 < len(band) < drawn.n_vertices // 3, (name, len(band))
        assert getattr(bare, "skin", None) is None
        outside = np.setdiff1d(np.arange(drawn.n_vertices), band)
        moved = 0
        for k in range(0, len(motion.rotvecs), 8):
            pushed = np.array(drawn.synthesize(motion.rotvecs[k], motion.root_translation[k]), dtype=np.float64)
            plain = np.array(bare.synthesize(motion.rotvecs[k], motion.root_translation[k]), dtype=np.float64)
            step = np.linalg.norm(pushed - plain, axis=1)
            assert step[outside].max() < 1e-6 and step.max() <= MAX_PUSH + 1e-5, (name, k, step.max())
            moved += int(np.count_nonzero(step > 1e-4))
        assert moved > 0, name  # the walk does bring the edges under the skin


def test_make_run_walk_draws_no_body_face_through_the_cloth():
    """The display check on what `make run` publishes (shipped databases, body with its covered faces left out),
    over the walk at the heavier sweep shape where the last faces poked out: none drawn pokes through away from the
    open edges (and no more than measured near them), few faces
    left out are seen from outside (23 per frame; 149 when the neck showed through the collar), and the layering
    keeps the T-shirt out of the trousers (under 0.5 % of its vertices)."""
    from agentdress_ros.evaluate.display_check import check

    report = check(subdivisions=(0,), frames_step=4, sweep_times=(5.0,))
    run = report["runs"]["subdivision=0,layered=True"]
    assert run["drawn_body_faces_poking_per_frame"] == 0.0, run
    # within 3 cm of the open edges (cuffs, hem, collar) skin still pokes through: 21.1 faces per frame measured
    # 2026-12-07 with the edges pushed off the posed skin, 25.9 without (the saw-tooth along a sleeve's edge); the
    # check is deterministic, and the bound fails when the push is lost
    assert run["drawn_body_faces_poking_at_edges_per_frame"] < 25, run
    assert run["all_body_faces_poking_per_frame"] > 50  # with every face drawn, the check does see skin through
    assert run["hidden_body_faces_seen_from_outside_per_frame"] < 50, run
    assert run["tshirt_vertices_inside_trousers_pct"] < 0.5, run
