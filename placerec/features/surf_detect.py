"""SURF interest-point detection (Bay et al., CVIU 2008, Sec. 3): fast-Hessian on box filters.

Conventions (shared with :mod:`placerec.features.surf_describe`):

* Pixel ``(x, y)`` is column ``x``, row ``y``; its centre has integer coordinates (OpenCV's convention).
* The integral image ``S`` has shape ``(H + 1, W + 1)`` with ``S[y, x] = sum(img[:y, :x])``.
* A box filter of side ``L`` (9, 15, 21, ...) approximates second-order Gaussian derivatives at scale
  ``s = 1.2 * L / 9``. Lobes follow the paper (and OpenSURF): ``l = L / 3``; Dxx/Dyy lobes are ``l`` by
  ``2l - 1``, Dxy lobes ``l`` by ``l`` one pixel off the centre. As in OpenCV's SURF (``resizeHaarPattern``), each
  lobe's sum is divided by that lobe's area (not by ``L * L`` as OpenSURF does), intensities are 0..255, and
  ``det = Dxx Dyy - (0.9 Dxy)^2``, so ``hessian_threshold`` (400 in the VPR paper's Table I) means what it
  means in OpenCV.
* Octave ``o`` (0-based) uses the paper's overlapping sizes ``L = 3 * (2**(o+1) * (l+1) + 1)`` for layers
  ``l = 0 .. n_octave_layers + 1`` (9, 15, 21, 27, 33 | 15, 27, 39, 51, 63 | 27, 51, ...) and evaluates the
  responses every ``2**o`` pixels.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "Detections",
    "integral_image",
    "layer_sizes",
    "hessian_layer",
    "detect_keypoints",
]

log = logging.getLogger(__name__)

_DXY_WEIGHT = 0.9  # the paper's relative weight w that balances the box-filter determinant


@dataclass(frozen=True)
class Detections:
    """Detected interest points as plain arrays (one entry per point).

    ``xy`` (K, 2) sub-pixel positions; ``size`` the interpolated filter side ``L`` (so ``s = 1.2 L / 9``);
    ``response`` the determinant of the Hessian at the detected sample (all three float32, as ``cv2.KeyPoint``
    stores them, so that describing from arrays or from keypoints gives the same descriptors); ``octave`` the
    0-based octave; ``laplacian`` the sign (+1/-1) of the trace of the Hessian (bright blob on dark: -1).
    """

    xy: np.ndarray
    size: np.ndarray
    response: np.ndarray
    octave: np.ndarray
    laplacian: np.ndarray

    def __len__(self) -> int:
        return int(self.response.shape[0])


def integral_image(img: np.ndarray) -> np.ndarray:
    """Summed-area table of a 2D image, shape (H + 1, W + 1): int32 for 8-bit images small enough not to
    overflow (exact, and half the memory traffic of float64), float64 otherwise."""
    img = np.ascontiguousarray(img)
    if img.dtype == np.uint8 and 255 * img.size < 2**31 - 1:
        return cv2.integral(img, sdepth=cv2.CV_32S)
    return cv2.integral(img.astype(np.float64, copy=False), sdepth=cv2.CV_64F)


def layer_sizes(octave: int, n_octave_layers: int) -> list[int]:
    """Box-filter sides of one octave (0-based): ``n_octave_layers + 2`` sizes, spacing ``6 * 2**octave``."""
    return [3 * ((2 ** (octave + 1)) * (layer + 1) + 1) for layer in range(n_octave_layers + 2)]


def _grid_range(n_pixels: int, half: int, step: int) -> tuple[int, int]:
    """First and one-past-last grid index ``k`` with ``half <= k * step <= n_pixels - 1 - half``."""
    first = -(-half // step)
    last = (n_pixels - 1 - half) // step
    return first, max(first, last + 1)


def hessian_layer(
    s: np.ndarray, size: int, step: int, grid_shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """Determinant and trace of the box-filter Hessian of side ``size`` on the grid of pixels ``(k*step, j*step)``.

    Returns ``(det, trace, (k0, k1, j0, j1))``: ``det`` float64 (lobe-area normalised), ``trace`` the raw
    ``Dxx + Dyy`` box sums in the table's dtype (only its sign is used), both of ``grid_shape`` and zero outside
    the index rectangle ``[k0, k1) x [j0, j1)`` where the whole filter lies inside the image. Each box sum is four
    integral-image lookups, done for the whole layer at once with shifted, strided views; boxes that share a row
    or column band share the first difference.
    """
    h, w = s.shape[0] - 1, s.shape[1] - 1
    lobe = size // 3
    half = (size - 1) // 2
    mid = (lobe - 1) // 2
    k0, k1 = _grid_range(h, half, step)
    j0, j1 = _grid_range(w, half, step)
    det = np.zeros(grid_shape, np.float64)
    trace = np.zeros(grid_shape, s.dtype)
    if k1 <= k0 or j1 <= j0:
        return det, trace, (k0, k0, j0, j0)
    y_first, y_last = k0 * step, (k1 - 1) * step
    x_first, x_last = j0 * step, (j1 - 1) * step

    def rows(a: np.ndarray, off: int) -> np.ndarray:  # a[y + off] for every grid row y
        return a[y_first + off : y_last + off + 1 : step]

    def cols(a: np.ndarray, off: int) -> np.ndarray:  # a[:, x + off] for every grid column x
        return a[:, x_first + off : x_last + off + 1 : step]

    def col_band(c0: int, c1: int) -> np.ndarray:  # per table row: sum over columns x+c0 .. x+c1 (inclusive)
        return cols(s, c1 + 1) - cols(s, c0)

    def row_band(r0: int, r1: int) -> np.ndarray:  # per table column: sum over rows y+r0 .. y+r1 (inclusive)
        return rows(s, r1 + 1) - rows(s, r0)

    # Dyy: +1 / -2 / +1 lobes of height `lobe`, width 2*lobe-1, stacked vertically == whole band - 3 * middle lobe
    band = col_band(-(lobe - 1), lobe - 1)
    dyy = (rows(band, half + 1) - rows(band, -half)) - 3 * (rows(band, mid + 1) - rows(band, -mid))
    band = row_band(-(lobe - 1), lobe - 1)
    dxx = (cols(band, half + 1) - cols(band, -half)) - 3 * (cols(band, mid + 1) - cols(band, -mid))
    # Dxy: four lobe x lobe squares one pixel off the centre row/column, + on the main diagonal, - off it
    band = col_band(-lobe, -1) - col_band(1, lobe)  # left minus right, per table row
    dxy = (rows(band, 0) - rows(band, -lobe)) - (rows(band, lobe + 1) - rows(band, 1))
    # OpenCV's normalisation: every lobe's sum is divided by that lobe's area
    lobe_area = float(lobe * (2 * lobe - 1))
    fxx = dxx.astype(np.float64)
    fxy = dxy.astype(np.float64)
    fxy *= fxy
    fxy *= (_DXY_WEIGHT * lobe_area / float(lobe * lobe)) ** 2
    out = det[k0:k1, j0:j1]
    np.multiply(fxx, dyy, out=out)
    out -= fxy
    out *= 1.0 / lobe_area**2
    trace[k0:k1, j0:j1] = dxx + dyy  # only its sign is used: left unnormalised, in the table's dtype
    return det, trace, (k0, k1, j0, j1)


# the 26 neighbours of a sample in (layer, row, column) scale space
_NEIGHBOURS = np.array(
    [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)], np.intp
)


def _refine(flat: np.ndarray, idx: np.ndarray, strides: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Fit a 3D quadratic around each candidate (Brown & Lowe 2002): offsets (K, 3) in (x, y, layer), ok mask.

    ``flat`` is the raveled (layer, row, column) response stack, ``idx`` the candidates' flat indices and
    ``strides`` the flat steps of one layer and one row.
    """
    s_layer, s_row = strides

    def at(dl: int, dk: int, dj: int) -> np.ndarray:
        return flat.take(idx + (dl * s_layer + dk * s_row + dj))

    v = at(0, 0, 0)
    g = np.stack(
        [
            (at(0, 0, 1) - at(0, 0, -1)) / 2,
            (at(0, 1, 0) - at(0, -1, 0)) / 2,
            (at(1, 0, 0) - at(-1, 0, 0)) / 2,
        ],
        axis=1,
    )
    dxx = at(0, 0, 1) + at(0, 0, -1) - 2 * v
    dyy = at(0, 1, 0) + at(0, -1, 0) - 2 * v
    dss = at(1, 0, 0) + at(-1, 0, 0) - 2 * v
    dxy = (at(0, 1, 1) - at(0, 1, -1) - at(0, -1, 1) + at(0, -1, -1)) / 4
    dxs = (at(1, 0, 1) - at(1, 0, -1) - at(-1, 0, 1) + at(-1, 0, -1)) / 4
    dys = (at(1, 1, 0) - at(1, -1, 0) - at(-1, 1, 0) + at(-1, -1, 0)) / 4
    hess = np.stack(
        [np.stack([dxx, dxy, dxs], 1), np.stack([dxy, dyy, dys], 1), np.stack([dxs, dys, dss], 1)], axis=1
    )
    det3 = np.linalg.det(hess) if len(v) else np.zeros(0)
    scale = np.maximum(np.abs(hess).max(axis=(1, 2)), 1e-300) if len(v) else np.ones(0)
    solvable = np.abs(det3) > 1e-12 * scale**3
    off = np.zeros((len(v), 3))
    if solvable.any():
        off[solvable] = -np.linalg.solve(hess[solvable], g[solvable][..., None])[..., 0]
    ok = solvable & np.all(np.abs(off) <= 0.5, axis=1)
    return off, ok


