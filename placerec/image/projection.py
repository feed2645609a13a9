"""Cylindrical intensity images from LiDAR scans (VPR paper, Sec. IV-A).

Three ways to form the image, chosen by `ImageParams.mode`:

* ``uniform`` — the paper's eq. 2 for any point cloud: ``u = 0.5 (1 - theta / pi) W`` with ``theta = atan2(y, x)``
  and ``v = (1 - (phi + f_down) / f) H`` with ``phi = asin(z / rho)``, ``f = f_up + f_down`` (degrees of the
  vertical field of view above and below the horizon, both positive). Eq. 2 as printed adds ``f_up``; like the
  reference implementations (RangeNet++) we add the magnitude of the *lower* field of view, which puts the top of
  the field of view in row 0 and the bottom in row ``H``. Sensors with uneven beams (HDL-64) leave empty rows,
  which are detected and filled (`fill_empty_rows`).
* ``per-beam`` — the row is the beam's rank by elevation (from ``Scan.ring`` and the sensor's beam elevations),
  the column as above: no empty rows by construction.
* ``organized`` — an organised scan (Ouster) is used as it is: row = beam, column = azimuth step.

* ``spherical`` — for clouds that are not one 360 deg spinning sweep (Livox-style rosettes, solid-state scanners
  with a limited field of view, keyframes accumulated from several scans): azimuth and elevation on a regular grid
  of ``resolution_deg`` pixels over the sensor's field of view (``SensorInfo.horizontal_fov_deg`` centred on +x,
  else 360; the vertical one from the sensor or the cloud). Column ``u = (h/2 - theta) / h * W`` for a horizontal
  field of view ``h`` (for ``h`` = 360 this is eq. 2's column), row as in eq. 2. Without a given resolution the
  pixel is sized to the cloud's density: ``sqrt(field of view / (valid points / density_points_per_pixel))``,
  rounded to 0.05 deg so that keyframes of one sequence share an image size. Such clouds leave empty pixels
  between the points (a rosette covers the field of view unevenly); `fill_sparse_pixels` fills each empty pixel
  that has valid neighbours within ``fill_radius_px`` with their mean (measured in docs/sensors.md).

``auto`` picks ``organized`` for organised scans, ``spherical`` for sensors that are not spinning (see
`placerec.types.SensorInfo.is_spinning`), ``per-beam`` when rings are known, else ``uniform``. When
several points fall in one pixel the one with the smallest range is kept; the image stores its intensity (and,
in separate channels, its range and its point index).

Degenerate scans (no points, every point at the origin or at a non-finite range, all outside the field of view)
give a blank image (no valid pixel), from which extractors find no features; rings outside the sensor's beam
layout are a `ScanDataError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from pydantic import Field, model_validator

from placerec.errors import ConfigError, ScanDataError
from placerec.params import Params
from placerec.types import Scan, take_rows, valid_points

__all__ = [
    "ImageParams",
    "IntensityImage",
    "make_image",
    "project_uniform",
    "project_per_beam",
    "from_organized",
    "detect_empty_rows",
    "fill_empty_rows",
    "fill_vertical_holes",
    "fill_sparse_pixels",
    "project_spherical",
    "spherical_grid",
    "to_uint8",
    "UNIFORM_HOLES_MAX_GAP",
]

#: default ``fill_holes_max_gap`` of uniform (eq. 2) images: on 26 real KITTI HDL-64E frames it leaves no row
#: streak, where the paper's whole-row filling leaves 7 a frame (tools/eval_row_filling.py, docs/intensity_images.md)
UNIFORM_HOLES_MAX_GAP = 2


class ImageParams(Params):
    """How scans become intensity images.

    ``width``/``height``: image size (default: the sensor's columns / beams, else 1024 x 64). ``fov_up_deg`` /
    ``fov_down_deg``: vertical field of view above / below the horizon, both positive (default: from the sensor's
    beam elevations, else from the scan's own elevation range). ``empty_row_threshold``: a row whose fraction of
    valid pixels is below it counts as empty. ``fill_holes_max_gap`` > 0 also fills single empty pixels (partly
    empty rows, as KITTI's HDL-64 leaves) by vertical interpolation when valid pixels lie within that many rows
    above and below (an improvement over the paper's whole-row filling; 0 = off; None = `UNIFORM_HOLES_MAX_GAP`
    for the uniform projection, which leaves such streaks, and 0 for per-beam and organised images, which have
    none). ``clip``: ``percentile`` (of the image's valid intensities) or ``saturation`` (a fixed value in the scan's units) is mapped to 255; ``equalize`` applies histogram
    equalisation after that.
    """

    mode: Literal["auto", "uniform", "per-beam", "organized", "spherical"] = Field(
        "auto",
        description="VPR paper Sec. IV-A eq. 2 (uniform), per-beam rows, the organised scan, or a spherical grid "
        "over a limited field of view (non-spinning sensors, keyframes)",
    )
    resolution_deg: float | None = Field(
        None, gt=0, le=10, description="spherical: pixel size in deg; None = from the cloud's point density"
    )
    density_points_per_pixel: float = Field(
        1.0,
        gt=0,
        le=100,
        description="spherical, no resolution given: mean valid points per pixel to size for",
    )
    fill_radius_px: int = Field(
        1,
        ge=0,
        le=8,
        description="spherical: fill empty pixels from valid ones within this many px (0 = off)",
    )
    width: int | None = Field(
        None, gt=0, le=1 << 15, description="px (at most 32768); None = the sensor's columns, else 1024"
    )
    height: int | None = Field(
        None, gt=0, le=4096, description="px (at most 4096); None = the sensor's beams, else 64"
    )
    fov_up_deg: float | None = Field(
        None, description="deg above the horizon; None = from the sensor or scan"
    )
    fov_down_deg: float | None = Field(
        None, description="deg below the horizon; None = from the sensor or scan"
    )
    fill_empty_rows: bool = Field(True, description="VPR paper Sec. IV-A: interpolate empty rows")
    empty_row_threshold: float = Field(0.05, ge=0, le=1, description="valid-pixel fraction of an empty row")
    fill_holes_max_gap: int | None = Field(
        None,
        ge=0,
        description="rows; fill empty pixels vertically (0 = off, None = 2 for uniform images, else 0)",
    )
    clip: Literal["percentile", "saturation"] = Field("percentile", description="what maps to 255")
    percentile: float = Field(99.0, gt=0, le=100, description="of the valid intensities, for clip=percentile")
    saturation: float | None = Field(None, gt=0, description="intensity mapped to 255, for clip=saturation")
    equalize: bool = Field(False, description="histogram equalisation after clipping")

    @model_validator(mode="after")
    def _consistent(self) -> ImageParams:
        if self.clip == "saturation" and self.saturation is None:
            raise ValueError("clip 'saturation' needs a 'saturation' value")
        if (
            self.fov_up_deg is not None
            and self.fov_down_deg is not None
            and self.fov_up_deg + self.fov_down_deg <= 0
        ):
            raise ValueError(
                f"fov_up_deg + fov_down_deg must be positive, got {self.fov_up_deg} + {self.fov_down_deg}"
            )
        return self


_DEFAULT_PARAMS = ImageParams()


@dataclass(frozen=True, eq=False)
class IntensityImage:
    """An image formed from a scan: float ``intensity``, ``range`` (0 where empty), ``valid`` mask,
    ``point_index`` (index of the scan point in each pixel, -1 where empty or interpolated), the 8-bit
    ``image`` used by feature extractors, and ``filled_rows`` (rows filled by interpolation)."""

    intensity: np.ndarray
    range: np.ndarray
    valid: np.ndarray
    point_index: np.ndarray
    image: np.ndarray
    filled_rows: np.ndarray
    mode: str

    @property
    def shape(self) -> tuple[int, int]:
        return self.intensity.shape


def _columns(xyz: np.ndarray, width: int) -> np.ndarray:
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    u = np.floor(0.5 * (1.0 - theta / np.pi) * width).astype(np.int64)
    return np.mod(u, width)  # theta = -pi lands on u = W: wrap to column 0


def _scatter_nearest(
    rows: np.ndarray,
    cols: np.ndarray,
    ranges: np.ndarray,
    scan: Scan,
    idx: np.ndarray,
    shape: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel, the point with the smallest range: (intensity, range, point index) images; all empty when no
    point is given."""
    h, w = shape
    inten = np.zeros(h * w, np.float32)
    rng = np.zeros(h * w, np.float32)
    pidx = np.full(h * w, -1, np.int32)
    if rows.size == 0:
        return inten.reshape(shape), rng.reshape(shape), pidx.reshape(shape)
    pix = rows * w + cols
    first = _nearest_per_pixel(pix, np.ascontiguousarray(ranges, np.float32), h * w)
    inten[pix[first]] = scan.intensity[idx[first]]
    rng[pix[first]] = ranges[first]
    pidx[pix[first]] = idx[first]
    return inten.reshape(shape), rng.reshape(shape), pidx.reshape(shape)


@numba.njit(cache=True)
def _nearest_per_pixel(pix: np.ndarray, ranges: np.ndarray, n_pixels: int) -> np.ndarray:  # pragma: no cover
    """Indices (into ``pix``) of each occupied pixel's nearest point, the first of equal ranges, in pixel order:
    one pass over the points (a sort of them costs several times more on a 120k-point scan)."""
    best = np.full(n_pixels, -1, np.int64)
    for i in range(pix.shape[0]):
        p = pix[i]
        b = best[p]
        if b < 0 or ranges[i] < ranges[b]:
            best[p] = i
    return best[best >= 0]


def _valid_points(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    r = scan.ranges
    idx = np.flatnonzero(valid_points(scan, intensity=True, ranges=r))
    return idx, r[idx]


def _elevations(xyz: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Elevation (deg) of points ``xyz`` at ranges ``r``."""
    return np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))


def _fov(
    scan: Scan, params: ImageParams, xyz: np.ndarray, r: np.ndarray, phi: np.ndarray | None = None
) -> tuple[float, float]:
    """(up, down) field of view of the image; ``phi``: the points' `_elevations` where computed already."""
    up, down = params.fov_up_deg, params.fov_down_deg
    sensor_fov = scan.sensor.vertical_fov_deg
    if (up is None or down is None) and sensor_fov is not None:
        # half a beam spacing of margin so the extreme beams fall inside the image (none for a field of view
        # given without a beam layout: it bounds the points already)
        margin = 0.0
        if scan.sensor.beam_elevations_deg:
            elev = np.sort(np.asarray(scan.sensor.beam_elevations_deg))
            margin = 0.5 * float(np.median(np.diff(elev))) if elev.size > 1 else 0.5
        up = sensor_fov[0] + margin if up is None else up
        down = sensor_fov[1] + margin if down is None else down
    if up is None or down is None:
        phi = _elevations(xyz, r) if phi is None else phi
        up = float(phi.max()) + 0.1 if up is None else up
        down = float(-phi.min()) + 0.1 if down is None else down
    if up + down <= 0:
        raise ConfigError(f"vertical field of view must be positive, got up={up}, down={down}")
    return float(up), float(down)


def project_uniform(
    scan: Scan, params: ImageParams = _DEFAULT_PARAMS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 2 projection (uniform beams): (intensity, range, point index) images.

    Compiled in two passes over the points (elevations of the valid points, then rows, columns and each pixel's
    nearest point), in float32 as numpy computes them for float32 scans: the images numpy's step-by-step
    version gives (kept as the reference in tests/test_scan_path_identity.py), 5x faster on a real HDL-64 scan."""
    h = params.height or scan.sensor.n_beams or 64
    w = params.width or scan.sensor.columns or 1024
    r = scan.ranges
    valid = valid_points(scan, intensity=True, ranges=r)
    phi = _valid_elevations(scan.xyz, r, valid)
    if not valid.any():
        empty = np.zeros(0, np.int64)
        return _scatter_nearest(empty, empty, r[:0], scan, empty, (h, w))
    up, down = _fov(scan, params, scan.xyz, r, phi[valid])
    inten, rng, pidx = _scatter_uniform(
        scan.xyz, scan.intensity, r, phi, valid, np.float32(down), np.float32(up + down), h, w
    )
    return inten.reshape(h, w), rng.reshape(h, w), pidx.reshape(h, w)


#: numpy's float32 `np.degrees` factor (180 / pi, each in float32, divided in float32)
_DEGREES_F32 = np.float32(180.0) / np.float32(np.pi)


@numba.njit(cache=True, nogil=True)
def _valid_elevations(xyz: np.ndarray, r: np.ndarray, valid: np.ndarray) -> np.ndarray:  # pragma: no cover
    """`_elevations` (float32 degrees, as numpy computes them) of the ``valid`` float32 points at ranges ``r``;
    0 elsewhere."""
    phi = np.zeros(xyz.shape[0], np.float32)
    one = np.float32(1.0)
    for i in range(xyz.shape[0]):
        if valid[i]:
            s = min(max(xyz[i, 2] / r[i], -one), one)
            phi[i] = np.arcsin(s) * _DEGREES_F32
    return phi


@numba.njit(cache=True, nogil=True)
def _scatter_uniform(
    xyz: np.ndarray,
    intensity: np.ndarray,
    r: np.ndarray,
    phi: np.ndarray,
    valid: np.ndarray,
    down: np.float32,
    span: np.float32,
    h: int,
    w: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Eq. 2's row and column of each valid point (float32 arithmetic, as `_columns` and `project_uniform`'s
    rows in numpy) and per pixel the nearest point, the first of equal ranges: flat (intensity, range, index)."""
    best = np.full(h * w, -1, np.int64)
    one, half = np.float32(1.0), np.float32(0.5)
    pi, fh, fw = np.float32(np.pi), np.float32(h), np.float32(w)
    for i in range(xyz.shape[0]):
        if not valid[i]:
            continue
        v = int(np.floor((one - (phi[i] + down) / span) * fh))
        if v < 0 or v >= h:
            continue
        theta = np.float32(np.arctan2(xyz[i, 1], xyz[i, 0]))
        u = int(np.floor(half * (one - theta / pi) * fw)) % w
        p = v * w + u
        b = best[p]
        if b < 0 or r[i] < r[b]:
            best[p] = i
    inten = np.zeros(h * w, np.float32)
    rng = np.zeros(h * w, np.float32)
    pidx = np.full(h * w, -1, np.int32)
    for p in range(h * w):
        b = best[p]
        if b >= 0:
            inten[p] = intensity[b]
            rng[p] = r[b]
            pidx[p] = b
    return inten, rng, pidx


def project_per_beam(
    scan: Scan, params: ImageParams = _DEFAULT_PARAMS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One row per beam (rank of its elevation, top first), columns from eq. 2: no empty rows by construction."""
    if scan.ring is None:
        raise ScanDataError(f"{scan.source or 'scan'}: per-beam projection needs the ring index")
    elev = scan.sensor.beam_elevations_deg
    if elev is not None:
        rank = np.empty(len(elev), np.int64)
        rank[np.argsort(-np.asarray(elev), kind="stable")] = np.arange(len(elev))
        n_rows = len(elev)
    else:  # no layout: assume ring 0 is the top beam and rings are consecutive
        n_rows = max(int(scan.ring.max()) + 1, 1) if len(scan) else 1
        rank = np.arange(n_rows)
    w = params.width or scan.sensor.columns or 1024
    idx, r = _valid_points(scan)
    ring = scan.ring[idx].astype(np.int64)
    ok = (ring >= 0) & (ring < rank.size)
    if elev is not None and not ok.all():
        raise ScanDataError(
            f"{scan.source or 'scan'}: {int((~ok).sum())} of {ok.size} points have a ring outside "
            f"0..{rank.size - 1}, the {rank.size}-beam layout of sensor {scan.sensor.name!r}; "
            "use image mode 'uniform' or give the right sensor"
        )
    idx, r, ring = idx[ok], r[ok], ring[ok]
    cols = _columns(take_rows(scan.xyz, idx), w)
    return _scatter_nearest(rank[ring], cols, r, scan, idx, (n_rows, w))


#: the automatic spherical pixel size is rounded to this step (deg) and kept within these bounds
_RESOLUTION_STEP_DEG = 0.05
_RESOLUTION_BOUNDS_DEG = (0.05, 2.0)


@dataclass(frozen=True)
class SphericalGrid:
    """The angular grid of a spherical image: horizontal field of view ``h_fov`` (deg, centred on +x), vertical
    field of view ``up`` / ``down`` (deg above / below the horizon) and the image size."""

    h_fov: float
    up: float
    down: float
    height: int
    width: int

    def pixels(self, xyz: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows, columns, inside) of points ``xyz`` at ranges ``r``."""
        theta = np.degrees(np.arctan2(xyz[:, 1], xyz[:, 0]))
        phi = _elevations(xyz, r)
        u = np.floor((0.5 * self.h_fov - theta) / self.h_fov * self.width).astype(np.int64)
        v = np.floor((1.0 - (phi + self.down) / (self.up + self.down)) * self.height).astype(np.int64)
        if self.h_fov >= 360.0:
            u = np.mod(u, self.width)
        inside = (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)
        return v, u, inside


def spherical_grid(scan: Scan, params: ImageParams = _DEFAULT_PARAMS) -> SphericalGrid:
    """The spherical grid ``scan`` is projected onto (see the module docstring for the automatic resolution)."""
    idx, r = _valid_points(scan)
    return _spherical_grid(scan, params, take_rows(scan.xyz, idx), r)


def _spherical_grid(scan: Scan, params: ImageParams, xyz: np.ndarray, r: np.ndarray) -> SphericalGrid:
    """`spherical_grid` of the valid points ``xyz`` at ranges ``r``."""
    h_fov = float(scan.sensor.horizontal_fov_deg or 360.0)
    if len(xyz) == 0:
        up, down = scan.sensor.vertical_fov_deg or (1.0, 1.0)
    else:
        up, down = _fov(scan, params, xyz, r)
    res = params.resolution_deg
    if res is None:
        n = max(len(xyz), 1)
        res = float(np.sqrt(h_fov * (up + down) * params.density_points_per_pixel / n))
        res = round(res / _RESOLUTION_STEP_DEG) * _RESOLUTION_STEP_DEG
        res = float(np.clip(res, *_RESOLUTION_BOUNDS_DEG))
    width = params.width or max(int(np.ceil(h_fov / res)), 1)
    height = params.height or max(int(np.ceil((up + down) / res)), 1)
    return SphericalGrid(h_fov, float(up), float(down), int(height), int(width))


def project_spherical(
    scan: Scan, params: ImageParams = _DEFAULT_PARAMS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A spherical grid over the sensor's field of view: (intensity, range, point index) images."""
    idx, r = _valid_points(scan)
    xyz = take_rows(scan.xyz, idx)
    grid = _spherical_grid(scan, params, xyz, r)
    rows, cols, inside = grid.pixels(xyz, r)
    return _scatter_nearest(
        rows[inside], cols[inside], r[inside], scan, idx[inside], (grid.height, grid.width)
    )


def fill_sparse_pixels(image: np.ndarray, valid: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill each empty pixel that has valid pixels within ``radius`` (a square window) with their mean (a
    normalised box filter). Returns (image, valid); pixels with no valid neighbour stay empty."""
    if radius <= 0 or valid.all() or not valid.any():
        return image, valid
    import cv2

    k = (2 * radius + 1, 2 * radius + 1)
    w = valid.astype(np.float32)
    total = cv2.boxFilter(np.where(valid, image, 0).astype(np.float32), -1, k, normalize=False)
    count = cv2.boxFilter(w, -1, k, normalize=False)
    hole = ~valid & (count > 0.5)
    out = image.astype(np.float32, copy=True)
    out[hole] = total[hole] / count[hole]
    return out, valid | hole


def from_organized(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An organised scan's own grid: (intensity, range, point index); zero points are empty."""
    if scan.shape is None:
        raise ScanDataError(f"{scan.source or 'scan'}: not an organised scan")
    r = scan.ranges
    ok = valid_points(scan, intensity=True, ranges=r)
    inten = np.where(ok, scan.intensity, 0.0).astype(np.float32).reshape(scan.shape)
    rng = np.where(ok, r, 0.0).astype(np.float32).reshape(scan.shape)
    pidx = np.where(ok, np.arange(len(scan), dtype=np.int32), -1).reshape(scan.shape)
    return inten, rng, pidx


def detect_empty_rows(valid: np.ndarray, threshold: float = 0.05) -> np.ndarray:
    """Rows whose fraction of valid pixels is below ``threshold``.

    The paper's recipe binarises the image (valid -> 1) and filters it with a horizontal kernel as wide as the
    image; at a row's centre column that filter's response is exactly the row's fraction of valid pixels, which
    is what is computed here (a row mean, instead of an O(W^2) convolution whose other columns are not used).
    """
    return np.asarray(valid, dtype=np.float32).mean(axis=1) < threshold


def fill_empty_rows(image: np.ndarray, empty: np.ndarray) -> np.ndarray:
    """Fill each empty row by linear interpolation between the nearest non-empty rows above and below (per
    column); rows above the first / below the last non-empty row copy it."""
    good = np.flatnonzero(~empty)
    out = image.astype(np.float32, copy=True)
    if good.size == 0 or not empty.any():
        return out
    rows = np.flatnonzero(empty)
    pos = np.searchsorted(good, rows)
    above = good[np.clip(pos - 1, 0, good.size - 1)]
    below = good[np.clip(pos, 0, good.size - 1)]
    span = (below - above).astype(np.float32)
    t = np.divide(rows - above, span, out=np.zeros_like(span), where=span > 0)
    out[rows] = (1.0 - t)[:, None] * out[above] + t[:, None] * out[below]
    return out


def fill_vertical_holes(image: np.ndarray, valid: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill empty pixels from the nearest valid pixels above and below in the same column when both lie within
    ``max_gap`` rows (linear interpolation). Returns (image, valid)."""
    holes = _vertical_holes(valid, max_gap)
    if holes is None:
        return image, valid
    return _fill_holes(image, holes), valid | holes[0]


_Holes = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _vertical_holes(valid: np.ndarray, max_gap: int) -> _Holes | None:
    """The pixels `fill_vertical_holes` fills: (hole mask, row above, row below, column, weight of the row below)
    of each, row-major; None when there is none. Found once, they fill every image of the same pixels."""
    h = valid.shape[0]
    rows = np.arange(h)[:, None]
    above, below = _valid_above_below(np.ascontiguousarray(valid, dtype=np.bool_))
    hole = ~valid & (above >= 0) & (below < h) & (rows - above <= max_gap) & (below - rows <= max_gap)
    r, c = np.nonzero(hole)
    if r.size == 0:
        return None
    a, b = above[r, c], below[r, c]
    return hole, a, b, c, (r - a) / (b - a)


@numba.njit(cache=True)
def _valid_above_below(valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Per pixel, the nearest valid row at or above it (-1: none) and at or below it (the height: none)."""
    h, w = valid.shape
    above = np.empty((h, w), np.int64)
    below = np.empty((h, w), np.int64)
    last = np.full(w, -1, np.int64)
    for r in range(h):
        for c in range(w):
            if valid[r, c]:
                last[c] = r
            above[r, c] = last[c]
    last[:] = h
    for r in range(h - 1, -1, -1):
        for c in range(w):
            if valid[r, c]:
                last[c] = r
            below[r, c] = last[c]
    return above, below


def _fill_holes(image: np.ndarray, holes: _Holes) -> np.ndarray:
    """``image`` with the pixels of `_vertical_holes` interpolated between the rows above and below."""
    hole, a, b, c, t = holes
    out = image.astype(np.float32, copy=True)
    out[hole] = (1 - t) * image[a, c] + t * image[b, c]
    return out


def to_uint8(intensity: np.ndarray, valid: np.ndarray, params: ImageParams = _DEFAULT_PARAMS) -> np.ndarray:
    """Map intensities to 0..255: clip at a percentile of the valid pixels or at a saturation value."""
    if params.clip == "saturation":
        top = float(params.saturation)  # type: ignore[arg-type]  # set whenever clip is saturation
    else:
        vals = intensity[valid]
        top = float(np.percentile(vals, params.percentile)) if vals.size else 1.0
    scale = 255.0 / top if top > 0 else 0.0
    img: np.ndarray = np.clip(intensity * scale, 0, 255).astype(np.uint8)
    img[~valid] = 0
    if params.equalize:
        import cv2

        img = cv2.equalizeHist(img)
    return img


def _resolve_mode(scan: Scan, mode: str) -> str:
    if mode == "auto":
        if scan.shape is not None:
            return "organized"
        if not scan.sensor.is_spinning:
            return "spherical"
        return "per-beam" if scan.ring is not None else "uniform"
    return mode


def make_image(scan: Scan, params: ImageParams = _DEFAULT_PARAMS) -> IntensityImage:
    """Form the intensity image of ``scan`` (see the module docstring)."""
    mode = _resolve_mode(scan, params.mode)
    if mode == "organized":
        inten, rng, pidx = from_organized(scan)
    elif mode == "per-beam":
        inten, rng, pidx = project_per_beam(scan, params)
    elif mode == "spherical":
        inten, rng, pidx = project_spherical(scan, params)
    else:
        inten, rng, pidx = project_uniform(scan, params)
    valid = pidx >= 0
    filled = np.zeros(inten.shape[0], bool)
    if mode == "spherical":  # no row structure: fill the gaps between the points instead of rows
        rng, _ = fill_sparse_pixels(rng, valid, params.fill_radius_px)
        inten, valid = fill_sparse_pixels(inten, valid, params.fill_radius_px)
        return IntensityImage(inten, rng, valid, pidx, to_uint8(inten, valid, params), filled, mode)
    if params.fill_empty_rows:
        filled = detect_empty_rows(valid, params.empty_row_threshold)
        if filled.any() and (~filled).any():
            inten = fill_empty_rows(inten, filled)
            rng = fill_empty_rows(rng, filled)
            valid = valid.copy()
            valid[filled] = fill_empty_rows(valid.astype(np.float32), filled)[filled] > 0.5
        else:
            filled[:] = False
    gap = params.fill_holes_max_gap
    if gap is None:
        gap = UNIFORM_HOLES_MAX_GAP if mode == "uniform" else 0
    holes = _vertical_holes(valid, gap) if gap > 0 else None
    if holes is not None:  # the range and the intensity image have the same holes
        rng, inten, valid = _fill_holes(rng, holes), _fill_holes(inten, holes), valid | holes[0]
    image = to_uint8(inten, valid, params)
    return IntensityImage(inten, rng, valid, pidx, image, filled, mode)
