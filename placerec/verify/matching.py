"""Correspondences for verification: mutual nearest neighbours between two descriptor sets.

Compiled single-threaded loops: binary descriptors (packed ``uint8``, e.g. ORB, BRISK) by Hamming distance over
64-bit words (SWAR popcount), float descriptors (SURF, ...) by Euclidean distance. Sets are a few hundred
descriptors per image: a threaded library's start-up costs more than the work, and stalls when other processes
load the cores (docs/benchmarks.md, visual pipeline per scan).
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
def _nearest_both_ways(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For word arrays a (n, w), b (m, w): each row of a's nearest row of b and its distance, and each row of
    b's nearest row of a (the first of equal distances, as ``argmin``)."""
    n, m = a.shape[0], b.shape[0]
    nn_ab = np.zeros(n, np.int64)
    d_ab = np.full(n, 1 << 30, np.int64)
    nn_ba = np.zeros(m, np.int64)
    d_ba = np.full(m, 1 << 30, np.int64)
    for i in range(n):
        for j in range(m):
            d = 0
            for w in range(a.shape[1]):
                d += _popcount(a[i, w] ^ b[j, w])
            if d < d_ab[i]:
                d_ab[i] = d
                nn_ab[i] = j
            if d < d_ba[j]:
                d_ba[j] = d
                nn_ba[j] = i
    return nn_ab, d_ab, nn_ba


@njit(cache=True, nogil=True, fastmath=True)
def _nearest_both_ways_l2(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_nearest_both_ways` for float rows by squared Euclidean distance. (The nearest-so-far update is written out
    in both kernels: as a shared compiled helper it made them 4-7x slower.)"""
    n, m = a.shape[0], b.shape[0]
    nn_ab = np.zeros(n, np.int64)
    d_ab = np.full(n, np.inf)
    nn_ba = np.zeros(m, np.int64)
    d_ba = np.full(m, np.inf)
    for i in range(n):
        for j in range(m):
            d = 0.0
            for k in range(a.shape[1]):
                e = a[i, k] - b[j, k]
                d += e * e
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
        nn, d, back = _nearest_both_ways(to_words(dq), to_words(dm))
        dist = d.astype(np.float64)
    else:
        q = np.ascontiguousarray(dq, np.float32)
        nn, d, back = _nearest_both_ways_l2(q, np.ascontiguousarray(dm, np.float32))
        dist = np.sqrt(d)
    qi = np.flatnonzero(back[nn] == np.arange(dq.shape[0]))
    return qi, nn[qi], dist[qi]
