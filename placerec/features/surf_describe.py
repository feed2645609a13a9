"""SURF orientation assignment and descriptor (Bay et al., CVIU 2008, Sec. 4), vectorised over keypoints.

Haar wavelets are read from an integral image of the (border-replicated) image, at sample points rounded to
the nearest pixel, as in the original: a wavelet of even side ``w`` centred on a sample point covers the pixels
``round(p - (w - 1) / 2) .. + w - 1`` on each axis; ``dx`` = right half - left half, ``dy`` = bottom - top.

Angles are in image coordinates (x right, y down): ``theta = atan2(dy, dx)``; the keypoint frame has axes
``u = (cos theta, sin theta)`` and ``v = (-sin theta, cos theta)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from placerec.features.surf_detect import integral_image

__all__ = [
    "PaddedIntegral",
    "haar_responses",
    "dominant_orientation",
    "surf_descriptors",
    "descriptor_extent",
]

_ORI_RADIUS = 6  # orientation samples within 6s, step s
_ORI_SIGMA = 2.0  # Gaussian sigma 2s
_ORI_WINDOW = np.pi / 3  # sliding window width (60 one-degree bins)
_DESC_SIGMA = 3.3  # Gaussian sigma 3.3s over the 20s window
_DESC_SAMPLES = 20  # 4x4 sub-regions of 5x5 samples, spacing s

_g = np.arange(-_ORI_RADIUS, _ORI_RADIUS + 1, dtype=np.float64)
_gx, _gy = np.meshgrid(_g, _g)
_inside = _gx**2 + _gy**2 <= _ORI_RADIUS**2
_ORI_OFFSETS = np.stack([_gx[_inside], _gy[_inside]], axis=1)  # (109, 2) in units of s
_ORI_WEIGHTS = np.exp(-(_ORI_OFFSETS**2).sum(1) / (2 * _ORI_SIGMA**2))

_d = np.arange(_DESC_SAMPLES, dtype=np.float64) - (_DESC_SAMPLES - 1) / 2  # -9.5 .. 9.5
_DESC_A, _DESC_B = (m.ravel() for m in np.meshgrid(_d, _d))  # a along u (columns), b along v (rows)
_DESC_WEIGHTS = np.exp(-(_DESC_A**2 + _DESC_B**2) / (2 * _DESC_SIGMA**2))


def descriptor_extent(scale: np.ndarray | float) -> np.ndarray:
    """Pixels around a keypoint of scale ``s`` that the orientation and descriptor samples may touch."""
    s = np.asarray(scale, np.float64)
    return np.ceil((_DESC_SAMPLES - 1) / 2 * np.sqrt(2) * s + 2 * np.maximum(np.round(2 * s), 1) + 2)


class PaddedIntegral:
    """Integral image of ``img`` padded by ``pad`` replicated pixels on every side (Haar lookups past the border)."""

    def __init__(self, img: np.ndarray, pad: int):
        self.pad = int(max(pad, 0))
        padded = cv2.copyMakeBorder(img, *(self.pad,) * 4, cv2.BORDER_REPLICATE) if self.pad else img
        self.sum = integral_image(padded)
        self.flat = self.sum.ravel()
        self.rows, self.cols = self.sum.shape


def haar_responses(
    ii: PaddedIntegral, px: np.ndarray, py: np.ndarray, wsize: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Haar wavelet responses (dx, dy) of even side ``wsize`` (broadcast against px, py) centred on (px, py).

    The caller guarantees that the padding covers every wavelet (see :func:`descriptor_extent`).
    """
    shift = _corner_shift(ii, wsize)
    return _haar_from_corners(ii, px + shift, py + shift, wsize // 2)


def _corner_shift(ii: PaddedIntegral, wsize: np.ndarray) -> np.ndarray:
    """Add to a wavelet's centre to get its top-left pixel in the padded table (before rounding)."""
    return ii.pad - (2 * (wsize // 2) - 1) / 2.0


def _haar_from_corners(
    ii: PaddedIntegral, x0: np.ndarray, y0: np.ndarray, half: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) float32 of wavelets of side ``2 * half`` whose top-left pixels are ``rint(x0), rint(y0)``."""
    c = ii.cols
    base = np.rint(y0).astype(np.intp)
    base *= c
    base += np.rint(x0).astype(np.intp)
    wsz = 2 * half
    take = ii.flat.take
    # table corners: rows top / middle / bottom (0, half, wsz) x columns left / middle / right (0, half, wsz)
    tl, tm, tr = take(base), take(base + half), take(base + wsz)
    ml, mr = take(base + half * c), take(base + (half * c + wsz))
    bl, bm, br = take(base + wsz * c), take(base + (wsz * c + half)), take(base + (wsz * c + wsz))
    diag = br - tl
    anti = tr - bl
    dx = (diag - anti) + 2 * (tm - bm)  # right half - left half
    dy = (diag + anti) + 2 * (ml - mr)  # bottom half - top half
    return dx.astype(np.float32), dy.astype(np.float32)


def dominant_orientation(ii: PaddedIntegral, xy: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Dominant orientation (radians, in [0, 2 pi)) of each keypoint.

    Gaussian-weighted (sigma 2s) Haar responses of side 4s at the samples within 6s are summed inside a window of
    pi/3 that slides around the circle in 1 degree steps (responses binned per degree, window sums from a
    circular cumulative sum); the orientation is that of the longest summed vector.
    """
    n = len(scale)
    if n == 0:
        return np.zeros(0)
    s = scale[:, None]
    half = np.maximum(np.rint(2 * scale), 1).astype(np.intp)[:, None]  # wavelet side 4s, even
    shift = _corner_shift(ii, 2 * half)
    dx, dy = _haar_from_corners(
        ii, (xy[:, 0:1] + shift) + _ORI_OFFSETS[:, 0] * s, (xy[:, 1:2] + shift) + _ORI_OFFSETS[:, 1] * s, half
    )
    dx *= _ORI_WEIGHTS.astype(np.float32)
    dy *= _ORI_WEIGHTS.astype(np.float32)
    nbins = 360
    width = int(round(np.degrees(_ORI_WINDOW)))
    bins = np.floor(np.degrees(np.arctan2(dy, dx))).astype(np.intp) % nbins
    bins += (np.arange(n) * nbins)[:, None]
    hx = np.bincount(bins.ravel(), dx.ravel(), n * nbins).reshape(n, nbins)
    hy = np.bincount(bins.ravel(), dy.ravel(), n * nbins).reshape(n, nbins)
    zero = np.zeros((n, 1))
    cx = np.cumsum(np.concatenate([zero, hx, hx[:, : width - 1]], axis=1), axis=1)
    cy = np.cumsum(np.concatenate([zero, hy, hy[:, : width - 1]], axis=1), axis=1)
    wx = cx[:, width:] - cx[:, :nbins]  # window [b, b + width) degrees, b = 0 .. 359
    wy = cy[:, width:] - cy[:, :nbins]
    best = np.argmax(wx * wx + wy * wy, axis=1)
    rows = np.arange(n)
    return np.mod(np.arctan2(wy[rows, best], wx[rows, best]), 2 * np.pi)


def _block_matrix() -> np.ndarray:
    """(400, 16): Gaussian weight of each descriptor sample in the column of its 5x5 sub-region."""
    q = _DESC_SAMPLES // 4
    idx = np.arange(_DESC_SAMPLES * _DESC_SAMPLES)
    block = (idx // _DESC_SAMPLES // q) * 4 + (idx % _DESC_SAMPLES) // q  # row-major over (v block, u block)
    m = np.zeros((idx.size, 16))
    m[idx, block] = _DESC_WEIGHTS
    return m


_BLOCKS32 = _block_matrix().astype(np.float32)


def surf_descriptors(
    ii: PaddedIntegral, xy: np.ndarray, scale: np.ndarray, theta: np.ndarray, extended: bool = False
) -> np.ndarray:
    """SURF descriptors (K, 64) or (K, 128) float32, unit length.

    20s window along ``theta``, 20x20 samples at spacing s, Haar side 2s, Gaussian sigma 3.3s, responses rotated
    into the keypoint frame and summed per 5x5-sample sub-region (4x4 of them, row-major along v then u) as
    (dx, dy, |dx|, |dy|); ``extended`` gives 8 sums per sub-region, (dx, |dx|) for dy < 0, (dx, |dx|) for
    dy >= 0, (dy, |dy|) for dx < 0, (dy, |dy|) for dx >= 0 (SURF-128).
    """
    n = len(scale)
    dim = 128 if extended else 64
    if n == 0:
        return np.zeros((0, dim), np.float32)
    c = np.cos(theta)[:, None]
    sn = np.sin(theta)[:, None]
    sc, ss = scale[:, None] * c, scale[:, None] * sn
    half = np.maximum(np.rint(scale), 1).astype(np.intp)[:, None]  # wavelet side 2s, even
    shift = _corner_shift(ii, 2 * half)
    px = (xy[:, 0:1] + shift) + _DESC_A * sc
    px -= _DESC_B * ss
    py = (xy[:, 1:2] + shift) + _DESC_A * ss
    py += _DESC_B * sc
    dx, dy = _haar_from_corners(ii, px, py, half)
    c32, s32 = c.astype(np.float32), sn.astype(np.float32)
    rx = dx * c32
    rx += dy * s32
    ry = dy * c32
    ry -= dx * s32
    if extended:
        neg_y, neg_x = ry < 0, rx < 0
        ax, ay = np.abs(rx), np.abs(ry)
        zero = np.float32(0)
        parts = [
            np.where(neg_y, rx, zero),
            np.where(neg_y, ax, zero),
            np.where(neg_y, zero, rx),
            np.where(neg_y, zero, ax),
            np.where(neg_x, ry, zero),
            np.where(neg_x, ay, zero),
            np.where(neg_x, zero, ry),
            np.where(neg_x, zero, ay),
        ]
    else:
        parts = [rx, ry, np.abs(rx), np.abs(ry)]
    # Gaussian weighting and the per-sub-region sums in one matrix product: (n, parts, 400) @ (400, 16)
    sums = np.stack(parts, axis=1) @ _BLOCKS32
    desc = sums.transpose(0, 2, 1).reshape(n, dim)  # per sub-region, its parts
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    desc /= np.where(norm > 0, norm, np.float32(1))
    return desc.astype(np.float32, copy=False)
