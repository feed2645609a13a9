"""Nearest descriptors for the 3D retrieval pipelines: the 2-NN ratio test, a pruned exact index and an
approximate one.

``tau = d1 / d2`` (ISHOT paper, eq. 4) of a query descriptor's two nearest database descriptors decides
whether it votes (`ratio_votes`). Exact search is brute force (`placerec.retrieval.descriptor_store`: at
1344-d a k-d tree is much slower and HNSW slow to build, docs/benchmarks.md), or `ProjectedIndex` (``index:
pca``): the same neighbours with a lower bound pruning most rows; `IvfIndex` is the sub-linear approximate search
(faiss IVF) a pipeline uses with ``index: ivf``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

from placerec.retrieval.descriptor_store import DescriptorStore, knn2, omp_threads, sq_norms
from placerec.threads import import_openmp

__all__ = ["IvfIndex", "ProjectedIndex", "nn_ratio", "ratio_votes"]


def nn_ratio(dist: np.ndarray) -> np.ndarray:
    """``tau = d1 / d2`` (eq. 4) of `knn2` distances; 1 where ``d2`` is 0 (two identical neighbours) or infinite
    (an approximate search found fewer than two)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where((dist[:, 1] > 0) & np.isfinite(dist[:, 1]), dist[:, 0] / dist[:, 1], 1.0)


