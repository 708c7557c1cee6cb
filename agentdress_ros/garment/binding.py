"""Garment-to-body bindings: surface binding (follows any body shape), skin weights, and the 7 bone regions.

All functions are pure array functions. Shapes: V garment vertices, N body (hm08) vertices, B bones.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

# The paper's N_g = 7 bone regions (AgentDress Sec. 3.3): torso, the two upper arms, the two forearms with the
# hands, the two legs. Head and neck move the collar, so they belong to the torso.
REGIONS = {
    "torso": ("Hips", "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head", "LHipJoint", "RHipJoint",
              "LeftShoulder", "RightShoulder"),
    "left_upper_arm": ("LeftArm",),
    "left_forearm": ("LeftForeArm", "LeftHand", "LThumb", "LeftFingerBase", "LeftHandFinger1"),
    "right_upper_arm": ("RightArm",),
    "right_forearm": ("RightForeArm", "RightHand", "RThumb", "RightFingerBase", "RightHandFinger1"),
    "left_leg": ("LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase"),
    "right_leg": ("RightUpLeg", "RightLeg", "RightFoot", "RightToeBase"),
}
REGION_NAMES = tuple(REGIONS)


@dataclass(frozen=True)
class SurfaceBinding:
    """Each garment vertex sits on a body-surface triangle (barycentric) plus an offset along its normal."""

    triangles: np.ndarray  # (V, 3) int32 vertex ids of the carrying triangle (hm08 ids)
    barycentric: np.ndarray  # (V, 3) float64, rows sum to 1
    offset: np.ndarray  # (V,) float64 metres along the interpolated surface normal


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) unique undirected edges of a triangle mesh (F, 3)."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) the normals of the triangles faces (F, 3) over vertices (N, 3), twice their areas long (not unit)."""
    corners = vertices[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) of a triangle mesh (vertices (N, 3), faces (F, 3))."""
    by_face = face_normals(vertices, faces)
    # bincount sums the face normals onto their corners ~5x faster than np.add.at
    ids = faces.reshape(-1)
    normals = np.stack([np.bincount(ids, np.repeat(by_face[:, a], 3), minlength=len(vertices))
                        for a in range(3)], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def largest_face_corners(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 2): for every vertex, the other two corners (next, previous in the winding) of its largest incident face
    (the first of equal ones; vertices (N, 3), faces (F, 3)), so (p_next - p) x (p_previous - p) is that face's
    outward normal wherever the mesh is posed. A vertex of no face names itself twice (a zero normal)."""
    area = np.linalg.norm(face_normals(vertices, faces), axis=1)
    owner = faces.reshape(-1)  # face f's corner c at 3 f + c
    following = faces[:, [1, 2, 0]].reshape(-1)
    preceding = faces[:, [2, 0, 1]].reshape(-1)
    face = np.repeat(np.arange(len(faces)), 3)
    # by vertex, then area, then face index falling: each vertex's largest face last, the first of equal ones (the
    # two halves of a quad)
    last = np.lexsort((-face, np.repeat(area, 3), owner))
    pick = last[np.flatnonzero(np.r_[owner[last][1:] != owner[last][:-1], True])]
    out = np.repeat(np.arange(len(vertices))[:, None], 2, axis=1)
    out[owner[pick], 0] = following[pick]
    out[owner[pick], 1] = preceding[pick]
    return out


def project_to_surface(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray):
    """Closest surface point of every point (V, 3): (triangle vertex ids (V, 3), barycentric (V, 3), distance (V,))."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, distance, face_ids = trimesh.proximity.closest_point(mesh, points)
    triangles = faces[face_ids]
    barycentric = trimesh.triangles.points_to_barycentric(vertices[triangles], closest)
    barycentric = np.clip(barycentric, 0.0, 1.0)
    barycentric /= barycentric.sum(axis=1, keepdims=True)
    return triangles.astype(np.int32), barycentric, distance


def bind_to_surface(points, vertices, faces, offset) -> SurfaceBinding:
    """Bind points (V, 3) lying on (or near) the surface (vertices (N, 3), faces (F, 3)) with a normal offset."""
    triangles, barycentric, _ = project_to_surface(points, vertices, faces)
    offset = np.broadcast_to(np.asarray(offset, dtype=np.float64), (len(points),)).copy()
    return SurfaceBinding(triangles, barycentric, offset)


def _surface_frame(triangles, barycentric, vertices, normals):
    """Surface points (V, 3) and unit interpolated normals (V, 3) at barycentric positions on triangles."""
    weights = barycentric[:, :, None]
    base = (vertices[triangles] * weights).sum(axis=1)
    normal = (normals[triangles] * weights).sum(axis=1)
    return base, normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)


def bind_with_clearance(points, vertices, faces) -> SurfaceBinding:
    """Bind points (V, 3) off a surface to their closest triangle, keeping their clearance along the normal."""
    triangles, barycentric, _ = project_to_surface(points, vertices, faces)
    base, normal = _surface_frame(triangles, barycentric, vertices, vertex_normals(vertices, faces))
    return SurfaceBinding(triangles, barycentric, ((points - base) * normal).sum(axis=1))


def evaluate_surface_binding(binding: SurfaceBinding, vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Garment vertices (V, 3) on a (re)shaped surface with body vertices (N, 3) and unit vertex normals (N, 3)."""
    base, normal = _surface_frame(binding.triangles, binding.barycentric, vertices, normals)
    return base + binding.offset[:, None] * normal


def signed_clearance(points, vertices, faces, mesh=None) -> np.ndarray:
    """Distance (V,) of points to a closed surface, negative inside (sign from the closest face's normal); mesh: that
    surface as a trimesh.Trimesh when the caller has one."""
    mesh = trimesh.Trimesh(vertices, faces, process=False) if mesh is None else mesh
    closest, distance, face_ids = trimesh.proximity.closest_point(mesh, points)
    outward = ((points - closest) * mesh.face_normals[face_ids]).sum(axis=1) >= 0
    return np.where(outward, distance, -distance)


def interpolate_skin_weights(triangles, barycentric, skin_indices, skin_weights, n_bones, max_influences=4):
    """Skin weights of points given as barycentric combos of skinned vertices.

    triangles (V, 3) vertex ids, barycentric (V, 3), skin_indices/skin_weights (N, K) of those vertices.
    Returns (indices (V, max_influences) int32, weights (V, max_influences) float64) renormalised.
    """
    dense = np.zeros((len(triangles), n_bones))
    rows = np.arange(len(triangles))
    for corner in range(triangles.shape[1]):
        ids = triangles[:, corner]
        for k in range(skin_indices.shape[1]):
            np.add.at(dense, (rows, skin_indices[ids, k]), barycentric[:, corner] * skin_weights[ids, k])
    order = np.argsort(-dense, axis=1)[:, :max_influences]
    weights = np.take_along_axis(dense, order, axis=1)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    return order.astype(np.int32), weights


def region_weights(skin_indices: np.ndarray, skin_weights: np.ndarray, bone_names) -> np.ndarray:
    """w_{g,y} (V, 7): per vertex, the summed skin weight of each region's bones (rows sum to 1)."""
    bone_region = np.array([next(g for g, (_, bones) in enumerate(REGIONS.items()) if name in bones)
                            for name in bone_names])
    out = np.zeros((len(skin_indices), len(REGIONS)))
    rows = np.repeat(np.arange(len(skin_indices)), skin_indices.shape[1])
    np.add.at(out, (rows, bone_region[skin_indices.reshape(-1)]), skin_weights.reshape(-1))
    return out
