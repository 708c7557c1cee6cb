"""A synthetic database of realistic sizes and plausible values, for benchmarks and tests (no simulation).

The garment is the project's T-shirt template; anchor, example and sequence poses are random within human joint
ranges (root upright). Each anchor's clothing shape model is built so that it is exact and meaningful:
its PCA components are the orthonormalised first-order displacements of the *skinned* garment when one training
phenotype moves by one unit z (the garment follows the body's girth, height, ...), plus a smooth wrinkle field;
the ridge maps (z, z^2, 1) onto them, so f(beta, theta_s) is exactly linear in (z, z^2) (what the engine's
exact-reproduction tests rely on). Drapes are the skinned garment plus smooth wrinkles of a few millimetres.
"""
from __future__ import annotations

import numpy as np

from ..body import REFERENCE_SHAPE, AnnyBody
from ..body.assets import PHENOTYPE_NAMES
from ..body.kinematics import linear_blend_skinning
from ..garment import REGION_NAMES, make_garment
from .database import Database

#: Per-axis rotation limits (radians) of random poses, by bone-name fragment (first match wins).
JOINT_LIMITS = (
    ("Hips", 0.0), ("HipJoint", 0.05), ("Thumb", 0.2), ("Finger", 0.2), ("Hand", 0.4), ("ForeArm", 0.8),
    ("Arm", 0.9), ("Shoulder", 0.2), ("UpLeg", 0.6), ("Leg", 0.7), ("Foot", 0.3), ("Toe", 0.2), ("Neck", 0.3),
    ("Head", 0.3), ("Back", 0.25), ("Spine", 0.25),
)
TRAINING_PHENOTYPES = ("weight", "height", "gender", "muscle")
LEVELS = (-2.0, -1.0, 1.0, 2.0)  # training shapes at z = -2, -1, 1, 2 per phenotype (the paper's design)
BETA_SCALE = {"gender": 0.25, "weight": 0.2, "height": 0.2, "muscle": 0.2, "age": 0.2, "proportions": 0.2}

_GARMENTS: dict = {}


def joint_limits(bone_names) -> np.ndarray:
    """(B,) per-axis rotation limit of each bone."""
    return np.array([next((lim for key, lim in JOINT_LIMITS if key in name), 0.3) for name in bone_names])


def random_poses(rng, count: int, bone_names) -> np.ndarray:
    """(count, B, 3) rotation vectors uniform within the joint limits; the root stays upright."""
    limits = joint_limits(bone_names)
    return rng.uniform(-1.0, 1.0, size=(count, len(bone_names), 3)) * limits[None, :, None]


def smooth_field(rng, points: np.ndarray, amplitude: float, waves: int = 4) -> np.ndarray:
    """(V, 3) smooth random displacement field on points (V, 3): a few sine waves of 10-40 rad/m."""
    field = np.zeros_like(points)
    for _ in range(waves):
        k = rng.normal(size=3)
        k *= rng.uniform(10.0, 40.0) / np.linalg.norm(k)
        direction = rng.normal(size=3)
        field += np.sin(points @ k + rng.uniform(0, 2 * np.pi))[:, None] * direction / np.linalg.norm(direction)
    return field * (amplitude / np.sqrt(waves))


def _skin(rest, garment, transforms):
    out = np.empty_like(rest)
    return linear_blend_skinning(rest, garment.skin_indices, garment.skin_weights, transforms, out)


