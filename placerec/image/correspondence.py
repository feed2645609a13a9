"""Ground-truth pixel correspondences between the intensity images of two scans with known poses.

Every valid pixel of an intensity image holds one scan point (`IntensityImage.point_index`). Two pixels, one in
each image, correspond when their points, moved into a common frame with the scans' poses, lie within
``max_dist`` of each other: pixel ``a`` is paired with the pixel of the other scan whose point is nearest to its
own. This checks visibility and occlusion by construction: a surface point hidden from the second sensor (behind
an occluder, outside its field of view or its range) has no measured point near it there, so it gets no
partner; the occluder's own points lie further than ``max_dist`` away unless they touch the surface. With
``mutual`` the pairing must hold both ways, which also makes it one-to-one.

Used to train learned features (``tools/train_superpoint.py``) and to measure repeatability and matching score
(``tools/eval_features.py``), where a keypoint's match is correct within ``px`` pixels of its partner or
``max_dist`` metres in 3D.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from placerec.errors import ScanDataError
from placerec.image.projection import IntensityImage
from placerec.types import Scan

__all__ = [
    "PixelCorrespondences",
    "keypoint_points",
    "pixel_points",
    "pixel_correspondences",
    "transform_points",
]


@dataclass(frozen=True)
class PixelCorrespondences:
    """Pixel pairs: ``uv_a`` / ``uv_b`` (M, 2) int32 ``(column, row)``, ``dist`` (M,) float32 metres between
    their points in the common frame."""

    uv_a: np.ndarray
    uv_b: np.ndarray
    dist: np.ndarray

    def __len__(self) -> int:
        return int(self.uv_a.shape[0])


def pixel_points(image: IntensityImage, scan: Scan) -> np.ndarray:
    """(H, W, 3) float32: the scan point (sensor frame) behind each pixel; NaN where the pixel holds none
    (empty, or filled by interpolation)."""
    idx = image.point_index
    if idx.size and int(idx.max(initial=-1)) >= len(scan.xyz):
        raise ScanDataError(f"{scan.source or 'scan'}: the image indexes points the scan does not have")
    out = np.full(idx.shape + (3,), np.nan, np.float32)
    ok = idx >= 0
    out[ok] = scan.xyz[idx[ok]]
    return out


def transform_points(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``T`` (4, 4) applied to points (..., 3)."""
    T = np.asarray(T, np.float64)
    return (xyz @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def pixel_correspondences(
    points_a: np.ndarray,
    points_b: np.ndarray,
    a_to_b: np.ndarray,
    max_dist: float = 0.3,
    mutual: bool = True,
) -> PixelCorrespondences:
    """Correspondences between two images' pixel points (`pixel_points`, sensor frames), given ``a_to_b``, the
    4x4 transform taking scan A's frame into scan B's (``inv(pose_b) @ pose_a`` for world poses)."""
    if points_a.ndim != 3 or points_b.ndim != 3 or points_a.shape[2] != 3 or points_b.shape[2] != 3:
        raise ScanDataError(f"pixel points must be (H, W, 3), got {points_a.shape} and {points_b.shape}")
    if max_dist <= 0:
        raise ValueError(f"max_dist must be positive, got {max_dist}")
    va = np.flatnonzero(np.isfinite(points_a[..., 0]).ravel())
    vb = np.flatnonzero(np.isfinite(points_b[..., 0]).ravel())
    empty = np.zeros((0, 2), np.int32)
    if va.size == 0 or vb.size == 0:
        return PixelCorrespondences(empty, empty, np.zeros(0, np.float32))
    pa = transform_points(a_to_b, points_a.reshape(-1, 3)[va])
    pb = points_b.reshape(-1, 3)[vb]
    d_ab, j = cKDTree(pb).query(pa, distance_upper_bound=max_dist)
    hit = np.flatnonzero(np.isfinite(d_ab))
    ia, ib, dist = va[hit], vb[j[hit]], d_ab[hit]
    if mutual and hit.size:
        _, back = cKDTree(pa).query(pb[j[hit]])
        keep = va[back] == ia
        ia, ib, dist = ia[keep], ib[keep], dist[keep]
    wa, wb = points_a.shape[1], points_b.shape[1]
    uv_a = np.stack([ia % wa, ia // wa], axis=1).astype(np.int32)
    uv_b = np.stack([ib % wb, ib // wb], axis=1).astype(np.int32)
    return PixelCorrespondences(uv_a, uv_b, dist.astype(np.float32))


#: Pixel offsets (row, column) searched, nearest first, for a keypoint whose own pixel holds no scan point.
_NEIGHBOURS = ((0, 0), (0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1))


def keypoint_points(keypoints: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """Index of the scan point behind each keypoint (K,): the point the projection kept in the keypoint's pixel
    (OpenCV's pixel centres are integers), else in the nearest of its 8 neighbours that holds one (columns
    wrap around); -1 where none does (an interpolated row or a hole)."""
    h, w = point_index.shape
    kp = np.asarray(keypoints, np.float64).reshape(-1, 2)
    u = np.rint(kp[:, 0]).astype(np.int64)
    v = np.rint(kp[:, 1]).astype(np.int64)
    out = np.full(kp.shape[0], -1, np.int64)
    for dv, du in _NEIGHBOURS:
        todo = out < 0
        if not todo.any():
            break
        rows = v[todo] + dv
        inside = (rows >= 0) & (rows < h)
        found = np.full(rows.shape, -1, np.int64)
        found[inside] = point_index[rows[inside], np.mod(u[todo][inside] + du, w)]
        out[todo] = found
    return out
