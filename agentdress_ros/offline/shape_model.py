"""Clothing shape model of one anchor (AgentDress Eq. 5-6): PCA of the drapes, ridge from shape to coefficients."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from sklearn.decomposition import PCA
from sklearn.linear_model import Ridge

from ..engine.database import shape_features

RIDGE_ALPHA = 0.2


@dataclass(frozen=True)
class ShapeModel:
    mean: np.ndarray  # (V, 3)
    components: np.ndarray  # (C, V, 3)
    ridge: np.ndarray  # (2P+1, C) features -> PCA coefficients
    explained_variance_ratio: np.ndarray  # (C,)
    beta0: np.ndarray  # (P,)
    beta_scale: np.ndarray  # (P,)

    def predict(self, betas: np.ndarray) -> np.ndarray:
        """Drapes (K, V, 3) for shapes (K, P)."""
        coefficients = shape_features(betas, self.beta0, self.beta_scale) @ self.ridge
        return self.mean[None] + np.tensordot(coefficients, self.components, axes=(1, 0))


def fit_shape_model(drapes, betas, beta0, beta_scale, n_components: int = 5, alpha: float = RIDGE_ALPHA):
    """PCA (n_components, capped by the sample count) of drapes (K, V, 3), ridge (alpha) from (z, z^2, 1)."""
    k, v, _ = drapes.shape
    n_components = min(n_components, k)
    flat = drapes.reshape(k, -1)
    with np.errstate(divide="ignore", invalid="ignore"):  # one drape: sklearn's variance divides by k - 1 = 0
        pca = PCA(n_components=n_components, svd_solver="full").fit(flat)
    coefficients = pca.transform(flat)
    # The constant feature is in the design matrix, so the ridge's own intercept is off (it would go unpenalised
    # and double-count); the paper's W multiplies (beta, beta^2, 1) directly.
    ridge = Ridge(alpha=alpha, fit_intercept=False).fit(shape_features(betas, beta0, beta_scale), coefficients)
    ratio = np.zeros(n_components)
    # one drape has no variance: its single component is zero and explains nothing
    ratio[: len(pca.explained_variance_ratio_)] = pca.explained_variance_ratio_ if k > 1 else 0.0
    return ShapeModel(
        mean=pca.mean_.reshape(v, 3),
        components=pca.components_.reshape(n_components, v, 3),
        ridge=ridge.coef_.reshape(coefficients.shape[1], -1).T.copy(),  # sklearn drops the axis of one target
        explained_variance_ratio=ratio,
        beta0=np.asarray(beta0, dtype=np.float64),
        beta_scale=np.asarray(beta_scale, dtype=np.float64),
    )
