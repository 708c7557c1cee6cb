"""Training body shapes of the clothing shape models (AgentDress Sec. 3.2, adapted to Anny's phenotypes).

The paper drapes 17 SMPL bodies per anchor: beta0 plus 4 levels (-2, -1, +1, +2 standard deviations) along each
of the first four shape components. Anny has no PCA shape space but named phenotypes in [0, 1]; we take the four
that change a garment's drape most - gender (breasts, hips, shoulders), weight (girth), height (length) and muscle
(chest, arms) - at four levels around beta0, each alone, so every phenotype's effect is sampled at two distances on
both sides (what the quadratic features (beta, beta^2, 1) of Eq. 6 need). Age and proportions stay at beta0:
garments are sized for adults, and age mostly moves the body towards a child's, a different garment size.
"""
from __future__ import annotations

import numpy as np

from .assets import PHENOTYPE_NAMES
from .shape import REFERENCE_SHAPE

TRAINING_PHENOTYPES = ("gender", "weight", "height", "muscle")
#: Offsets from beta0 of the four levels; gender spans the whole male-female axis.
LEVELS = {
    "gender": (-0.5, -0.25, 0.25, 0.5),
    "weight": (-0.4, -0.2, 0.2, 0.4),
    "height": (-0.4, -0.2, 0.2, 0.4),
    "muscle": (-0.4, -0.2, 0.2, 0.4),
}


def training_shapes(count: int = 17, beta0=REFERENCE_SHAPE) -> np.ndarray:
    """(count, 6) shapes: beta0 first, then 4 levels for each of the first (count - 1) / 4 training phenotypes.

    count must be 1 + 4j with 0 <= j <= 4 (17 is the paper's design).
    """
    if count < 1 or (count - 1) % 4 or (count - 1) // 4 > len(TRAINING_PHENOTYPES):
        raise ValueError(f"--shapes must be 1, 5, 9, 13 or 17 (beta0 + 4 levels per phenotype), got {count}")
    beta0 = np.asarray(beta0, dtype=np.float64)
    shapes = [beta0]
    for name in TRAINING_PHENOTYPES[: (count - 1) // 4]:
        for offset in LEVELS[name]:
            beta = beta0.copy()
            beta[PHENOTYPE_NAMES.index(name)] = np.clip(beta0[PHENOTYPE_NAMES.index(name)] + offset, 0.0, 1.0)
            shapes.append(beta)
    return np.array(shapes)


def shape_range(shapes: np.ndarray) -> np.ndarray:
    """(6, 2) min and max of each phenotype over the training shapes: the range the models are valid in."""
    return np.stack([shapes.min(axis=0), shapes.max(axis=0)], axis=1)


def shape_scale() -> np.ndarray:
    """(6,) the step between training levels per phenotype: one "standard deviation" of the paper's design."""
    scale = np.full(len(PHENOTYPE_NAMES), 0.2)
    for name in TRAINING_PHENOTYPES:
        scale[PHENOTYPE_NAMES.index(name)] = abs(LEVELS[name][2])
    return scale


def trained_phenotypes(beta_range) -> np.ndarray:
    """(T,) indices of the phenotypes a database's training range (6, 2) spans: those its shape models vary."""
    low, high = np.asarray(beta_range, dtype=np.float64).T
    return np.flatnonzero(high - low > 1e-9)


def uniform_shapes(beta0, beta_range, count: int, rng, margin: float = 0.0) -> np.ndarray:
    """(count, 6) shapes whose trained phenotypes (trained_phenotypes) are drawn uniformly from the range widened by
    `margin` on both sides (clipped to Anny's [0, 1]); the others stay at beta0. One draw per shape, in order, so a
    seeded rng gives the same shapes however many are asked for."""
    trained = trained_phenotypes(beta_range)
    low, high = np.asarray(beta_range, dtype=np.float64).T
    low, high = np.clip(low - margin, 0.0, 1.0), np.clip(high + margin, 0.0, 1.0)
    shapes = np.repeat(np.asarray(beta0, dtype=np.float64)[None], count, axis=0)
    for shape in shapes:
        shape[trained] = rng.uniform(low[trained], high[trained])
    return shapes
