"""Layered garments: the outer garment is pushed out of the inner one through a fixed binding (no per-frame search),
and lifted where an inner vertex passes between its vertices (the reverse binding, a local search per frame)."""
import numpy as np
import pytest
import trimesh

from agentdress_ros.engine.layering import (LayerBinding, bind_layers, bind_to_vertices, bind_under,
                                           face_vertex_normals, lift_over_inner, push_out_of_inner, track_nearest,
                                           vertex_neighbours)

from .test_coverage import grid


def test_vertex_normals_of_a_sphere_point_outwards():
    sphere = trimesh.creation.icosphere(3)
    normals = face_vertex_normals(sphere.vertices, sphere.faces, np.empty_like(sphere.vertices))
    radial = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1)[:, None]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    assert (normals * radial).sum(axis=1).min() > 0.999  # area weighting tilts them by under 3 degrees


def test_an_outer_sheet_inside_the_inner_one_is_pushed_to_the_clearance_and_only_over_it():
    inner, inner_faces = grid(11, 0.5)  # inner garment: a 50 cm square at z = 0, normals +z
    outer, _ = grid(21, 1.0, z=-0.01)  # outer garment: 1 m square 1 cm *inside* the inner one
    binding = bind_layers(outer, inner, inner_faces, max_distance=0.05, edge_margin=0.02)
    over = np.abs(outer[:, :2]).max(axis=1) <= 0.25 - 0.02 + 1e-9
    np.testing.assert_array_equal(np.isin(np.arange(len(outer)), binding.outer), over)
    moved = outer.copy()
    count = push_out_of_inner(moved, inner, inner_faces, binding, clearance=0.004)
    assert count == over.sum()
    np.testing.assert_allclose(moved[over, 2], 0.004, atol=1e-12)  # exactly the clearance outside
    np.testing.assert_array_equal(moved[~over], outer[~over])  # beyond the inner garment's edge: untouched
    np.testing.assert_array_equal(moved[:, :2], outer[:, :2])  # pushed along the normal only


def test_the_binding_follows_the_posed_inner_garment():
    """Bound at rest, then both garments move rigidly: the push acts along the moved normals."""
    inner, inner_faces = grid(11, 0.5)
    outer, _ = grid(11, 0.5, z=0.02)  # outside at rest
    binding = bind_layers(outer, inner, inner_faces, max_distance=0.05, edge_margin=0.0)
    angle = 0.7
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    inner_posed = inner @ rotation.T + [0.1, 0.2, 0.3]
    outer_posed = (outer - [0, 0, 0.03]) @ rotation.T + [0.1, 0.2, 0.3]  # slid 1 cm inside the inner sheet
    moved = outer_posed.copy()
    push_out_of_inner(moved, inner_posed, inner_faces, binding, clearance=0.005)
    normal = rotation @ [0, 0, 1]
    np.testing.assert_allclose((moved - inner_posed) @ normal, 0.005, atol=1e-9)


def test_an_outer_garment_already_outside_is_left_alone():
    sphere = trimesh.creation.icosphere(3)
    outer = sphere.vertices * 1.05
    binding = bind_layers(outer, sphere.vertices, sphere.faces, max_distance=0.1)
    assert len(binding) == len(outer)  # a closed inner garment has no edge: everything binds
    moved = outer.copy()
    assert push_out_of_inner(moved, sphere.vertices, sphere.faces, binding, clearance=0.01) == 0
    np.testing.assert_array_equal(moved, outer)
    inside = sphere.vertices * 0.97
    push_out_of_inner(inside, sphere.vertices, sphere.faces, bind_layers(inside, sphere.vertices, sphere.faces),
                      clearance=0.01)
    assert np.linalg.norm(inside, axis=1).min() > 1.0  # every vertex ends outside the inner sphere


def test_by_default_the_outer_garment_binds_over_the_inner_edge_and_is_pushed_when_that_edge_slides_under_it():
    """A shirt's hem over the trousers' waist: bound at rest beyond the waist's edge (the default binds at the edges
    too), it is pushed out once the hips swing the waist under it; further than 10 cm at rest, nothing binds."""
    inner, inner_faces = grid(11, 0.5)  # the trousers, edge at |x|, |y| = 0.25
    outer = np.array([[0.27, 0.0, 0.002], [0.0, 0.0, 0.02], [0.4, 0.0, 0.0]])  # over the edge, over, far off
    binding = bind_layers(outer, inner, inner_faces)
    np.testing.assert_array_equal(binding.outer, [0, 1])
    slid = inner + [0.05, 0.0, 0.0]  # the waist slides 5 cm under the hem vertex
    moved = outer.copy()
    assert push_out_of_inner(moved, slid, inner_faces, binding, clearance=0.004) == 1
    np.testing.assert_allclose(moved[0], [0.27, 0.0, 0.004], atol=1e-12)
    np.testing.assert_array_equal(moved[1:], outer[1:])