def _sensitivity_q(body, garment, shape, rest, regions, step=1e-3):
    """Q (R, D) and joint weights (D,) from finite differences of the skinned garment at the rest pose (Eq. 7, 11)."""
    n_dof = 3 * body.n_bones
    delta = np.zeros((len(rest), n_dof))
    for m in range(n_dof):
        rotvecs = np.zeros((body.n_bones, 3))
        rotvecs[m // 3, m % 3] = step
        plus = _skin(rest, garment, body.pose(shape, rotvecs)[0])
        rotvecs[m // 3, m % 3] = -step
        minus = _skin(rest, garment, body.pose(shape, rotvecs)[0])
        delta[:, m] = np.linalg.norm(plus - minus, axis=1) / (2 * step)
    per_joint = delta.sum(axis=0).reshape(-1, 3).sum(axis=1)
    return regions.T @ delta**2, np.repeat(per_joint, 3)


def training_betas(beta0: np.ndarray) -> np.ndarray:
    """(17, P) beta0 plus four levels of each training phenotype."""
    shapes = [beta0]
    for name in TRAINING_PHENOTYPES:
        p = PHENOTYPE_NAMES.index(name)
        for level in LEVELS:
            beta = beta0.copy()
            beta[p] = np.clip(beta0[p] + level * BETA_SCALE[name], 0.0, 1.0)
            shapes.append(beta)
    return np.array(shapes)


def make_synthetic_database(n_vertices: int = 12000, n_anchors: int = 150, n_components: int = 5,
                            n_examples: int = 24, seed: int = 0, body: AnnyBody | None = None,
                            n_sequence: int = 16, quadratic: float = 0.1) -> Database:
    """A Database with V ~ n_vertices (the T-shirt template), N anchors, C components, M examples, T sequence frames.

    `quadratic` scales the z^2 ridge rows relative to the linear ones. Takes ~1 s + the garment build (~3 s at 12k
    vertices, cached per body and size within a process).
    """
    rng = np.random.default_rng(seed)
    body = body if body is not None else AnnyBody()
    key = (id(body), int(n_vertices))
    if key not in _GARMENTS:
        _GARMENTS[key] = make_garment("tshirt", body, n_vertices)
    garment = _GARMENTS[key]
    beta0 = np.asarray(REFERENCE_SHAPE, dtype=np.float64)
    reference = body.shape(beta0)
    rest = garment.rest_vertices(body, reference)
    v = len(rest)
    names = body.bone_names
    scale = np.array([BETA_SCALE[n] for n in PHENOTYPE_NAMES])

    # one unit of z along each training phenotype: the body and garment refitted at rest
    unit_shapes = []
    for name in TRAINING_PHENOTYPES[: max(1, min(n_components, len(TRAINING_PHENOTYPES)))]:
        beta = beta0.copy()
        p = PHENOTYPE_NAMES.index(name)
        beta[p] += scale[p]
        shape = body.shape(beta)
        unit_shapes.append((p, shape, garment.rest_vertices(body, shape)))

    anchor_poses = random_poses(rng, n_anchors, names)
    n_features = 2 * len(PHENOTYPE_NAMES) + 1
    means = np.empty((n_anchors, v, 3))
    components = np.zeros((n_anchors, n_components, v, 3))
    ridge = np.zeros((n_anchors, n_features, n_components))
    ratios = np.zeros((n_anchors, n_components))
    for s, pose in enumerate(anchor_poses):
        skinned = _skin(rest, garment, body.pose(reference, pose)[0])
        means[s] = skinned + smooth_field(rng, rest, 0.004)
        columns = [(_skin(unit_rest, garment, body.pose(shape, pose)[0]) - skinned).reshape(-1)
                   for _, shape, unit_rest in unit_shapes]
        while len(columns) < n_components:  # beyond the trained phenotypes: small smooth extra modes
            columns.append(smooth_field(rng, rest, 0.002).reshape(-1))
        basis, triangular = np.linalg.qr(np.stack(columns[:n_components], axis=1))
        components[s] = basis.T.reshape(n_components, v, 3)
        # coefficients phi = triangular @ (z_p for the trained phenotypes): f = mean + sum_p z_p D_p (+ z^2 terms)
        for column, (p, _, _) in enumerate(unit_shapes[:n_components]):
            ridge[s, p] = triangular[:, column]
            ridge[s, len(PHENOTYPE_NAMES) + p] = quadratic * triangular[:, column]
        energy = (triangular**2).sum(axis=1)
        ratios[s] = energy / max(energy.sum(), 1e-30)

    example_poses = random_poses(rng, n_examples, names)
    example_drapes = np.stack([_skin(rest, garment, body.pose(reference, pose)[0]) + smooth_field(rng, rest, 0.004)
                               for pose in example_poses])
    # a smooth sequence between two random poses, simulated (here: skinned plus slowly varying wrinkles)
    ends = random_poses(rng, 2, names)
    alpha = np.linspace(0.0, 1.0, n_sequence)[:, None, None]
    sequence_poses = (1 - alpha) * ends[0] + alpha * ends[1]
    wrinkle_a, wrinkle_b = smooth_field(rng, rest, 0.004), smooth_field(rng, rest, 0.004)
    sequence_drapes = np.stack([_skin(rest, garment, body.pose(reference, pose)[0])
                                + (1 - a) * wrinkle_a + a * wrinkle_b
                                for pose, a in zip(sequence_poses, alpha[:, 0, 0])])

    region_dof, dof_weights = _sensitivity_q(body, garment, reference, rest, garment.regions)
    shapes = training_betas(beta0)
    return Database(
        garment="tshirt",
        faces=garment.faces.astype(np.int32),
        rest=rest.astype(np.float32),
        skin_indices=garment.skin_indices.astype(np.int32),
        skin_weights=garment.skin_weights.astype(np.float32),
        regions=garment.regions.astype(np.float32),
        region_names=REGION_NAMES,
        bone_names=tuple(names),
        parents=np.asarray(body.parents, dtype=np.int32),
        beta_names=PHENOTYPE_NAMES,
        beta0=beta0,
        beta_range=np.stack([shapes.min(axis=0), shapes.max(axis=0)], axis=1),
        beta_scale=scale,
        joint_weights=dof_weights.astype(np.float32),
        region_dof=region_dof.astype(np.float32),
        anchor_poses=anchor_poses.astype(np.float32),
        training_betas=shapes,
        pca_mean=means.astype(np.float32),
        pca_components=components.astype(np.float32),
        ridge=ridge,
        explained_variance_ratio=ratios,
        example_poses=example_poses.astype(np.float32),
        example_drapes=example_drapes.astype(np.float32),
        sequence_poses=sequence_poses.astype(np.float32),
        sequence_root_translation=np.zeros((n_sequence, 3), dtype=np.float32),
        sequence_drapes=sequence_drapes.astype(np.float32),
        sequence_fps=30.0,
        body_model="anny/cmu_mb (synthetic database)",
        build_command=f"make_synthetic_database({n_vertices}, {n_anchors}, {n_components}, {n_examples}, {seed})",
        provenance={"synthetic": True, "seed": seed},
    )
