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
_ORI_WINDOW = np.pi / 3  # sliding window width
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
    half = wsize // 2
    wsz = 2 * half
    corner = (
        ii.pad - (wsz - 1) / 2.0
    )  # top-left pixel of the wavelet, in padded coordinates, minus the centre
    x0 = np.rint(px + corner).astype(np.intp)
    y0 = np.rint(py + corner).astype(np.intp)
    c = ii.cols
    base = y0 * c
    base += x0
    take = ii.flat.take
    # table corners: rows top / middle / bottom (0, half, wsz) x columns left / middle / right (0, half, wsz)
    tl, tm, tr = take(base), take(base + half), take(base + wsz)
    ml, mr = take(base + half * c), take(base + (half * c + wsz))
    bl, bm, br = take(base + wsz * c), take(base + (wsz * c + half)), take(base + (wsz * c + wsz))
    diag = br - tl
    anti = tr - bl
    dx = (diag - anti) + 2 * (tm - bm)  # right half - left half
    dy = (diag + anti) + 2 * (ml - mr)  # bottom half - top half
    return dx.astype(np.float64), dy.astype(np.float64)


def dominant_orientation(ii: PaddedIntegral, xy: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Dominant orientation (radians, in [0, 2 pi)) of each keypoint: longest sum of Gaussian-weighted Haar
    responses (side 4s, samples within 6s) over a sliding angular window of pi/3 (windows start at every
    response's angle, so the result is exactly covariant with image rotation)."""
    n = len(scale)
    if n == 0:
        return np.zeros(0)
    s = scale[:, None]
    px = xy[:, 0:1] + _ORI_OFFSETS[None, :, 0] * s
    py = xy[:, 1:2] + _ORI_OFFSETS[None, :, 1] * s
    wsize = (2 * np.maximum(np.rint(2 * scale), 1)).astype(np.intp)[:, None]
    dx, dy = haar_responses(ii, px, py, wsize)
    dx = dx * _ORI_WEIGHTS
    dy = dy * _ORI_WEIGHTS
    ang = np.mod(np.arctan2(dy, dx), 2 * np.pi)
    order = np.argsort(ang, axis=1, kind="stable")
    ang = np.take_along_axis(ang, order, 1)
    dx = np.take_along_axis(dx, order, 1)
    dy = np.take_along_axis(dy, order, 1)
    m = ang.shape[1]
    # unroll the circle once so that windows may run past 2 pi; cumulative sums give window sums in O(1)
    ang2 = np.concatenate([ang, ang + 2 * np.pi], axis=1)
    cx = np.concatenate([np.zeros((n, 1)), np.cumsum(np.concatenate([dx, dx], 1), 1)], 1)
    cy = np.concatenate([np.zeros((n, 1)), np.cumsum(np.concatenate([dy, dy], 1), 1)], 1)
    # one flat, globally sorted array: row r lives in [r * 8 pi, r * 8 pi + 4 pi)
    base = (np.arange(n) * 8 * np.pi)[:, None]
    flat = (ang2 + base).ravel()
    starts = np.arange(m)[None, :] + np.arange(n)[:, None] * 2 * m
    ends = np.searchsorted(flat, (ang + _ORI_WINDOW + base).ravel(), side="left").reshape(n, m)
    ends -= np.arange(n)[:, None] * 2 * m
    begin = starts - np.arange(n)[:, None] * 2 * m
    sx = np.take_along_axis(cx, ends, 1) - np.take_along_axis(cx, begin, 1)
    sy = np.take_along_axis(cy, ends, 1) - np.take_along_axis(cy, begin, 1)
    best = np.argmax(sx * sx + sy * sy, axis=1)
    bx = sx[np.arange(n), best]
    by = sy[np.arange(n), best]
    return np.mod(np.arctan2(by, bx), 2 * np.pi)


def surf_descriptors(
    ii: PaddedIntegral, xy: np.ndarray, scale: np.ndarray, theta: np.ndarray, extended: bool = False
) -> np.ndarray:
    """SURF descriptors (K, 64) or (K, 128) float32, unit length.

    20s window along ``theta``, 20x20 samples at spacing s, Haar side 2s, Gaussian sigma 3.3s, responses rotated
    into the keypoint frame and summed per 5x5-sample sub-region as (dx, dy, |dx|, |dy|); ``extended`` splits the
    sums of dx, |dx| by the sign of dy and those of dy, |dy| by the sign of dx (SURF-128).
    """
    n = len(scale)
    dim = 128 if extended else 64
    if n == 0:
        return np.zeros((0, dim), np.float32)
    c = np.cos(theta)[:, None]
    sn = np.sin(theta)[:, None]
    s = scale[:, None]
    px = xy[:, 0:1] + s * (_DESC_A * c - _DESC_B * sn)
    py = xy[:, 1:2] + s * (_DESC_A * sn + _DESC_B * c)
    wsize = (2 * np.maximum(np.rint(scale), 1)).astype(np.intp)[:, None]
    dx, dy = haar_responses(ii, px, py, wsize)
    rx = (dx * c + dy * sn) * _DESC_WEIGHTS
    ry = (-dx * sn + dy * c) * _DESC_WEIGHTS
    q = _DESC_SAMPLES // 4

    def block_sum(v: np.ndarray) -> np.ndarray:
        return v.reshape(n, 4, q, 4, q).sum(axis=(2, 4))  # (n, 4 rows along v, 4 columns along u)

    if extended:
        neg_y, neg_x = ry < 0, rx < 0
        parts = [
            block_sum(np.where(neg_y, rx, 0.0)),
            block_sum(np.where(neg_y, np.abs(rx), 0.0)),
            block_sum(np.where(neg_y, 0.0, rx)),
            block_sum(np.where(neg_y, 0.0, np.abs(rx))),
            block_sum(np.where(neg_x, ry, 0.0)),
            block_sum(np.where(neg_x, np.abs(ry), 0.0)),
            block_sum(np.where(neg_x, 0.0, ry)),
            block_sum(np.where(neg_x, 0.0, np.abs(ry))),
        ]
    else:
        parts = [block_sum(rx), block_sum(ry), block_sum(np.abs(rx)), block_sum(np.abs(ry))]
    desc = np.stack(parts, axis=-1).reshape(n, dim)
    norm = np.linalg.norm(desc, axis=1, keepdims=True)
    desc = desc / np.where(norm > 0, norm, 1.0)
    return desc.astype(np.float32)
