"""RANSAC for a rigid pose from 3D-3D correspondences, vectorised over hypotheses.

Each round draws ``batch_size`` minimal samples (3 pairs for 6-DoF, 2 for 4-DoF: a rotation about z and a
translation have 4 unknowns, two points give 6 equations), drops samples whose pairwise distances disagree
between the two sides by more than twice the inlier threshold (a rigid motion keeps distances; the pre-test of
Open3D's edge-length checker and of PCL's sample consensus) or whose source points are (nearly) collinear, solves
the survivors at once (`placerec.verify.kabsch`), and scores every hypothesis on all correspondences with the
MSAC cost ``sum min(r^2, thr^2)`` (Torr & Zisserman 2000), which ranks hypotheses with equal inlier counts by
their residuals. The number of rounds adapts to the best inlier ratio w seen so far: stop after
``log(1 - confidence) / log(1 - w^s)`` hypotheses (s = sample size) or ``max_iterations``. The pose is then
refit by least squares on its inliers, and inliers re-selected, until the set no longer changes (at most 5 times).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.verify.kabsch import check_pairs, kabsch_batch, rigid_fit, yaw_batch
from placerec.verify.params import RansacParams

__all__ = ["RansacResult", "ransac_pose", "refit", "required_iterations"]

_MAX_REFITS = 5


@dataclass(frozen=True)
class RansacResult:
    """``T_dst_src`` (4x4; identity when no pose was found), the inlier mask over the input pairs, the inlier
    count, the hypotheses drawn and whether a pose with at least ``min_inliers`` inliers was found."""

    T: np.ndarray
    inliers: np.ndarray
    n_inliers: int
    iterations: int
    success: bool

    @property
    def inlier_ratio(self) -> float:
        return self.n_inliers / max(len(self.inliers), 1)


def required_iterations(inlier_ratio: float, sample_size: int, confidence: float) -> float:
    """Hypotheses needed to draw one all-inlier sample with probability ``confidence`` (inf for ratio 0)."""
    p_good = inlier_ratio**sample_size
    if p_good >= 1.0:
        return 1.0
    if p_good <= 0.0:
        return float("inf")
    return float(np.log1p(-confidence) / np.log1p(-p_good))


def _samples(rng: np.random.Generator, n: int, size: int, count: int) -> np.ndarray:
    """Up to ``count`` rows of ``size`` distinct indices in [0, n): rows with a repeated index are dropped."""
    out = rng.integers(0, n, size=(count, size))
    srt = np.sort(out, axis=1)
    return out[(srt[:, 1:] != srt[:, :-1]).all(axis=1)]


def _plausible(ps: np.ndarray, pd: np.ndarray, thr: float, mode: str) -> np.ndarray:
    """Samples (H, s, 3) whose pairwise lengths agree on both sides within 2 ``thr``, whose source points are at
    least 2 ``thr`` apart and, for 6-DoF, span a triangle of at least that height."""
    a, b = np.triu_indices(ps.shape[1], 1)
    es, ed = ps[:, a] - ps[:, b], pd[:, a] - pd[:, b]
    ls = np.sqrt(np.einsum("hpi,hpi->hp", es, es))
    ld = np.sqrt(np.einsum("hpi,hpi->hp", ed, ed))
    min_len = 2.0 * thr
    ok = ((np.abs(ls - ld) <= min_len) & (ls >= min_len)).all(axis=1)
    if mode == "6dof":
        u, v = es[:, 0], es[:, 1]  # p0 - p1, p0 - p2: |u x v| is twice the triangle's area
        cx = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
        cy = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
        cz = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
        area2 = np.sqrt(cx * cx + cy * cy + cz * cz)
        ok &= area2 >= min_len * ls.max(axis=1)
    return ok


def ransac_pose(src: np.ndarray, dst: np.ndarray, params: RansacParams | None = None) -> RansacResult:
    """Robust ``T_dst_src`` from pairs ``src[i] <-> dst[i]`` ((N, 3) each); see the module docstring.

    Fewer pairs than the sample size, or no hypothesis with ``min_inliers`` inliers, gives ``success=False``
    with the identity pose; malformed input raises `ScanDataError`.
    """
    params = params or RansacParams()
    s_all, d_all = check_pairs(src, dst)
    n = s_all.shape[0]
    size = 3 if params.mode == "6dof" else 2
    solve = kabsch_batch if params.mode == "6dof" else yaw_batch
    thr2 = params.inlier_threshold**2
    none = RansacResult(np.eye(4), np.zeros(n, dtype=bool), 0, 0, False)
    if n < max(size, params.min_inliers):
        return none
    rng = np.random.default_rng(params.seed)
    best_cost, best_count, best_R, best_t = np.inf, 0, None, None
    drawn, needed = 0, float(params.max_iterations)
    while drawn < min(needed, params.max_iterations):
        count = min(params.batch_size, params.max_iterations - drawn)
        idx = _samples(rng, n, size, count)
        drawn += count
        if idx.shape[0] == 0:
            continue
        ps, pd = s_all[idx], d_all[idx]
        keep = _plausible(ps, pd, params.inlier_threshold, params.mode)
        if not keep.any():
            continue
        R, t = solve(ps[keep], pd[keep])
        res = s_all @ np.swapaxes(R, 1, 2) + (t[:, None] - d_all[None])  # (H, N, 3): R s + t - d
        r2 = np.einsum("hni,hni->hn", res, res)
        inl = r2 <= thr2
        counts = inl.sum(axis=1)
        cost = np.minimum(r2, thr2).sum(axis=1)
        h = int(np.argmin(cost))
        if cost[h] < best_cost and counts[h] >= size:
            best_cost, best_R, best_t = float(cost[h]), R[h], t[h]
            best_count = max(best_count, int(counts[h]))
        best_count = max(best_count, int(counts.max()))
        needed = required_iterations(best_count / n, size, params.confidence)
    if best_R is None:
        return RansacResult(np.eye(4), np.zeros(n, dtype=bool), 0, drawn, False)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = best_R, best_t
    T, mask = refit(T, s_all, d_all, params)
    n_in = int(mask.sum())
    return RansacResult(T, mask, n_in, drawn, n_in >= params.min_inliers)


def refit(
    T: np.ndarray, src: np.ndarray, dst: np.ndarray, params: RansacParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares refit of ``T`` on its inliers among ``src[i] <-> dst[i]``, inliers re-selected, until the set
    is stable (at most 5 times; a refit that loses inliers is not taken). Returns (T, inlier mask)."""
    params = params or RansacParams()
    s_all, d_all = check_pairs(src, dst)
    thr2 = params.inlier_threshold**2
    size = 3 if params.mode == "6dof" else 2
    mask = _inliers(T, s_all, d_all, thr2)
    for _ in range(_MAX_REFITS):
        if mask.sum() < size:
            break
        T_new = rigid_fit(s_all[mask], d_all[mask], mode=params.mode)
        new_mask = _inliers(T_new, s_all, d_all, thr2)
        if new_mask.sum() < mask.sum():
            break
        T, done, mask = T_new, np.array_equal(new_mask, mask), new_mask
        if done:
            break
    return T, mask


def _inliers(T: np.ndarray, src: np.ndarray, dst: np.ndarray, thr2: float) -> np.ndarray:
    r = src @ T[:3, :3].T + T[:3, 3] - dst
    return np.einsum("ni,ni->n", r, r) <= thr2
