"""Flat radius-neighbour lists: every (query, neighbour) pair within a radius as parallel arrays.

The descriptor stack works on *pairs* rather than on ragged Python lists: one array of query ids, one of
neighbour ids and one of squared distances, grouped by query (``splits`` marks each query's segment). Pair
quantities are then computed at once and reduced per query with ``np.bincount`` / ``ufunc.reduceat``.

The search is Open3D's fixed-radius hash-grid search (``open3d.core.nns``), multithreaded C++ that returns
exactly this flat layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from placerec.errors import DependencyError, ScanDataError

__all__ = ["RadiusPairs", "radius_pairs", "check_points"]


def check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """``points`` as a C-contiguous (N, 3) float64 array of finite values, else `ScanDataError`."""
    P = np.ascontiguousarray(points, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ScanDataError(f"{name} must have shape (N, 3), got {P.shape}")
    if not np.isfinite(P).all():
        raise ScanDataError(f"{name} contain NaN or inf; remove invalid points first")
    return P


@dataclass(frozen=True)
class RadiusPairs:
    """All pairs (query q, point j) with ``|p_j - q| <= radius``, grouped by query in query order.

    ``query``, ``index`` (int64) and ``dist2`` (float64, squared distance) are parallel (M,) arrays; ``splits``
    (Q + 1,) gives each query's segment ``[splits[q], splits[q + 1])``. The order inside a segment is
    unspecified. A query point that belongs to the cloud is its own neighbour (distance 0).
    """

    query: np.ndarray
    index: np.ndarray
    dist2: np.ndarray
    splits: np.ndarray
    radius: float

    @property
    def n_queries(self) -> int:
        return int(self.splits.shape[0] - 1)

    @property
    def counts(self) -> np.ndarray:
        """Number of neighbours of every query (int64)."""
        return np.diff(self.splits)

    def within(self, radius: float) -> RadiusPairs:
        """The pairs with ``dist2 <= radius**2`` (``radius`` <= this one's), order kept."""
        if radius > self.radius + 1e-12:
            raise ScanDataError(f"cannot widen radius pairs from {self.radius} m to {radius} m")
        if radius >= self.radius:
            return self
        keep = np.flatnonzero(self.dist2 <= radius * radius)
        query = self.query.take(keep)
        splits = np.zeros(self.n_queries + 1, dtype=np.int64)
        np.cumsum(np.bincount(query, minlength=self.n_queries), out=splits[1:])
        return RadiusPairs(query, self.index.take(keep), self.dist2.take(keep), splits, float(radius))

    def adjacency(self, n_points: int):
        """The pairs as a (Q, n_points) CSR matrix of ones (row q holds q's neighbours)."""
        from scipy import sparse

        data = np.ones(self.index.shape[0])
        return sparse.csr_matrix((data, self.index, self.splits), shape=(self.n_queries, n_points))


def radius_pairs(points: np.ndarray, queries: np.ndarray, radius: float) -> RadiusPairs:
    """Every point of ``points`` within ``radius`` of each row of ``queries`` (both (N, 3) / (Q, 3))."""
    if not radius > 0:
        raise ScanDataError(f"search radius must be positive, got {radius}")
    P = np.ascontiguousarray(points, dtype=np.float64)
    Q = np.ascontiguousarray(queries, dtype=np.float64)
    nq = Q.shape[0]
    if P.shape[0] == 0 or nq == 0:
        empty_i = np.zeros(0, dtype=np.int64)
        return RadiusPairs(empty_i, empty_i, np.zeros(0), np.zeros(nq + 1, dtype=np.int64), float(radius))
    try:
        import open3d.core as o3c
    except ImportError as exc:  # pragma: no cover - open3d is a hard dependency
        raise DependencyError("the 3D descriptor stack needs open3d (pip install open3d)") from exc
    nns = o3c.nns.NearestNeighborSearch(o3c.Tensor.from_numpy(P))
    nns.fixed_radius_index(float(radius))
    idx, d2, splits = nns.fixed_radius_search(o3c.Tensor.from_numpy(Q), float(radius), sort=False)
    index = idx.numpy().astype(np.int64, copy=False)
    splits_np = splits.numpy().astype(np.int64, copy=False)
    query = np.repeat(np.arange(nq, dtype=np.int64), np.diff(splits_np))
    return RadiusPairs(query, index, d2.numpy().astype(np.float64, copy=False), splits_np, float(radius))
