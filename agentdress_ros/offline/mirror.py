"""Left-right mirror images of training drapes: a second pose for every simulated drape, at no simulation cost.

The body at beta0, its skeleton and the garments are symmetric about the body's sagittal plane (x = 0), and so is
the physics. A drape reflected through that plane is the drape of the reflected pose: each bone takes its twin's
rotation (LeftArm <-> RightArm), reflected. The skeleton's bone frames are the world's axes (the joints are points,
body.kinematics), so the reflection x -> -x turns a rotation vector r into (r_x, -r_y, -r_z): S R S with S =
diag(-1, 1, 1) is the rotation about S a by minus the angle. The rest-frame garment (the drape unposed, the
`regressor`'s target) reflects the same way once each vertex knows where its mirror image lies on the rest garment
(a point of a rest triangle, barycentric; the garment's mesh is symmetric only up to its refinement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The reflection through the sagittal plane, and what it does to a rotation vector.
REFLECTION = np.array([-1.0, 1.0, 1.0])
ROTATION_REFLECTION = np.array([1.0, -1.0, -1.0])
#: Largest mismatch (m) of a skeleton's joints or a rest garment with its own mirror image that still counts as
#: symmetric (Anny at beta0: 1.8 mm; the T-shirt's vertices to its mirrored surface: 1.8 mm).
SYMMETRY_TOLERANCE = 0.005


def twin_name(name: str) -> str:
    """The mirror twin of a CMU bone name: LeftArm <-> RightArm, LHipJoint <-> RHipJoint; a middle bone is its own."""
    for side, other in (("Left", "Right"), ("Right", "Left")):
        if name.startswith(side):
            return other + name[len(side):]
    if len(name) > 1 and name[0] in "LR" and name[1].isupper():
        return {"L": "R", "R": "L"}[name[0]] + name[1:]
    return name


def bone_twins(names) -> np.ndarray:
    """(B,) index of each bone's mirror twin."""
    names = list(names)
    missing = [twin_name(n) for n in names if twin_name(n) not in names]
    if missing:
        raise ValueError(f"the skeleton has no mirror twin for {missing}")
    return np.array([names.index(twin_name(n)) for n in names], dtype=np.int64)


def mirrored_poses(poses: np.ndarray, twins: np.ndarray) -> np.ndarray:
    """(F, B, 3) rotation vectors of the reflected poses of poses (F, B, 3)."""
    return np.asarray(poses)[:, twins] * ROTATION_REFLECTION


def mirrored_canonical_poses(poses: np.ndarray, twins: np.ndarray) -> np.ndarray:
    """(F, B, 3) the mirror images of canonical poses (F, B, 3), canonical again: the poses the regressor trains its
    mirror images on."""
    from ..engine.pose_models import canonical_poses

    return canonical_poses(mirrored_poses(poses, twins))


def garment_mirror(rest: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Where each rest vertex's mirror image lies on the rest garment (V, 3) / faces (T, 3): (corners (V, 3), the
    vertices of the triangle holding it, barycentric weights (V, 3), largest distance (m) from the image to it)."""
    from ..garment.binding import project_to_surface

    rest = np.asarray(rest, dtype=np.float64)
    corners, weights, distance = project_to_surface(rest * REFLECTION, rest, np.asarray(faces))
    return corners, weights, float(distance.max())


def mirrored_positions(positions: np.ndarray, corners: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(F, V, 3) reflected garments of positions (F, V, 3) in the rest frame (garment_mirror's corners, weights)."""
    return np.einsum("fvkc,vk->fvc", np.asarray(positions)[:, corners], weights) * REFLECTION


@dataclass
class Mirror:
    """The mirror images of a garment's training data at beta0 (offline.regressor.TrainingData)."""

    twins: np.ndarray  # (B,) int
    corners: np.ndarray  # (V, 3) int
    weights: np.ndarray  # (V, 3)

    @classmethod
    def of(cls, db, body) -> "Mirror":
        """The mirror of a database's garment on the body at db.beta0; refuses a body or garment that is not
        symmetric about x = 0 within SYMMETRY_TOLERANCE."""
        twins = bone_twins(body.bone_names)
        heads = np.asarray(body.shape(db.beta0).heads, dtype=np.float64)
        skeleton_gap = float(np.abs(heads[twins] * REFLECTION - heads).max())
        corners, weights, garment_gap = garment_mirror(db.rest, db.faces)
        for what, gap in (("skeleton at beta0", skeleton_gap), (f"{db.garment} rest garment", garment_gap)):
            if gap > SYMMETRY_TOLERANCE:
                raise ValueError(f"the {what} is {gap * 1e3:.1f} mm from its mirror image (at most "
                                 f"{SYMMETRY_TOLERANCE * 1e3:.0f} mm): no mirror images to train on")
        return cls(twins, corners, weights)

    def __call__(self, data):
        """Mirror images of TrainingData, each under its source's group (held out with its clip)."""
        from .regressor import TrainingData

        return TrainingData(mirrored_canonical_poses(data.poses, self.twins),
                            mirrored_positions(data.positions, self.corners, self.weights), data.groups)
