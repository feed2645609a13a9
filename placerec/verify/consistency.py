"""Geometric consistency grouping of 3D correspondences (ISHOT paper Sec. IV-F, V; PCL's
``GeometricConsistencyGrouping``, recognition/impl/cg/geometric_consistency.hpp).

A rigid motion keeps distances, so two correspondences ``(q_i, m_i)`` and ``(q_j, m_j)`` are consistent when
``| |q_i - q_j| - |m_i - m_j| | <= consensus_resolution``. Correspondences are visited in order of quality
(descriptor distance, best first). Each one not yet in a cluster seeds a cluster, which then takes, in the same
order, every correspondence not yet in a cluster that is consistent with *all* its current members. A cluster is
kept when it has at least ``min_cluster_size`` members (the paper's "minimum cluster size"; PCL keeps clusters
with *more than* its ``gc_threshold``); only then are its members taken, so those of a rejected cluster may still
join a later one. A candidate is tested against the cluster's current members (PCL 1.x compares it with the
first correspondences of the sorted list instead, ``at (k)`` for ``at (consensus_set[k])``; we follow the
documented intent). PCL then runs a RANSAC on each kept cluster (inlier threshold = the resolution); here
`placerec.verify.verify` runs `ransac_pose` with its own metric threshold on the largest cluster.

The pairwise test fills (N, N) bitsets (64 pairs a word) and the greedy growth (inherently sequential: each
new member narrows the set) ANDs them, both in Numba: O(N^2) distance pairs, O(N^2 / 64) words per seed at most.
"""

from __future__ import annotations

import numba
import numpy as np

from placerec.errors import ScanDataError
from placerec.verify.kabsch import check_pairs
from placerec.verify.params import ConsistencyParams

__all__ = ["consistency_matrix", "group_correspondences"]


def consistency_matrix(src: np.ndarray, dst: np.ndarray, resolution: float) -> np.ndarray:
    """(N, N) bool: pairs of correspondences whose source and destination distances differ by <= ``resolution``."""
    s, d = check_pairs(src, dst)
    bits = _consistency_bits(s, d, float(resolution))
    return np.unpackbits(bits.view(np.uint8), axis=1, count=s.shape[0], bitorder="little").astype(bool)


@numba.njit(cache=True)
def _consistency_bits(s: np.ndarray, d: np.ndarray, res: float) -> np.ndarray:  # pragma: no cover - compiled
    """`consistency_matrix` as row bitsets: (N, ceil(N / 64)) uint64, bit j of row i set when i, j agree."""
    n = s.shape[0]
    bits = np.zeros((n, (n + 63) // 64), dtype=np.uint64)
    one = np.uint64(1)
    for i in range(n):
        bits[i, i >> 6] |= one << np.uint64(i & 63)
        for j in range(i + 1, n):
            ls = np.sqrt((s[i, 0] - s[j, 0]) ** 2 + (s[i, 1] - s[j, 1]) ** 2 + (s[i, 2] - s[j, 2]) ** 2)
            ld = np.sqrt((d[i, 0] - d[j, 0]) ** 2 + (d[i, 1] - d[j, 1]) ** 2 + (d[i, 2] - d[j, 2]) ** 2)
            if abs(ls - ld) <= res:
                bits[i, j >> 6] |= one << np.uint64(j & 63)
                bits[j, i >> 6] |= one << np.uint64(i & 63)
    return bits


@numba.njit(cache=True)
def _grow(bits: np.ndarray, order: np.ndarray, min_size: int) -> np.ndarray:  # pragma: no cover - compiled
    n, words = bits.shape
    label = np.full(n, -1, dtype=np.int64)  # cluster id per correspondence (in input numbering)
    alive = np.empty(words, dtype=np.uint64)  # bitset: consistent with every member so far
    members = np.empty(n, dtype=np.int64)
    one = np.uint64(1)
    n_clusters = 0
    for a in range(n):
        seed = order[a]
        if label[seed] >= 0:
            continue
        for w in range(words):
            alive[w] = bits[seed, w]
        size = 1
        members[0] = seed
        for b in range(n):
            j = order[b]
            if j == seed or label[j] >= 0 or not (alive[j >> 6] >> np.uint64(j & 63)) & one:
                continue
            members[size] = j
            size += 1
            for w in range(words):
                alive[w] &= bits[j, w]
        if size >= min_size:
            for k in range(size):
                label[members[k]] = n_clusters
            n_clusters += 1
    return label


def group_correspondences(
    src: np.ndarray,
    dst: np.ndarray,
    quality: np.ndarray | None = None,
    params: ConsistencyParams | None = None,
) -> list[np.ndarray]:
    """Consistent clusters of the pairs ``src[i] <-> dst[i]``: a list of index arrays (into the input, in visit
    order), largest first; empty when no cluster reaches ``min_cluster_size``.

    ``quality``: (N,) lower is better (descriptor distance); None visits the pairs in input order.
    """
    params = params or ConsistencyParams()
    s, d = check_pairs(src, dst)
    n = s.shape[0]
    if quality is None:
        order = np.arange(n, dtype=np.int64)
    else:
        q = np.asarray(quality, dtype=np.float64).reshape(-1)
        if q.shape[0] != n or not np.isfinite(q).all():
            raise ScanDataError(f"quality must hold {n} finite values, got shape {q.shape}")
        order = np.argsort(q, kind="stable").astype(np.int64)
    if n == 0:
        return []
    bits = _consistency_bits(s, d, float(params.consensus_resolution))
    label = _grow(bits, order, params.min_cluster_size)
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    clusters = []
    for c in range(int(label.max()) + 1):
        idx = np.flatnonzero(label == c)
        clusters.append(idx[np.argsort(rank[idx], kind="stable")])
    clusters.sort(key=len, reverse=True)
    return clusters
