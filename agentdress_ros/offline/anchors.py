"""Pose set and anchor poses: sensitivity-weighted k-means over the pose space (AgentDress Sec. 3.6).

Poses are (B, 3) rotation vectors. The root's rotation and translation are removed (drapes are simulated upright:
the garment hangs the same way relative to gravity whatever way the agent faces, and runtime skinning applies the
root). Distances weight each dof by its joint's sensitivity s^L (Eq. 11), so joints that barely move the garment
(a knee for a T-shirt) do not split clusters.
"""
from __future__ import annotations

import numpy as np
from sklearn.cluster import KMeans


def canonical_poses(rotvecs: np.ndarray) -> np.ndarray:
    """(P, B, 3) poses with the root (bone 0) rotation zeroed."""
    poses = np.array(rotvecs, dtype=np.float64, copy=True)
    poses[:, 0] = 0.0
    return poses


def subsample(rotvecs: np.ndarray, every: int) -> np.ndarray:
    """Every `every`-th frame of a (F, B, 3) motion (the paper samples one pose every four frames)."""
    return rotvecs[:: max(1, int(every))]


def weighted_features(poses: np.ndarray, dof_weights: np.ndarray) -> np.ndarray:
    """(P, D) pose features whose Euclidean distance is the sensitivity-weighted pose distance."""
    return poses.reshape(len(poses), -1) * np.sqrt(dof_weights / dof_weights.max())[None, :]


def weighted_kmeans_anchors(poses: np.ndarray, dof_weights: np.ndarray, n_anchors: int, seed: int = 0):
    """Anchor poses (N, B, 3) and the pose-set index of each.

    k-means runs on the weighted features; each anchor is the medoid of its cluster (the real pose nearest its
    centre), so every anchor is a pose a person actually took, not an average of several.
    """
    features = weighted_features(poses, dof_weights)
    n_anchors = min(n_anchors, len(np.unique(features, axis=0)))
    kmeans = KMeans(n_clusters=n_anchors, n_init=4, random_state=seed).fit(features)
    chosen = []
    for c, centre in enumerate(kmeans.cluster_centers_):
        members = np.flatnonzero(kmeans.labels_ == c)
        chosen.append(members[np.argmin(((features[members] - centre) ** 2).sum(axis=1))])
    chosen = np.array(chosen)
    return poses[chosen], chosen


def uniform_anchors(poses: np.ndarray, n_anchors: int) -> np.ndarray:
    """The comparison sampler: n poses evenly spaced through the pose set (indices)."""
    return np.linspace(0, len(poses) - 1, n_anchors).round().astype(int)


def coverage(poses: np.ndarray, anchors: np.ndarray, dof_weights: np.ndarray) -> float:
    """Mean sensitivity-weighted distance from every pose of the set to its nearest anchor (lower covers better)."""
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(weighted_features(anchors, dof_weights)).query(weighted_features(poses, dof_weights))
    return float(distance.mean())


def farthest_poses(poses: np.ndarray, chosen: np.ndarray, dof_weights: np.ndarray, count: int) -> np.ndarray:
    """Indices of `count` more poses of the set, each the one farthest (weighted distance) from all chosen so far.

    Greedy farthest-point sampling starting from the poses `chosen` (N, B, 3): the extra pose-model examples go
    where the anchors cover the set worst, instead of repeating poses the anchors already have.
    """
    features = weighted_features(poses, dof_weights)
    seeds = weighted_features(chosen, dof_weights)
    nearest = np.full(len(poses), np.inf)
    for seed in seeds:
        nearest = np.minimum(nearest, ((features - seed) ** 2).sum(axis=1))
    picked = []
    for _ in range(min(count, len(poses))):
        index = int(np.argmax(nearest))
        if nearest[index] <= 0.0:
            break
        picked.append(index)
        nearest = np.minimum(nearest, ((features - features[index]) ** 2).sum(axis=1))
    return np.array(picked, dtype=int)
