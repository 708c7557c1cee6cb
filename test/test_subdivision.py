"""Display refinement: Loop subdivision as a fixed sparse matrix, checked against the scheme's exact properties."""
import numpy as np
import pytest
import trimesh

from agentdress_ros.engine.subdivision import LoopSubdivision, loop_stencils

from .test_coverage import grid


def test_one_round_adds_one_vertex_per_edge_and_four_triangles_per_triangle():
    sphere = trimesh.creation.icosphere(1)
    matrix, faces, edges = loop_stencils(sphere.faces, len(sphere.vertices))
    assert matrix.shape == (len(sphere.vertices) + len(sphere.edges_unique), len(sphere.vertices))
    assert len(faces) == 4 * len(sphere.faces)
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=1)).ravel(), 1.0)  # affine invariance
    refined = trimesh.Trimesh(np.zeros((matrix.shape[0], 3)), faces, process=False)
    assert refined.is_watertight and refined.is_winding_consistent


def test_known_stencils_on_a_regular_sheet():
    vertices, faces = grid(5, 1.0)
    matrix, _, edges = loop_stencils(faces, len(vertices))
    centre = 12  # interior vertex of valence 6: 1 - 6 * 1/16 = 5/8 itself, 1/16 each neighbour
    row = matrix[centre].toarray().ravel()
    assert row[centre] == pytest.approx(5 / 8) and np.sort(row[row > 0])[:6] == pytest.approx([1 / 16] * 6)
    corner_edge = np.flatnonzero((edges == [0, 1]).all(axis=1))[0]  # an open edge: its midpoint
    row = matrix[len(vertices) + corner_edge].toarray().ravel()
    assert row[0] == row[1] == 0.5 and row.sum() == 1.0


