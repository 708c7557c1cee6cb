"""Body shape beta: six named phenotypes in [0, 1] mapped to sparse blendshape coefficients (Anny's rule).

Each phenotype interpolates linearly between its MakeHuman variations (anchors); a target that is the product of
several variations (e.g. female-young-maxmuscle-averageweight) gets the product of their interpolation weights.
Race is fixed at an even mix, breast size and firmness at their average. At most ~100 of the ~400 targets are
non-zero for any beta, so a shape change only touches those.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .assets import PHENOTYPE_NAMES, VARIATIONS

# Anchor values of each phenotype's variations (anny's convention: age 0 = baby, 1/3 child, 2/3 young, 1 old).
ANCHORS = {
    "gender": np.array([0.0, 1.0]),
    "age": np.linspace(-1.0 / 3.0, 1.0, 5),
    "muscle": np.array([0.0, 0.5, 1.0]),
    "weight": np.array([0.0, 0.5, 1.0]),
    "height": np.array([0.0, 1.0]),
    "proportions": np.array([0.0, 1.0]),
}

#: A young adult of average build: the reference shape beta0 of the garments and databases.
REFERENCE_SHAPE = np.array([0.5, 2.0 / 3.0, 0.5, 0.5, 0.5, 0.5])


@dataclass(frozen=True)
class CheckedShape:
    beta: np.ndarray  # (6,) float64 inside [0, 1]
    clamped: bool  # True when some input value lay outside [0, 1] and was clamped


def check_shape(beta, clamp: bool = True) -> CheckedShape:
    """Validate a shape vector: 6 finite values; out-of-range values are clamped (flagged) or rejected.

    Raises ValueError naming the phenotype for a wrong length, a non-finite value, or (clamp=False) a value
    outside [0, 1].
    """
    values = np.asarray(beta, dtype=np.float64).reshape(-1)
    if values.shape != (len(PHENOTYPE_NAMES),):
        raise ValueError(
            f"body shape needs {len(PHENOTYPE_NAMES)} values {PHENOTYPE_NAMES}, got {values.size}"
        )
    bad = [PHENOTYPE_NAMES[i] for i in np.flatnonzero(~np.isfinite(values))]
    if bad:
        raise ValueError(f"body shape has non-finite values for {', '.join(bad)}")
    outside = [PHENOTYPE_NAMES[i] for i in np.flatnonzero((values < 0.0) | (values > 1.0))]
    if outside and not clamp:
        raise ValueError(f"body shape values outside [0, 1] for {', '.join(outside)}: {values.tolist()}")
    return CheckedShape(np.clip(values, 0.0, 1.0), bool(outside))


def variation_weights(beta: np.ndarray) -> dict:
    """Interpolation weight of every MakeHuman variation name for a checked beta (6,)."""
    weights = {}
    for name, value in zip(PHENOTYPE_NAMES, beta):
        anchors = ANCHORS[name]
        upper = int(np.clip(np.searchsorted(anchors, value, side="right"), 1, len(anchors) - 1))
        alpha = (value - anchors[upper - 1]) / (anchors[upper] - anchors[upper - 1])
        alpha = float(np.clip(alpha, 0.0, 1.0))
        for i, variation in enumerate(VARIATIONS[name]):
            weights[variation] = (1.0 - alpha) if i == upper - 1 else alpha if i == upper else 0.0
    for race in VARIATIONS["race"]:
        weights[race] = 1.0 / 3.0
    return weights


def blendshape_coefficients(beta: np.ndarray, target_variations: np.ndarray, variation_names) -> np.ndarray:
    """Coefficients (S,) of the blendshapes: the product of the weights of each target's variations."""
    weights = variation_weights(beta)
    per_variation = np.array([weights[v] for v in variation_names])
    masked = np.where(target_variations, per_variation[None, :], 1.0)
    return masked.prod(axis=1)
