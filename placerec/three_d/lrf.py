"""SHOT local reference frames (Tombari et al. 2010; PCL features/impl/shot_lrf.hpp), batched over keypoints.

For a keypoint p and its neighbours p_i within radius R (p itself excluded, at least 5 needed):
``M = sum (R - d_i)(p_i - p)(p_i - p)^T / sum (R - d_i)``; x is the eigenvector of the largest eigenvalue,
z of the smallest. Sign disambiguation: an axis is flipped when fewer than half of the neighbours have a
non-negative dot product with it, i.e. when ``2 * #{(p_i - p) . a >= 0} - n < 0``. On an exact tie PCL looks
at the five neighbours around the median distance and flips unless at least three of them have a strictly
positive dot product; we do the same. Finally y = z x x (a right-handed frame).
"""

from __future__ import annotations

import numpy as np

from placerec.errors import ScanDataError
from placerec.three_d._neighbors import RadiusPairs, check_points, radius_pairs

__all__ = ["shot_lrf", "lrf_from_offsets", "MIN_LRF_NEIGHBORS"]

MIN_LRF_NEIGHBORS = 5


def _tie_break(
    sign_pos: np.ndarray,
    ties: np.ndarray,
    q: np.ndarray,
    dist: np.ndarray,
    dots: np.ndarray,
    use: np.ndarray,
) -> None:
    """PCL's tie rule for the keypoints in ``ties``: flip (set ``sign_pos`` False) unless >= 3 of the 5
    neighbours around the median of the distance-sorted list have a positive dot product."""
    sel = np.flatnonzero(np.isin(q, ties) & use)
    order = sel[np.lexsort((dist[sel], q[sel]))]
    qs = q[order]
    starts = np.searchsorted(qs, ties, side="left")
    counts = np.searchsorted(qs, ties, side="right") - starts
    med = starts + counts // 2
    window = med[:, None] + np.arange(-2, 3)[None, :]
    window = np.clip(window, starts[:, None], (starts + counts - 1)[:, None])
    positive = (dots[order[window]] > 0).sum(axis=1)
    sign_pos[ties] = positive >= 3


def lrf_from_offsets(
    q: np.ndarray, splits: np.ndarray, d: np.ndarray, dist: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """LRFs from flat pairs grouped by keypoint: ``q`` keypoint of each pair (non-decreasing), ``splits``
    (K + 1,) segment bounds, ``d`` (3, M) offsets p_i - p stored as rows x, y, z, ``dist`` their norms.
    Pairs at distance 0 or beyond ``radius`` are ignored. Returns ``(frames, valid)`` as `shot_lrf`.
    """
    from scipy import sparse

    K = splits.shape[0] - 1
    counts = np.diff(splits)
    use = (dist > 0) & (dist <= radius)
    w = (radius - dist.astype(np.float64)) * use
    n = np.bincount(q, weights=use, minlength=K)
    wsum = np.bincount(q, weights=w, minlength=K)
    valid = (n >= MIN_LRF_NEIGHBORS) & (wsum > 0)
    # weighted scatter M[k] = sum_i w_i d_i d_i^T: the (K x M) matrix of weights times each product row
    W = sparse.csr_matrix((w, np.arange(q.shape[0]), splits), shape=(K, q.shape[0]))
    d64 = d.astype(np.float64)
    M = np.empty((K, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            M[:, a, b] = M[:, b, a] = W @ (d64[a] * d64[b])
    M[valid] /= wsum[valid, None, None]
    M[~valid] = np.eye(3)
    _, vecs = np.linalg.eigh(M)  # ascending eigenvalues
    axes = []
    for axis in (vecs[:, :, 2], vecs[:, :, 0]):  # x: largest, z: smallest
        rep = np.repeat(axis.astype(d.dtype), counts, axis=0)
        dots = d[0] * rep[:, 0] + d[1] * rep[:, 1] + d[2] * rep[:, 2]
        balance = 2 * np.bincount(q, weights=use & (dots >= 0), minlength=K) - n
        sign_pos = balance >= 0
        ties = np.flatnonzero((balance == 0) & valid)
        if ties.size:
            _tie_break(sign_pos, ties, q, dist, dots, use)
        axes.append(np.where(sign_pos[:, None], axis, -axis))
    x, z = axes
    frames = np.full((K, 3, 3), np.nan)
    frames[valid] = np.stack([x, np.cross(z, x), z], axis=1)[valid]
    return frames, valid


def shot_lrf(
    points: np.ndarray,
    keypoint_indices: np.ndarray,
    radius: float,
    pairs: RadiusPairs | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """SHOT LRFs of the keypoints: ``(frames, valid)``.

    ``frames`` (K, 3, 3) float64 holds the axes as rows (x, y, z), so ``frames[k] @ (q - p)`` gives local
    coordinates; ``valid`` is False (frame NaN) for keypoints with fewer than 5 neighbours within ``radius``.
    ``pairs``: precomputed neighbours of the keypoints (queries in keypoint order, radius >= ``radius``).
    """
    P = check_points(points)
    kp = np.asarray(keypoint_indices, dtype=np.int64).reshape(-1)
    if kp.size and (kp.min() < 0 or kp.max() >= P.shape[0]):
        raise ScanDataError(f"keypoint indices out of range for {P.shape[0]} points")
    K = kp.size
    if K == 0:
        return np.full((0, 3, 3), np.nan), np.zeros(0, dtype=bool)
    pr = (pairs or radius_pairs(P, P[kp], radius)).within(radius)
    if pr.n_queries != K:
        raise ScanDataError(f"pairs have {pr.n_queries} queries for {K} keypoints")
    d = (P[pr.index] - np.repeat(P[kp], pr.counts, axis=0)).T
    return lrf_from_offsets(pr.query, pr.splits, d, np.sqrt(np.einsum("ij,ij->i", d.T, d.T)), radius)