def test_a_flat_sheet_stays_flat_and_linear_fields_are_reproduced():
    vertices, faces = grid(9, 1.0)
    sub = LoopSubdivision(faces, len(vertices), levels=2, offset=0.0)
    refined = sub.apply(vertices)
    np.testing.assert_allclose(refined[:, 2], 0.0, atol=1e-15)
    field = vertices @ [0.3, -0.7, 0.0]
    # straight open edges stay straight and interior stencils are symmetric: x and y are reproduced exactly
    np.testing.assert_allclose(sub.matrix @ field, refined @ [0.3, -0.7, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(refined[:, :2]).max(), 0.5)  # the sheet keeps its extent
    lifted = LoopSubdivision(faces, len(vertices), levels=1, offset=0.003).apply(vertices)
    np.testing.assert_allclose(lifted[:, 2], 0.003, atol=1e-12)  # the offset along the normal


def test_a_sphere_shrinks_and_the_offset_lifts_it_back_out():
    sphere = trimesh.creation.icosphere(2)
    plain = LoopSubdivision(sphere.faces, len(sphere.vertices), 1, offset=0.0).apply(sphere.vertices)
    radius = np.linalg.norm(plain, axis=1)
    assert radius.max() < 1.0 and radius.min() > 0.97  # Loop lies inside a convex control mesh
    lifted = LoopSubdivision(sphere.faces, len(sphere.vertices), 1, offset=0.02).apply(sphere.vertices)
    np.testing.assert_allclose(np.linalg.norm(lifted, axis=1), radius + 0.02, atol=2e-3)


def test_levels_zero_is_the_identity_and_float32_keeps_its_dtype():
    vertices, faces = grid(5, 1.0)
    assert LoopSubdivision(faces, len(vertices), 0).apply(vertices) is vertices
    sub = LoopSubdivision(faces, len(vertices), 2)
    out = sub.apply(vertices.astype(np.float32))
    assert out.dtype == np.float32 and out.shape == (sub.n_vertices, 3) and len(sub.faces) == 16 * len(faces)
    with pytest.raises(ValueError, match="levels"):
        LoopSubdivision(faces, len(vertices), 4)


def _tube(count: int = 48, radius: float = 0.08, rings: int = 4, zigzag: float = 0.0):
    """An open cylinder (rings x count vertices, axis z, 3 cm between rings) whose two rims are the open boundaries;
    zigzag: the bottom rim's vertices moved alternately up and down by this much (a saw-toothed hem)."""
    angle = 2 * np.pi * np.arange(count) / count
    vertices = np.concatenate([np.stack([radius * np.cos(angle), radius * np.sin(angle), np.full(count, 0.03 * k)], 1)
                               for k in range(rings)])
    vertices[:count, 2] += zigzag * (-1.0) ** np.arange(count)
    faces = []
    for k in range(rings - 1):
        for i in range(count):
            a, b, c, d = k * count + i, k * count + (i + 1) % count, (k + 1) * count + i, (k + 1) * count + (i + 1) % count
            faces += [[a, b, d], [a, d, c]]
    return vertices, np.array(faces)


def test_boundary_smoothing_removes_a_saw_tooth_keeps_a_round_rim_and_leaves_the_inside_alone():
    from agentdress_ros.engine.subdivision import boundary_smoothing

    flat, faces = _tube(rings=6)
    jagged, _ = _tube(rings=6, zigzag=0.005)
    matrix = boundary_smoothing(faces, flat, sigma=0.05)
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=1)).ravel(), 1.0)  # affine invariance
    smoothed = matrix @ jagged
    count = 48
    # beyond the first ring inside, rows are the identity; the first ring moves with its boundary neighbours
    np.testing.assert_array_equal(smoothed[2 * count:-2 * count], jagged[2 * count:-2 * count])
    moved = matrix @ (jagged + [0.0, 0.0, 0.01]) - smoothed  # a rigid lift of everything stays a rigid lift
    np.testing.assert_allclose(moved[:, 2], 0.01, atol=1e-12)
    # the 5 mm alternation (the highest frequency along the rim) is gone to round-off
    assert np.abs(smoothed[:count, 2]).max() < 1e-6, np.abs(smoothed[:count, 2]).max()
    # a circle of radius 8 cm keeps its radius within 1.4 % (the width is capped at half the radius, compensated)
    radius = np.linalg.norm((matrix @ flat)[:count, :2], axis=1)
    assert 0.08 * 0.986 < radius.min() <= radius.max() <= 0.08 + 1e-12, (radius.min(), radius.max())
    # on the refined mesh the rim as drawn is the same circle, without the teeth
    sub = LoopSubdivision(faces, len(flat), 1, offset=0.0, rest=flat)
    refined = sub.apply(jagged)
    rim = np.flatnonzero(np.isclose(np.asarray(sub.matrix[:, :count].sum(axis=1)).ravel(), 1.0))
    assert np.abs(refined[rim, 2]).max() < 1e-3
    unsmoothed = LoopSubdivision(faces, len(flat), 1, offset=0.0).apply(jagged)
    assert np.abs(unsmoothed[rim, 2]).max() > 2e-3  # Loop's boundary rule alone keeps half the teeth
    with pytest.raises(ValueError, match="rest has"):
        LoopSubdivision(faces, len(flat), 1, rest=flat[:-1])


