"""The voxel grid the verification keeps a scan's cloud on: one point per occupied voxel, the mean of its points.

`voxel_points` gives what small_gicp's ``voxelgrid_sampling`` (single-threaded) gives, bit for bit: a point's voxel
is ``floor(p / voxel_size)`` per axis, the three coordinates offset by 2^20 and packed 21 bits each into one key;
the voxels come out in the order of their keys, each the double-precision mean of its points, then float32;
points whose voxel coordinates fall outside the 21-bit range (and non-finite ones) are left out. Neither sort fixes
the order in which a voxel's points are summed; sums in another order differ at most in the last bits of a double,
which the float32 result rounds away (it did on every cloud compared: `tests/test_voxel_grid.py` compares the two
on clouds of every scale).

It is compiled without the GIL: small_gicp's call holds the GIL for its whole run, and the visual front end's image
thread, which needs the GIL between its compiled steps, runs beside the voxel grid (docs/benchmarks.md, "The ICP
cloud's voxel grid without the GIL").
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["voxel_points"]

#: bits of each packed voxel coordinate, and the offset that makes the coordinates of the range non-negative
_BITS = 21
_OFFSET = 1 << (_BITS - 1)


def voxel_points(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N, 3+) points (extra columns ignored) voxelised at ``voxel_size``: (M, 3) float32 (module docstring)."""
    p = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64)
    if p.shape[0] == 0:
        return np.zeros((0, 3), np.float32)
    return _voxel_means(p, 1.0 / float(voxel_size))


@njit(cache=True, nogil=True)
def _voxel_means(p: np.ndarray, inv: float) -> np.ndarray:  # pragma: no cover - compiled
    n = p.shape[0]
    keys = np.empty(n, np.uint64)
    kept = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        key = np.uint64(0)
        inside = True
        for d in range(3):
            c = np.floor(p[i, d] * inv)
            if not (c >= -_OFFSET and c < _OFFSET):  # NaN fails both comparisons
                inside = False
                break
            key |= np.uint64(np.int64(c) + _OFFSET) << np.uint64(_BITS * d)
        if inside:
            keys[m] = key
            kept[m] = i
            m += 1
    out = np.empty((m, 3), np.float32)
    if m == 0:
        return out
    keys = keys[:m]
    order = np.argsort(keys)
    v = 0
    sx = sy = sz = 0.0
    count = 0.0
    for j in range(m):
        k = order[j]
        if j > 0 and keys[k] != keys[order[j - 1]]:
            out[v, 0], out[v, 1], out[v, 2] = sx / count, sy / count, sz / count
            v += 1
            sx = sy = sz = 0.0
            count = 0.0
        i = kept[k]
        sx += p[i, 0]
        sy += p[i, 1]
        sz += p[i, 2]
        count += 1.0
    out[v, 0], out[v, 1], out[v, 2] = sx / count, sy / count, sz / count
    return out[: v + 1].copy()
