"""Correspondences for verification: mutual nearest neighbours between two descriptor sets.

Binary descriptors (packed ``uint8``, e.g. ORB, BRISK): a compiled single-threaded loop, Hamming distance over
64-bit words (SWAR popcount), a query row against all of the other set's rows at once; sets are a few hundred to a
thousand descriptors per image, where a threaded library's start-up costs more than the work (docs/benchmarks.md,
visual pipeline per scan). Float descriptors (SuperPoint, SURF) by Euclidean distance: float32 dot products give
every squared distance approximately (summed 4 x 4 pairs at a time), which leaves a few candidates per row and per
column (those within a tolerance far above the products' rounding of the smallest); their exact distances, by the
all-pairs loop's own arithmetic (`_nearest_both_ways_l2`), decide. So the matches and distances are the all-pairs
loop's, bit for bit, in two fifths of its time for 300 x 256 floats. (A BLAS product was
faster still but left OpenBLAS's idle threads spinning on the other core after every candidate, which cost the
concurrent describe more than it saved: docs/benchmarks.md.)
"""

from __future__ import annotations

import numpy as np
from numba import njit

from placerec.retrieval.bits import to_words

__all__ = ["mutual_nearest"]

_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@njit(cache=True, nogil=True)
def _popcount(x: np.uint64) -> int:
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return int((x * _H01) >> np.uint64(56))


