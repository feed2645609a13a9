"""Closed-form rigid alignment of corresponding points, batched over hypotheses.

* 6-DoF (Kabsch 1976; Umeyama 1991 without scale): with centroids ``c_s``, ``c_d`` and the weighted cross
  covariance ``H = sum w (s - c_s)(d - c_d)^T = U S V^T``, the rotation minimising ``sum w |R s + t - d|^2`` is
  ``R = V diag(1, 1, sign det(V U^T)) U^T`` (the sign term keeps R a rotation where the plain ``V U^T`` would be a
  reflection) and ``t = c_d - R c_s``.
* 4-DoF (rotation about z only, for gravity-aligned sensors): z does not mix with x, y, so the weighted least
  squares yaw maximises ``sum w (a_x b_x + a_y b_y) cos(psi) + sum w (a_x b_y - a_y b_x) sin(psi)`` over the
  centred points a (source), b (destination): ``psi = atan2(sum w (a_x b_y - a_y b_x), sum w (a_x b_x + a_y b_y))``;
  ``t = c_d - R_z(psi) c_s`` (z translation included).

Every function takes stacks ``(H, k, 3)`` and returns ``(H, 3, 3)`` rotations and ``(H, 3)`` translations, so
RANSAC solves all its hypotheses of a batch in one call (one batched SVD).
"""

from __future__ import annotations

import numpy as np

from placerec.errors import ScanDataError

__all__ = ["kabsch_batch", "yaw_batch", "rigid_fit", "to_matrix", "check_pairs"]


def check_pairs(src: np.ndarray, dst: np.ndarray, min_pairs: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``src``, ``dst`` as float64 (N, 3) arrays of equal length with finite values; `ScanDataError` otherwise."""
    s = np.asarray(src, dtype=np.float64)
    d = np.asarray(dst, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3 or d.ndim != 2 or d.shape[1] != 3:
        raise ScanDataError(f"correspondences must be (N, 3) arrays, got {s.shape} and {d.shape}")
    if s.shape[0] != d.shape[0]:
        raise ScanDataError(
            f"correspondences: {s.shape[0]} source points but {d.shape[0]} destination points"
        )
    if s.shape[0] < min_pairs:
        raise ScanDataError(f"correspondences: {s.shape[0]} pairs, at least {min_pairs} needed")
    if not (np.isfinite(s).all() and np.isfinite(d).all()):
        raise ScanDataError("correspondences contain NaN or infinite coordinates")
    return s, d


def _centred(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None):
    if w is None:
        cs = src.mean(axis=1)
        cd = dst.mean(axis=1)
        wn = None
    else:
        wn = w / w.sum(axis=1, keepdims=True)
        cs = np.einsum("hk,hkc->hc", wn, src)
        cd = np.einsum("hk,hkc->hc", wn, dst)
    return src - cs[:, None], dst - cd[:, None], cs, cd, wn


def kabsch_batch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (H, 3, 3) and translations (H, 3) with ``R @ src[h, i] + t ~= dst[h, i]`` (least squares).

    ``src``, ``dst``: (H, k, 3); ``weights``: (H, k) non-negative, None = equal. Always proper rotations.
    """
    a, b, cs, cd, wn = _centred(src, dst, weights)
    if wn is not None:
        a = a * wn[..., None]
    cov = np.einsum("hki,hkj->hij", a, b)  # sum w a b^T
    U, _, Vt = np.linalg.svd(cov)
    V = np.swapaxes(Vt, 1, 2)
    Ut = np.swapaxes(U, 1, 2)
    sign = np.sign(np.linalg.det(V @ Ut))
    sign[sign == 0] = 1.0
    V[:, :, 2] *= sign[:, None]  # V diag(1, 1, sign)
    R = V @ Ut
    t = cd - np.einsum("hij,hj->hi", R, cs)
    return R, t


def yaw_batch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """4-DoF least squares: rotations about z (H, 3, 3) and translations (H, 3); inputs as `kabsch_batch`."""
    a, b, cs, cd, wn = _centred(src, dst, weights)
    w = np.ones(a.shape[:2]) if wn is None else wn
    cross = np.sum(w * (a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]), axis=1)
    dot = np.sum(w * (a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]), axis=1)
    psi = np.arctan2(cross, dot)
    c, s = np.cos(psi), np.sin(psi)
    R = np.zeros((a.shape[0], 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    t = cd - np.einsum("hij,hj->hi", R, cs)
    return R, t


def to_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """One 4x4 homogeneous matrix from a rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def rigid_fit(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, mode: str = "6dof"
) -> np.ndarray:
    """``T`` (4x4) minimising ``sum w |T src - dst|^2``: the 6-DoF Kabsch/Umeyama solution or the 4-DoF one.

    ``src``, ``dst``: (N, 3) with N >= 3 (6-DoF) or N >= 2 (4-DoF); `ScanDataError` for bad input.
    """
    if mode not in ("6dof", "4dof"):
        raise ScanDataError(f"rigid_fit: mode must be '6dof' or '4dof', got {mode!r}")
    s, d = check_pairs(src, dst, 3 if mode == "6dof" else 2)
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape[0] != s.shape[0] or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
            raise ScanDataError("rigid_fit: weights must be N finite non-negative values with a positive sum")
        w = w[None]
    solve = kabsch_batch if mode == "6dof" else yaw_batch
    R, t = solve(s[None], d[None], w)
    return to_matrix(R[0], t[0])