def _height_over(vertices, faces, point) -> float:
    """Height of the flat-ish sheet (V, 3), (F, 3) over the point's (x, y): the face its projection falls in."""
    corners = vertices[faces]
    for face, (a, b, c) in zip(faces, corners):
        w = trimesh.triangles.points_to_barycentric(np.array([[a, b, c]]) * [1, 1, 0], np.array([[*point[:2], 0.0]]))[0]
        if (w >= -1e-9).all():
            return float(w @ vertices[face][:, 2])
    raise AssertionError("no face over the point")


def test_an_inner_vertex_through_an_outer_triangle_lifts_that_triangle_over_it():
    """The reverse binding: inner vertices under the outer sheet (and inside its edges) are bound to its triangles;
    one pushed through the sheet between the outer vertices lifts the triangle it is under to the clearance over
    it, along the normals, and nothing else moves."""
    inner, _ = grid(21, 0.5)  # the trousers, 2.5 cm edges
    outer, outer_faces = grid(11, 1.0, z=0.01)  # the shirt 1 cm over them, 10 cm edges
    under = bind_under(inner, outer, outer_faces)
    assert len(under) == len(inner)  # all under the shirt, inside its edges
    bump = 10 * 21 + 3  # an inner vertex between the outer vertices
    inner[bump, 2] = 0.02  # 1 cm through the shirt
    lifted = outer.copy()
    assert lift_over_inner(lifted, outer_faces, inner, under, clearance=0.004) == 1
    assert _height_over(lifted, outer_faces, inner[bump]) == pytest.approx(0.024, abs=1e-9)
    moved = np.linalg.norm(lifted - outer, axis=1) > 0
    assert 1 <= moved.sum() <= 3  # the corners of one triangle
    np.testing.assert_array_equal(lifted[:, :2], outer[:, :2])  # along the normals (+z) only


def test_the_reverse_binding_finds_the_triangle_an_inner_vertex_slid_under():
    """Bound at rest, then the shirt slides 7 cm over the trousers (a walk's hip swing): the vertex that pokes
    through lifts the triangle it now lies under, not the one closest to it at rest."""
    inner, _ = grid(21, 0.5)
    outer, outer_faces = grid(21, 1.0, z=0.01)  # 5 cm edges: three rings reach 15 cm
    under = bind_under(inner, outer, outer_faces)
    slid = outer + [0.07, 0.0, 0.0]
    bump = 10 * 21 + 10  # the centre
    inner[bump, 2] = 0.02
    lifted = slid.copy()
    assert lift_over_inner(lifted, outer_faces, inner, under, clearance=0.004) == 1
    assert _height_over(lifted, outer_faces, inner[bump]) == pytest.approx(0.024, abs=1e-9)


def test_vertex_neighbours_of_a_grid_are_its_edge_neighbours():
    vertices, faces = grid(3, 2.0)  # 3 x 3: the centre has the 4 axis neighbours and the 2 diagonal ones the
    offsets, neighbours = vertex_neighbours(faces, len(vertices))  # split of each square adds
    centre = neighbours[offsets[4]:offsets[5]]
    assert sorted(centre.tolist()) == [0, 1, 3, 5, 7, 8]
    assert offsets[-1] == len(neighbours) == 2 * 16  # 16 edges, each listed from both ends


def test_a_vertex_binding_follows_the_inner_garment_as_it_slides():
    """The shirt bound at rest to the trousers vertex under each of its vertices; then the trousers slide 4 cm
    and a bump (a seam's ridge, 2 cm high) comes under the shirt: tracked, each shirt vertex is pushed out of the
    trousers vertex now under it and clears the bump; the binding fixed at rest leaves the bump through the shirt."""
    inner, inner_faces = grid(21, 0.4)  # 2 cm spacing
    outer, _ = grid(21, 0.4, z=0.006)
    binding = bind_to_vertices(outer, inner)
    slid = inner + [0.04, 0.0, 0.0]
    slid[np.isclose(slid[:, 0], 0.04), 2] = 0.02  # the ridge now lies under the shirt's column at x = 0.04
    heights = {}
    for tracked in (False, True):
        own = LayerBinding(binding.outer, binding.triangles.copy(), binding.barycentric, binding.faces)
        moved = outer.copy()
        if tracked:
            track_nearest(moved, slid, own, vertex_neighbours(inner_faces, len(inner)))
        push_out_of_inner(moved, slid, inner_faces, own, clearance=0.004)
        heights[tracked] = moved[np.isclose(moved[:, 0], 0.04) & (np.abs(moved[:, 1]) < 0.15), 2]
    assert heights[False].max() < 0.02 < 0.024 - 1e-6 <= heights[True].min(), heights
