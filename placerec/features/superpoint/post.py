"""SuperPoint's post-processing in NumPy, the same for every backend: keypoint probability, non-maximum
suppression, bicubic descriptor sampling."""

from __future__ import annotations

import cv2
import numpy as np

from placerec.features.superpoint.arch import CELL

__all__ = ["keypoint_probability", "select_keypoints", "sample_descriptors", "cubic_weights"]


def keypoint_probability(semi: np.ndarray) -> np.ndarray:
    """(Hc*8, Wc*8) keypoint probability from (65, Hc, Wc) detector logits: softmax over the 65 channels, the
    dustbin (channel 64) dropped, channel ``8 * dy + dx`` moved to pixel ``(8 * row + dy, 8 * col + dx)``."""
    s = np.asarray(semi, np.float32)
    e = np.exp(s - s.max(axis=0, keepdims=True))
    p = e[:-1] / e.sum(axis=0, keepdims=True)
    hc, wc = s.shape[1:]
    return p.reshape(CELL, CELL, hc, wc).transpose(2, 0, 3, 1).reshape(hc * CELL, wc * CELL)


def select_keypoints(
    prob: np.ndarray, mask: np.ndarray, min_probability: float, nms_radius: int, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(u, v)`` (K, 2) and probabilities (K,) of the ``n`` most probable local maxima of ``prob`` within
    ``nms_radius`` (a (2r+1)^2 window) that reach ``min_probability`` where ``mask`` is non-zero."""
    size = 2 * nms_radius + 1
    peak = prob >= cv2.dilate(prob, np.ones((size, size), np.uint8))
    v, u = np.nonzero(peak & (prob >= min_probability) & (mask != 0))
    score = prob[v, u]
    order = np.lexsort((u, v, -score.astype(np.float64)))[:n]
    return np.stack([u[order], v[order]], axis=1).astype(np.float64), score[order]


def cubic_weights(t: np.ndarray, a: float = -0.75) -> np.ndarray:
    """(..., 4) weights of the taps at offsets -1, 0, 1, 2 for fractional positions ``t`` in [0, 1) (Keys'
    cubic convolution with ``a`` = -0.75, as torch's and OpenCV's bicubic interpolation)."""
    t = np.asarray(t, np.float64)[..., None]
    x = np.abs(np.array([-1.0, 0.0, 1.0, 2.0]) - t)
    near = ((a + 2) * x - (a + 3)) * x * x + 1
    far = ((a * x - 5 * a) * x + 8 * a) * x - 4 * a
    return np.where(x <= 1, near, np.where(x < 2, far, 0.0))


def sample_descriptors(desc: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(K, D) float32 unit descriptors at pixels ``uv`` (K, 2), bicubically interpolated in the (D, Hc, Wc) coarse
    map (cell centres at pixel ``8 * i + 3.5``; taps beyond the border take the border's value, as torch's
    ``grid_sample(mode="bicubic", padding_mode="border", align_corners=False)``)."""
    d = np.asarray(desc, np.float32)
    dim, hc, wc = d.shape
    if len(uv) == 0:
        return np.zeros((0, dim), np.float32)
    x = (np.asarray(uv[:, 0], np.float64) + 0.5) / CELL - 0.5
    y = (np.asarray(uv[:, 1], np.float64) + 0.5) / CELL - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    wx, wy = cubic_weights(x - x0), cubic_weights(y - y0)
    taps = np.arange(-1, 3)
    cols = np.clip(x0[:, None].astype(np.int64) + taps, 0, wc - 1)
    rows = np.clip(y0[:, None].astype(np.int64) + taps, 0, hc - 1)
    out = np.einsum("dkij,ki,kj->kd", _taps(d, rows, cols), wy, wx).astype(np.float32)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return out / np.maximum(norm, 1e-12)


def _taps(d: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``d[:, rows[:, :, None], cols[:, None, :]]`` (D, K, 4, 4), the same values in the same memory layout (the
    D axis innermost, as NumPy lays out that indexing), gathered as whole cells: one transposed copy of the map,
    then one row per tap, instead of a strided gather per channel (a 64 x 1024 image's 300 keypoints: ~1 ms
    against ~4 ms). The einsum that weights the taps therefore adds them in the same order, bit for bit."""
    dim, hc, wc = d.shape
    cells = np.ascontiguousarray(d.reshape(dim, hc * wc).T)  # (Hc * Wc, D)
    index = rows[:, :, None] * wc + cols[:, None, :]  # (K, 4, 4)
    return cells.take(index.ravel(), axis=0).reshape(*index.shape, dim).transpose(3, 0, 1, 2)
