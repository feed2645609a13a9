"""Nearest descriptors for the 3D retrieval pipelines: the 2-NN ratio test and an approximate index.

``tau = d1 / d2`` (ISHOT paper, eq. 4) of a query descriptor's two nearest database descriptors decides
whether it votes (`ratio_votes`). Exact search is brute force (`placerec.retrieval.descriptor_store`: at
1344-d a k-d tree is much slower and HNSW slow to build, docs/benchmarks.md); `IvfIndex` is the sub-linear
approximate search (faiss IVF) a pipeline uses with ``index: ivf``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from placerec.retrieval.descriptor_store import DescriptorStore, omp_threads
from placerec.threads import import_openmp

__all__ = ["IvfIndex", "nn_ratio", "ratio_votes"]


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


def ratio_votes(
    dist: np.ndarray, idx: np.ndarray, row_entry: np.ndarray, n_entries: int, tau_max: float
) -> np.ndarray:
    """Votes per entry: each query row votes for the entry of its 1st neighbour when ``d1 / d2 < tau_max``."""
    ok = (nn_ratio(dist) < tau_max) & (idx[:, 0] >= 0)
    return np.bincount(row_entry[idx[ok, 0]], minlength=n_entries)
