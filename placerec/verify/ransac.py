"""RANSAC for a rigid pose from 3D-3D correspondences, compiled (Numba) over hypotheses.

Each hypothesis draws a minimal sample (3 pairs for 6-DoF, 2 for 4-DoF: a rotation about z and a translation
have 4 unknowns, two points give 6 equations), drops it when its pairwise distances disagree between the two
sides by more than twice the inlier threshold (a rigid motion keeps distances; the pre-test of Open3D's
edge-length checker and of PCL's sample consensus) or its source points are (nearly) collinear, solves it in
closed form (the Kabsch rotation, computed in Horn's quaternion form; or the yaw fit: `placerec.verify.kabsch`),
and scores it on all correspondences with the
MSAC cost ``sum min(r^2, thr^2)`` (Torr & Zisserman 2000), which ranks hypotheses with equal inlier counts by
their residuals. The number of hypotheses adapts to the best inlier ratio w seen so far: stop after
``log(1 - confidence) / log(1 - w^s)`` hypotheses (s = sample size) or ``max_iterations``. The pose is then
refit by least squares on its inliers, and inliers re-selected, until the set no longer changes (at most 5 times).
The loop runs compiled (cached on disk after the first use), far faster than NumPy batches of hypotheses
(``docs/verification.md``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numba import njit

from placerec.numba_cache import needs_compile
from placerec.verify.kabsch import check_pairs, rigid_fit, to_matrix
from placerec.verify.params import RansacParams

__all__ = ["RansacResult", "ransac_pose", "refit", "required_iterations"]

_MAX_REFITS = 5
log = logging.getLogger(__name__)
_COMPILE_NOTED = False


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


@njit(cache=True, nogil=True)
def _centroids(s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cs = np.zeros(3)
    cd = np.zeros(3)
    for i in range(s.shape[0]):
        cs += s[i]
        cd += d[i]
    return cs / s.shape[0], cd / s.shape[0]


@njit(cache=True, nogil=True)
def _max_eigenvector4(N: np.ndarray) -> np.ndarray:
    """Unit eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi rotations)."""
    A = N.copy()
    V = np.eye(4)
    scale = max(np.abs(A).max(), 1e-300)
    for _ in range(50):
        off = 0.0
        for p in range(3):
            for q in range(p + 1, 4):
                off += A[p, q] * A[p, q]
        if off <= (1e-15 * scale) ** 2:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                if A[p, q] == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * A[p, q])
                t = np.sign(theta) / (abs(theta) + np.sqrt(theta * theta + 1.0)) if theta != 0.0 else 1.0
                c = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(4):  # A <- J^T A J, V <- V J
                    akp, akq = A[k, p], A[k, q]
                    A[k, p], A[k, q] = c * akp - sn * akq, sn * akp + c * akq
                for k in range(4):
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k], A[q, k] = c * apk - sn * aqk, sn * apk + c * aqk
                for k in range(4):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p], V[k, q] = c * vkp - sn * vkq, sn * vkp + c * vkq
    best = 0
    for k in range(1, 4):
        if A[k, k] > A[best, best]:
            best = k
    return V[:, best] / np.sqrt(np.sum(V[:, best] ** 2))


@njit(cache=True, nogil=True)
def _kabsch3(s: np.ndarray, d: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
    """Least-squares rotation R and translation t of k pairs (k, 3): the Kabsch solution of
    `placerec.verify.kabsch.kabsch_batch`, computed as Horn's (1987) closed form (the rotation is the unit
    quaternion of the largest eigenvalue of a symmetric 4x4 matrix of the cross covariance), which needs no
    LAPACK SVD: the kernel compiles in a fraction of the time."""
    cs, cd = _centroids(s, d)
    S = np.zeros((3, 3))  # sum (s - cs)(d - cd)^T
    for i in range(s.shape[0]):
        for a in range(3):
            for b in range(3):
                S[a, b] += (s[i, a] - cs[a]) * (d[i, b] - cd[b])
    N = np.empty((4, 4))
    N[0, 0] = S[0, 0] + S[1, 1] + S[2, 2]
    N[1, 1] = S[0, 0] - S[1, 1] - S[2, 2]
    N[2, 2] = -S[0, 0] + S[1, 1] - S[2, 2]
    N[3, 3] = -S[0, 0] - S[1, 1] + S[2, 2]
    N[0, 1] = N[1, 0] = S[1, 2] - S[2, 1]
    N[0, 2] = N[2, 0] = S[2, 0] - S[0, 2]
    N[0, 3] = N[3, 0] = S[0, 1] - S[1, 0]
    N[1, 2] = N[2, 1] = S[0, 1] + S[1, 0]
    N[1, 3] = N[3, 1] = S[2, 0] + S[0, 2]
    N[2, 3] = N[3, 2] = S[1, 2] + S[2, 1]
    w, x, y, z = _max_eigenvector4(N)
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    for a in range(3):
        t[a] = cd[a] - (R[a, 0] * cs[0] + R[a, 1] * cs[1] + R[a, 2] * cs[2])


@njit(cache=True, nogil=True)
def _yaw2(s: np.ndarray, d: np.ndarray, R: np.ndarray, t: np.ndarray) -> None:
    """Least-squares rotation about z and translation of k pairs (`placerec.verify.kabsch.yaw_batch`)."""
    k = s.shape[0]
    cs, cd = _centroids(s, d)
    cross = 0.0
    dot = 0.0
    for i in range(k):
        ax, ay = s[i, 0] - cs[0], s[i, 1] - cs[1]
        bx, by = d[i, 0] - cd[0], d[i, 1] - cd[1]
        cross += ax * by - ay * bx
        dot += ax * bx + ay * by
    psi = np.arctan2(cross, dot)
    c, sn = np.cos(psi), np.sin(psi)
    R[:, :] = 0.0
    R[0, 0], R[0, 1], R[1, 0], R[1, 1], R[2, 2] = c, -sn, sn, c, 1.0
    for a in range(3):
        t[a] = cd[a] - (R[a, 0] * cs[0] + R[a, 1] * cs[1] + R[a, 2] * cs[2])


@njit(cache=True, nogil=True)
def _plausible(ps: np.ndarray, pd: np.ndarray, thr: float, six_dof: bool) -> bool:
    """Whether a sample's pairwise lengths agree on both sides within 2 ``thr``, its source points are at least
    2 ``thr`` apart and, for 6-DoF, span a triangle of at least that height."""
    min_len = 2.0 * thr
    k = ps.shape[0]
    longest = 0.0
    for a in range(k):
        for b in range(a + 1, k):
            ls = np.sqrt(np.sum((ps[a] - ps[b]) ** 2))
            ld = np.sqrt(np.sum((pd[a] - pd[b]) ** 2))
            if abs(ls - ld) > min_len or ls < min_len:
                return False
            longest = max(longest, ls)
    if six_dof:
        u, v = ps[0] - ps[1], ps[0] - ps[2]  # |u x v| is twice the triangle's area
        cx = u[1] * v[2] - u[2] * v[1]
        cy = u[2] * v[0] - u[0] * v[2]
        cz = u[0] * v[1] - u[1] * v[0]
        if np.sqrt(cx * cx + cy * cy + cz * cz) < min_len * longest:
            return False
    return True


@njit(cache=True, nogil=True)
def _search(
    src: np.ndarray,
    dst: np.ndarray,
    thr: float,
    max_iterations: int,
    confidence: float,
    six_dof: bool,
    seed: int,
) -> tuple[np.ndarray, np.ndarray, bool, int]:
    """The hypothesis loop (module docstring): best (R, t) by MSAC cost, whether one was found, samples drawn."""
    np.random.seed(seed)
    n = src.shape[0]
    size = 3 if six_dof else 2
    thr2 = thr * thr
    idx = np.empty(size, np.int64)
    ps = np.empty((size, 3))
    pd = np.empty((size, 3))
    R = np.empty((3, 3))
    t = np.empty(3)
    best_R = np.eye(3)
    best_t = np.zeros(3)
    best_cost, best_count, found = np.inf, 0, False
    drawn, needed = 0, float(max_iterations)
    log_miss = np.log1p(-confidence)
    while drawn < max_iterations and drawn < needed:
        drawn += 1
        for j in range(size):
            idx[j] = np.random.randint(0, n)
        if idx[0] == idx[1] or (six_dof and (idx[2] == idx[0] or idx[2] == idx[1])):
            continue
        for j in range(size):
            ps[j] = src[idx[j]]
            pd[j] = dst[idx[j]]
        if not _plausible(ps, pd, thr, six_dof):
            continue
        if six_dof:
            _kabsch3(ps, pd, R, t)
        else:
            _yaw2(ps, pd, R, t)
        cost, count = 0.0, 0
        for i in range(n):
            r2 = 0.0
            for a in range(3):
                e = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a] - dst[i, a]
                r2 += e * e
            if r2 <= thr2:
                count += 1
                cost += r2
            else:
                cost += thr2
        if cost < best_cost and count >= size:
            best_cost, found = cost, True
            best_R[:, :] = R
            best_t[:] = t
        if count > best_count:
            best_count = count
            p_good = (count / n) ** size  # the adaptive stop of `required_iterations`
            needed = 1.0 if p_good >= 1.0 else log_miss / np.log1p(-p_good)
    return best_R, best_t, found, drawn


def ransac_pose(src: np.ndarray, dst: np.ndarray, params: RansacParams | None = None) -> RansacResult:
    """Robust ``T_dst_src`` from pairs ``src[i] <-> dst[i]`` ((N, 3) each); see the module docstring.

    Fewer pairs than the sample size, or no hypothesis with ``min_inliers`` inliers, gives ``success=False``
    with the identity pose; malformed input raises `ScanDataError`.
    """
    params = params or RansacParams()
    s_all, d_all = check_pairs(src, dst)
    n = s_all.shape[0]
    six_dof = params.mode == "6dof"
    if n < max(3 if six_dof else 2, params.min_inliers):
        return RansacResult(np.eye(4), np.zeros(n, dtype=bool), 0, 0, False)
    global _COMPILE_NOTED
    if not _COMPILE_NOTED:
        _COMPILE_NOTED = True
        if needs_compile(_search):
            log.warning(
                "compiling the verification's RANSAC kernel (once after install or update, ~10 s; cached)"
            )
    R, t, found, drawn = _search(
        np.ascontiguousarray(s_all),
        np.ascontiguousarray(d_all),
        float(params.inlier_threshold),
        int(params.max_iterations),
        float(params.confidence),
        six_dof,
        int(params.seed),
    )
    if not found:
        return RansacResult(np.eye(4), np.zeros(n, dtype=bool), 0, drawn, False)
    T, mask = refit(to_matrix(R, t), s_all, d_all, params)
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