def detect_keypoints(
    img: np.ndarray,
    hessian_threshold: float = 400.0,
    n_octaves: int = 4,
    n_octave_layers: int = 3,
    integral: np.ndarray | None = None,
) -> Detections:
    """Fast-Hessian detector: scale-space maxima of det(H) above ``hessian_threshold``, sub-pixel/sub-scale refined.

    Each octave stacks ``n_octave_layers + 2`` response layers; maxima are searched in the inner layers with a
    strict 3x3x3 non-maximum suppression; a candidate is dropped when the fitted offset exceeds 0.5 sample in any
    of x, y, scale. Output is ordered by octave, then layer, row and column (deterministic).
    """
    s = integral_image(img) if integral is None else integral
    h, w = s.shape[0] - 1, s.shape[1] - 1
    out_xy, out_size, out_resp, out_oct, out_lap = [], [], [], [], []
    for octave in range(n_octaves):
        step = 2**octave
        sizes = layer_sizes(octave, n_octave_layers)
        if sizes[2] > min(h, w):  # no inner layer whose neighbours fit
            break
        grid = (-(-h // step), -(-w // step))
        layers = [hessian_layer(s, size, step, grid) for size in sizes]
        det = np.stack([lay[0] for lay in layers])
        for layer in range(1, len(sizes) - 1):
            # the next (larger) filter has the smallest valid rectangle: keep one sample of margin inside it
            k0, k1, j0, j1 = layers[layer + 1][2]
            if k1 - k0 < 3 or j1 - j0 < 3:
                continue
            inner = det[layer, k0 + 1 : k1 - 1, j0 + 1 : j1 - 1]
            kk, jj = np.nonzero(inner > hessian_threshold)
            if kk.size == 0:
                continue
            kk = kk + k0 + 1
            jj = jj + j0 + 1
            # strict maximum over the 26 neighbours (same layer first, then compact): flat lookups
            flat = det.ravel()
            strides = (grid[0] * grid[1], grid[1])
            idx = (layer * grid[0] + kk) * grid[1] + jj
            val = flat[idx]
            for same_layer in (True, False):
                is_max = np.ones(idx.shape, bool)
                for dl, dk, dj in _NEIGHBOURS[(_NEIGHBOURS[:, 0] == 0) == same_layer]:
                    is_max &= val > flat.take(idx + int(dl * strides[0] + dk * strides[1] + dj))
                idx, val = idx[is_max], val[is_max]
            off, ok = _refine(flat, idx, strides)
            idx, val, off = idx[ok], val[ok], off[ok]
            kk, jj = np.divmod(idx - layer * strides[0], grid[1])
            size_step = sizes[1] - sizes[0]
            out_xy.append(np.stack([(jj + off[:, 0]) * step, (kk + off[:, 1]) * step], axis=1))
            out_size.append(sizes[layer] + off[:, 2] * size_step)
            out_resp.append(val)
            out_oct.append(np.full(val.shape, octave, np.int32))
            out_lap.append(np.where(layers[layer][1][kk, jj] > 0, 1, -1).astype(np.int8))
    if not out_resp:
        f32 = np.float32
        return Detections(
            np.zeros((0, 2), f32),
            np.zeros(0, f32),
            np.zeros(0, f32),
            np.zeros(0, np.int32),
            np.zeros(0, np.int8),
        )
    det_out = Detections(  # float32 like cv2.KeyPoint, so that describing either gives the same descriptors
        np.concatenate(out_xy).astype(np.float32),
        np.concatenate(out_size).astype(np.float32),
        np.concatenate(out_resp).astype(np.float32),
        np.concatenate(out_oct),
        np.concatenate(out_lap),
    )
    log.debug("SURF detector: %d keypoints on a %dx%d image", len(det_out), h, w)
    return det_out