class IvfIndex:
    """Approximate 2-NN over fixed rows: faiss ``IndexIVFFlat`` (L2), ``nlist`` k-means lists (trained on at most
    64 rows per list), ``nprobe`` of them searched per query; rows with no neighbour found get index -1 and an
    infinite distance. Searching visits about ``nprobe / nlist`` of the rows, so its time grows with the square
    root of the database when ``nlist`` does. Over a compressed `DescriptorStore` the lists hold codes of the
    same kind (``IndexIVFScalarQuantizer``, its own ranges fitted on the training rows), filled from blocks of
    decoded rows; the index keeps its own copy of the codes either way."""

    def __init__(
        self,
        rows: np.ndarray | DescriptorStore,
        nlist: int | None = None,
        nprobe: int = 16,
        threads: int | None = 1,
    ):
        faiss = import_openmp("faiss")
        store = rows if isinstance(rows, DescriptorStore) else DescriptorStore.from_rows(rows)
        n, d = store.shape
        self.nlist = max(1, min(n, int(nlist or round(np.sqrt(n)))))
        self.threads = threads
        if store.encoded:
            qt = faiss.ScalarQuantizer.QT_fp16 if store.dtype == "float16" else faiss.ScalarQuantizer.QT_8bit
            self.index: Any = faiss.IndexIVFScalarQuantizer(
                faiss.IndexFlatL2(d), d, self.nlist, qt, faiss.METRIC_L2, False
            )
        else:
            self.index = faiss.IndexIVFFlat(faiss.IndexFlatL2(d), d, self.nlist)
        sample = (
            store.rows()
            if n <= 64 * self.nlist
            else store.take(np.sort(np.random.default_rng(0).choice(n, 64 * self.nlist, replace=False)))
        )
        with omp_threads(threads):
            self.index.train(np.ascontiguousarray(sample))
            for a in range(0, n, 4096):
                self.index.add(np.ascontiguousarray(store.rows(a, a + 4096)))
        self.index.nprobe = min(int(nprobe), self.nlist)
        self.n_rows = n

    def knn2(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.ascontiguousarray(query, dtype=np.float32)
        with omp_threads(self.threads):
            d2, idx = self.index.search(q, 2)
        dist = np.where(idx >= 0, np.sqrt(np.maximum(d2, 0.0)), np.inf)
        return dist, np.asarray(idx, dtype=np.int64)


class ProjectedIndex:
    """Exact 2-NN over fixed rows, most rows pruned by a lower bound on their distance.

    The rows are projected on the ``dims`` leading principal axes of a sample of them (at most ``sample`` rows).
    The axes are orthonormal, so a row's distance to the query in projection is at most its true distance. A
    query's bound on its 2nd-NN distance is the 2nd smallest true distance among the ``probe`` rows nearest in
    projection; only the rows whose projected distance is within that bound can be among its two nearest, and
    their true distances decide (about 0.2 % of 98k simulated ISHOT rows a query at 256 axes, docs/benchmarks.md). The
    neighbours are brute force's (`knn2`), up to float rounding of the distances; the projected rows cost
    ``4 * dims`` bytes each. Batches whose candidate rows exceed half the database are searched by brute force.
    """

    def __init__(
        self,
        rows: np.ndarray | DescriptorStore,
        dims: int = 256,
        probe: int = 16,
        sample: int = 8192,
    ) -> None:
        store = rows if isinstance(rows, DescriptorStore) else DescriptorStore.from_rows(rows)
        n, d = store.shape
        self.store = store
        self.n_rows = n
        self.probe = max(2, int(probe))
        pick = (
            np.arange(n)
            if n <= sample
            else np.sort(np.random.default_rng(0).choice(n, sample, replace=False))
        )
        s = store.take(pick).astype(np.float64)
        self.mean = s.mean(axis=0)
        s -= self.mean
        _, vec = np.linalg.eigh(s.T @ s)  # ascending eigenvalues: the leading axes are the last columns
        self.axes = np.ascontiguousarray(vec[:, ::-1][:, : min(int(dims), d)], np.float32)
        self.mean = self.mean.astype(np.float32)
        self.projected = np.empty((n, self.axes.shape[1]), np.float32)
        for a in range(0, n, 4096):
            self.projected[a : a + 4096] = (store.rows(a, a + 4096) - self.mean) @ self.axes
        self.projected_sq = sq_norms(self.projected)

    def knn2(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distances (Q, 2) Euclidean, indices (Q, 2)) as `knn2`; needs at least 2 rows."""
        q = np.ascontiguousarray(query, dtype=np.float32)
        m, n = q.shape[0], self.n_rows
        if m == 0 or n <= self.probe:
            return knn2(q, self.store.rows(), "numpy", None)
        qp = (q - self.mean) @ self.axes
        # a row's squared projected distance is projected_sq[j] + |qp_i|^2 - 2 g[i, j]: the kernels read g once each
        g = qp @ self.projected.T
        near = _smallest(g, self.projected_sq, self.probe)
        qq = sq_norms(q)
        rows = self.store.take(near.reshape(-1)).reshape(m, self.probe, -1)
        probed = np.einsum("mpd,mpd->mp", rows, rows) - 2.0 * np.einsum("mpd,md->mp", rows, q) + qq[:, None]
        second = np.partition(probed, 1, axis=1)[:, 1]
        # float32 rounding of both sides is ~1e-6 of the squared norms; the margin is far wider
        margin = 1e-3 * (second + qq + float(self.projected_sq.max(initial=0.0)))
        qi, rj = _within(g, self.projected_sq, second + margin - sq_norms(qp))
        cand, inv = np.unique(rj, return_inverse=True)
        if cand.size > n // 2:
            return knn2(q, self.store.rows(), "numpy", None)
        x = self.store.take(cand)
        d2 = sq_norms(x)[inv] - 2.0 * (x @ q.T)[inv, qi] + qq[qi]
        order = np.lexsort((d2, qi))
        qi, rj, d2 = qi[order], rj[order], d2[order]
        first = np.searchsorted(qi, np.arange(m))
        take = np.stack([first, first + 1], axis=1)
        return np.sqrt(np.maximum(d2[take], 0.0)), rj[take].astype(np.int64)


@njit(cache=True, nogil=True)
def _smallest(g: np.ndarray, row_sq: np.ndarray, k: int) -> np.ndarray:  # pragma: no cover - compiled
    """For each row i of ``g`` (Q, N): the k columns j with the smallest ``row_sq[j] - 2 g[i, j]`` (in no order)."""
    out = np.empty((g.shape[0], k), np.int64)
    for i in range(g.shape[0]):
        best = np.full(k, np.inf)
        at = np.arange(k)
        worst = 0
        for j in range(g.shape[1]):
            v = row_sq[j] - 2.0 * g[i, j]
            if v < best[worst]:
                best[worst] = v
                at[worst] = j
                for t in range(k):
                    if best[t] > best[worst]:
                        worst = t
        out[i] = at
    return out


@njit(cache=True, nogil=True)
def _within(
    g: np.ndarray, row_sq: np.ndarray, limit: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """The pairs (i, j), row-major, with ``row_sq[j] - 2 g[i, j] <= limit[i]``."""
    count = 0
    for i in range(g.shape[0]):
        for j in range(g.shape[1]):
            if row_sq[j] - 2.0 * g[i, j] <= limit[i]:
                count += 1
    qi = np.empty(count, np.int64)
    rj = np.empty(count, np.int64)
    c = 0
    for i in range(g.shape[0]):
        for j in range(g.shape[1]):
            if row_sq[j] - 2.0 * g[i, j] <= limit[i]:
                qi[c] = i
                rj[c] = j
                c += 1
    return qi, rj


def ratio_votes(
    dist: np.ndarray, idx: np.ndarray, row_entry: np.ndarray, n_entries: int, tau_max: float
) -> np.ndarray:
    """Votes per entry: each query row votes for the entry of its 1st neighbour when ``d1 / d2 < tau_max``."""
    ok = (nn_ratio(dist) < tau_max) & (idx[:, 0] >= 0)
    return np.bincount(row_entry[idx[ok, 0]], minlength=n_entries)