def test_posed_boundary_smoothing_follows_the_rim_as_posed():
    """Per frame, along the drawn rim's own arc length: a 5 mm saw-tooth on a rim whose vertices a pose bunched on
    one side (spacing 1:4) is gone, a round rim keeps its radius, nothing beyond the first ring inside moves, and the
    first ring moves with its boundary neighbours (float32 in place, as the display's buffers are)."""
    from agentdress_ros.engine.subdivision import BoundaryLoops, smooth_posed_boundaries

    count = 48
    flat, faces = _tube(count=count, rings=6)
    loops = BoundaryLoops(faces)
    assert len(loops.starts) == 3 and sorted(np.diff(loops.starts)) == [count, count]
    bunched = np.linspace(0.0, 1.0, count, endpoint=False) ** 2 * 2 * np.pi  # dense near angle 0, sparse near 2 pi
    posed = flat.copy()
    posed[:count, :2] = 0.08 * np.stack([np.cos(bunched), np.sin(bunched)], axis=1)
    jagged = posed.copy()
    jagged[:count, 2] += 0.005 * (-1.0) ** np.arange(count)
    for vertices, tooth in ((posed, 0.0), (jagged, 0.005)):
        drawn = vertices.astype(np.float32)
        smooth_posed_boundaries(drawn, loops)
        # the rim's height: the teeth fall from 5 mm to 0.3 mm on average; the worst, 1.0 mm, where the spacing
        # jumps from 0.1 to 2.1 cm (as wide as the Gaussian) at the loop's seam
        height = np.abs(drawn[:count, 2])
        assert height.max() < (1.5e-3 if tooth else 1e-6) and height.mean() < (4e-4 if tooth else 1e-6), height
        radius = np.linalg.norm(drawn[:count, :2], axis=1)
        assert 0.08 * 0.98 < radius.min() <= radius.max() < 0.08 * 1.005, (radius.min(), radius.max())
        np.testing.assert_array_equal(drawn[2 * count:-2 * count], vertices[2 * count:-2 * count].astype(np.float32))
        ring_move = drawn[count:2 * count] - vertices[count:2 * count].astype(np.float32)
        rim_move = drawn[:count] - vertices[:count].astype(np.float32)
        # each first-ring vertex moves by the mean of its boundary neighbours' moves (here: i and i + 1 or i - 1)
        neighbours = [sorted({e for f in faces if count + i in f for e in f if e < count}) for i in range(count)]
        expected = np.array([rim_move[n].mean(axis=0) for n in neighbours])
        np.testing.assert_allclose(ring_move, expected, atol=1e-6)


def test_a_vertex_pushed_alone_becomes_a_smooth_bump_no_larger_than_the_push():
    """One rim vertex of a round tube pushed 1 cm outwards (as the edge push off the skin moves single vertices):
    its neighbours along the rim follow by the push faded with a Gaussian of 2 cm of arc (the vertex keeps its 1 cm,
    nobody moves more), the first ring inside follows the rim, the rest stays; the tooth (roughness 5.8 mm) becomes a
    bump of 1.6 mm."""
    from agentdress_ros.engine.subdivision import BoundaryLoops, spread_edge_moves
    from agentdress_ros.evaluate.look import edge_roughness

    count = 48
    before, faces = _tube(count=count, rings=6)
    loops = BoundaryLoops(faces)
    pushed = before.copy()
    pushed[0, :2] *= 1.0 + 0.01 / 0.08  # vertex 0 of the bottom rim, 1 cm out
    tooth = edge_roughness(pushed, np.arange(count))[0].max()
    spread = pushed.astype(np.float32)
    spread_edge_moves(spread, before, loops, sigma=0.02)
    move = np.linalg.norm(spread - before, axis=1)
    edge = 2 * 0.08 * np.sin(np.pi / count)  # the polygon's arc length from vertex 0 along the rim
    arc = edge * np.minimum(np.arange(count), count - np.arange(count))
    expected = np.where(arc <= 0.06, 0.01 * np.exp(-0.5 * (arc / 0.02) ** 2), 0.0)
    np.testing.assert_allclose(move[:count], expected, atol=2e-6)
    assert move.max() <= 0.01 + 1e-6
    rim_move = (spread - before)[:count]
    neighbours = [sorted({e for f in faces if count + i in f for e in f if e < count}) for i in range(count)]
    follow = np.array([rim_move[n].mean(axis=0) for n in neighbours])  # the ring follows its rim neighbours
    np.testing.assert_allclose((spread - before)[count:2 * count], follow, atol=2e-6)
    assert move[2 * count:].max() < 1e-7  # float32 round-off: the rest stays
    bump = edge_roughness(spread, np.arange(count))[0].max()
    assert tooth > 5.5 and bump < 2.0, (tooth, bump)