@njit(cache=True, nogil=True)
def _nearest_both_ways(a: np.ndarray, bt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For word arrays a (n, w) and bt (w, m), the second set's words transposed: each row of a's nearest row of
    b and its distance, and each row of b's nearest row of a (the first of equal distances, as ``argmin``), as
    int32. A row's m distances are summed word by word over contiguous columns and the other set's
    nearest-so-far updated without branches: loops the compiler vectorises (3x the speed of one pair at a time
    with branches for 1000 x 1000 ORB descriptors). Each side's nearest is the first of its equal distances, as
    the pairwise loop had it."""
    n, m = a.shape[0], bt.shape[1]
    nn_ab = np.zeros(n, np.int32)
    d_ab = np.zeros(n, np.int32)
    nn_ba = np.zeros(m, np.int32)
    d_ba = np.full(m, 1 << 30, np.int32)
    row = np.empty(m, np.int32)
    for i in range(n):
        row[:] = 0
        for w in range(a.shape[1]):
            aw = a[i, w]
            bw = bt[w]
            for j in range(m):
                row[j] += np.int32(_popcount(aw ^ bw[j]))
        nearest = np.argmin(row)  # the first of the row's equal minima
        nn_ab[i] = nearest
        d_ab[i] = row[nearest]
        for j in range(m):  # strictly nearer: an earlier row of a keeps a tie
            closer = row[j] < d_ba[j]
            d_ba[j] = row[j] if closer else d_ba[j]
            nn_ba[j] = np.int32(i) if closer else nn_ba[j]
    return nn_ab, d_ab, nn_ba


@njit(cache=True, nogil=True, fastmath=True)
def _nearest_both_ways_l2(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_nearest_both_ways` for float rows a (n, d), b (m, d) by squared Euclidean distance, one pair at a time.
    (The nearest-so-far update is written out in both kernels: as a shared compiled helper it made them 4-7x
    slower.)"""
    n, m = a.shape[0], b.shape[0]
    nn_ab = np.zeros(n, np.int64)
    d_ab = np.full(n, np.inf)
    nn_ba = np.zeros(m, np.int64)
    d_ba = np.full(m, np.inf)
    for i in range(n):
        for j in range(m):
            d = _sq_distance(a, i, b, j)
            if d < d_ab[i]:
                d_ab[i] = d
                nn_ab[i] = j
            if d < d_ba[j]:
                d_ba[j] = d
                nn_ba[j] = i
    return nn_ab, d_ab, nn_ba


def mutual_nearest(dq: np.ndarray, dm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between two descriptor sets (Hamming for packed uint8, Euclidean for float):
    (query rows, match rows, distances)."""
    if dq.shape[0] == 0 or dm.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    if dq.dtype == np.uint8:
        nn32, d, back = _nearest_both_ways(to_words(dq), np.ascontiguousarray(to_words(dm).T))
        nn, dist = nn32.astype(np.int64), d.astype(np.float64)
    else:
        q, m = np.ascontiguousarray(dq, np.float32), np.ascontiguousarray(dm, np.float32)
        small = min(q.shape[0], m.shape[0]) < _SCREEN_MIN_ROWS or q.shape[1] == 0
        nn, d, back = _nearest_both_ways_l2(q, m) if small else _nearest_both_ways_screened(q, m)
        dist = np.sqrt(d)
    qi = np.flatnonzero(back[nn] == np.arange(dq.shape[0]))
    return qi, nn[qi], dist[qi]


#: fewer rows on either side: the all-pairs loop (screening saves less than it costs)
_SCREEN_MIN_ROWS = 16
#: candidates are kept within this share of the largest squared norms of the smallest approximate distance: float32
#: dot products over d dimensions round by ~d * 6e-8 of them (1.5e-5 for 256), so the exact nearest is always kept
_CANDIDATE_TOLERANCE = 1e-3


def _nearest_both_ways_screened(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_nearest_both_ways_l2`'s result (the same arrays, bit for bit), screened: approximate squared distances
    ``|a|^2 + |b|^2 - 2 a.b`` in float32 (`_approx_distances`, ~2.5x faster than the exact loop) keep, for each
    row and each column, the entries within `_CANDIDATE_TOLERANCE` of its smallest; their exact distances, by
    the exact loop's own arithmetic, decide. Rows that are not finite take the exact loop (a NaN row would hide
    every column's nearest)."""
    a_sq = np.einsum("ij,ij->i", a, a)
    b_sq = np.einsum("ij,ij->i", b, b)
    if not (np.isfinite(a_sq).all() and np.isfinite(b_sq).all()):
        return _nearest_both_ways_l2(a, b)
    tol = np.float32(_CANDIDATE_TOLERANCE * (float(a_sq.max()) + float(b_sq.max())))
    return _screened(a, b, a_sq, b_sq, tol)


@njit(cache=True, nogil=True, fastmath=True)
def _screened(
    a: np.ndarray, b: np.ndarray, a_sq: np.ndarray, b_sq: np.ndarray, tol: np.float32
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """`_nearest_both_ways_screened`'s kernel. The exact distance is `_sq_distance`, as in `_nearest_both_ways_l2`,
    and candidates are visited in ascending order, so the first of equal distances wins as there."""
    n, m = a.shape[0], b.shape[0]
    approx = _approx_distances(a, b, a_sq, b_sq)
    row_min = np.full(n, np.inf, np.float32)
    col_min = np.full(m, np.inf, np.float32)
    for i in range(n):
        for j in range(m):
            v = approx[i, j]
            row_min[i] = min(row_min[i], v)
            col_min[j] = min(col_min[j], v)
    nn_ab, d_ab = _exact_nearest(approx, row_min + tol, a, b, True)
    nn_ba, _ = _exact_nearest(approx, col_min + tol, a, b, False)
    return nn_ab, d_ab, nn_ba


@njit(cache=True, nogil=True, fastmath=True)
def _approx_distances(
    a: np.ndarray, b: np.ndarray, a_sq: np.ndarray, b_sq: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """``|a_i|^2 + |b_j|^2 - 2 a_i.b_j`` for every pair, float32. The dot products of a 4 x 4 block of pairs are
    summed together, so each loaded element serves four products (twice the speed of one pair at a time); the
    rows and columns beyond the last whole block one pair at a time."""
    n, d = a.shape
    m = b.shape[0]
    out = np.empty((n, m), np.float32)
    n4, m4 = n - n % 4, m - m % 4
    acc = np.empty((4, 4), np.float32)
    for i in range(0, n4, 4):
        for j in range(0, m4, 4):
            s00 = s01 = s02 = s03 = s10 = s11 = s12 = s13 = np.float32(0.0)
            s20 = s21 = s22 = s23 = s30 = s31 = s32 = s33 = np.float32(0.0)
            for k in range(d):
                a0, a1, a2, a3 = a[i, k], a[i + 1, k], a[i + 2, k], a[i + 3, k]
                b0, b1, b2, b3 = b[j, k], b[j + 1, k], b[j + 2, k], b[j + 3, k]
                s00 += a0 * b0
                s01 += a0 * b1
                s02 += a0 * b2
                s03 += a0 * b3
                s10 += a1 * b0
                s11 += a1 * b1
                s12 += a1 * b2
                s13 += a1 * b3
                s20 += a2 * b0
                s21 += a2 * b1
                s22 += a2 * b2
                s23 += a2 * b3
                s30 += a3 * b0
                s31 += a3 * b1
                s32 += a3 * b2
                s33 += a3 * b3
            acc[0, 0], acc[0, 1], acc[0, 2], acc[0, 3] = s00, s01, s02, s03
            acc[1, 0], acc[1, 1], acc[1, 2], acc[1, 3] = s10, s11, s12, s13
            acc[2, 0], acc[2, 1], acc[2, 2], acc[2, 3] = s20, s21, s22, s23
            acc[3, 0], acc[3, 1], acc[3, 2], acc[3, 3] = s30, s31, s32, s33
            for u in range(4):
                for v in range(4):
                    out[i + u, j + v] = a_sq[i + u] + b_sq[j + v] - np.float32(2.0) * acc[u, v]
    for i in range(n):
        for j in range(m4 if i < n4 else 0, m):
            s = np.float32(0.0)
            for k in range(d):
                s += a[i, k] * b[j, k]
            out[i, j] = a_sq[i] + b_sq[j] - np.float32(2.0) * s
    return out


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _exact_nearest(
    approx: np.ndarray, limit: np.ndarray, a: np.ndarray, b: np.ndarray, by_row: bool
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """For each row of ``approx`` (``by_row``; else each column): among the entries at most its ``limit``, the one
    of least exact distance (the first of equal ones) and that distance."""
    n_out, n_in = (approx.shape[0], approx.shape[1]) if by_row else (approx.shape[1], approx.shape[0])
    nn = np.zeros(n_out, np.int64)
    dd = np.full(n_out, np.inf)
    for o in range(n_out):
        for x in range(n_in):
            i, j = (o, x) if by_row else (x, o)
            if approx[i, j] <= limit[o]:
                d = _sq_distance(a, i, b, j)
                if d < dd[o]:
                    dd[o] = d
                    nn[o] = x
    return nn, dd


@njit(cache=True, nogil=True, fastmath=True, inline="always")
def _sq_distance(a: np.ndarray, i: int, b: np.ndarray, j: int) -> float:  # pragma: no cover - compiled
    """Row ``i`` of ``a`` to row ``j`` of ``b``, squared: float32 differences squared, summed in float64 (the one
    definition both float kernels use, so their distances agree bit for bit)."""
    d = 0.0
    for k in range(a.shape[1]):
        e = a[i, k] - b[j, k]
        d += e * e
    return d
