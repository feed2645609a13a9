"""Intensity observations of map cells: registered scans -> unique (cell, beam, incidence bin, raw bin) counts.

Every point within the intensity range cut-off is moved into the world frame with its scan's pose and assigned
to a map cell: a ``voxel_size`` voxel, split by range band so that beams are compared at similar ranges (the range
compensation of real sensors is imperfect). A cell is kept when at least ``min_beams`` different beams saw it:
only those tie beams together.

Geometry matters because a vehicle-mounted sensor sees a surface from a beam-specific viewpoint: each beam meets
the ground at its own fixed angle, and a higher beam sees a given facade cell from nearer, closer to its normal.
Levinson & Thrun's model (a cell looks the same to every beam) would put these differences into the per-beam
tables. We therefore estimate each point's incidence angle from the registered map (the normal of its planar
``normal_cell`` neighbourhood) and keep points seen within ``arccos(min_cos_incidence)`` of the normal; the EM
then compares reflectivities under a Lambertian ``cos`` factor per incidence bin (`Observations.inc_factor`).
See docs/calibration.md.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from placerec.calibration.params import CalibrationParams
from placerec.errors import ScanDataError
from placerec.types import Scan, Sequence, as_pose

log = logging.getLogger(__name__)

__all__ = [
    "Observations",
    "RawBinning",
    "RegisteredPoints",
    "collect_observations",
    "gather_points",
    "group_observations",
    "incidence_cosine",
    "observations_from_points",
    "restrict_observations",
]

_KEY_BITS = 19  # per axis: +-2^18 cells (+-65 km at 0.25 m): 57 bits, room for a 6-bit range band
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


@dataclass(frozen=True)
class RawBinning:
    """Raw intensity bins: bin ``a`` is centred on raw value ``a * step``; ``n`` bins."""

    n: int
    step: float

    @classmethod
    def for_data(cls, intensity_max: float | None, observed_max: float, bins: int | None) -> RawBinning:
        """One bin per integer for <= 8-bit data (``intensity_max`` 255), else ``bins`` (256) bins up to the max."""
        top = float(intensity_max) if intensity_max else float(observed_max)
        if bins is None and 2.0 <= top <= 255.0 and float(top).is_integer():
            return cls(int(top) + 1, 1.0)
        n = int(bins or 256)
        return cls(n, max(top, 1e-12) / (n - 1))

    def index(self, raw: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(np.asarray(raw, dtype=np.float64) / self.step), 0, self.n - 1).astype(np.int64)


@dataclass(frozen=True)
class Observations:
    """Unique (cell, beam, incidence bin, raw bin) combinations and how often each occurred.

    ``cell`` (M,) indexes ``0..n_cells-1``; ``beam``, ``inc``, ``raw_bin`` and ``count`` (M,) are int64.
    ``inc_factor`` (n_inc,) is the expected reflectivity factor of each incidence bin relative to normal incidence
    (1.0 everywhere when incidence is not modelled). ``n_points`` counts the points collected.
    """

    cell: np.ndarray
    beam: np.ndarray
    raw_bin: np.ndarray
    count: np.ndarray
    n_cells: int
    n_beams: int
    binning: RawBinning
    inc: np.ndarray | None = None
    inc_factor: np.ndarray | None = None
    n_points: int = 0
    sensor: str = "unknown"

    @property
    def n_obs(self) -> int:
        return int(self.count.sum())

    @property
    def n_inc(self) -> int:
        return 1 if self.inc_factor is None else int(self.inc_factor.shape[0])

    @property
    def inc_index(self) -> np.ndarray:
        return np.zeros_like(self.cell) if self.inc is None else self.inc


def _cell_keys(xyz_world: np.ndarray, voxel_size: float, where: str) -> np.ndarray:
    ijk = np.floor(np.asarray(xyz_world, dtype=np.float64) / voxel_size).astype(np.int64) + _KEY_OFFSET
    if ijk.size and (ijk.min() < 0 or ijk.max() >= (1 << _KEY_BITS)):
        raise ScanDataError(f"{where}: points too far from the origin for {voxel_size} m map cells")
    return (ijk[:, 0] << (2 * _KEY_BITS)) | (ijk[:, 1] << _KEY_BITS) | ijk[:, 2]


def _keep_multi_beam(
    cell: np.ndarray, beam: np.ndarray, n_cells: int, n_beams: int, min_beams: int
) -> np.ndarray:
    """Per cell: whether at least ``min_beams`` different beams observed it."""
    pairs = np.unique(cell * n_beams + beam)
    return np.bincount(pairs // n_beams, minlength=n_cells) >= min_beams


def group_observations(
    keys: np.ndarray,
    beam: np.ndarray,
    raw_bin: np.ndarray,
    n_beams: int,
    binning: RawBinning,
    min_beams: int = 2,
    inc: np.ndarray | None = None,
    inc_factor: np.ndarray | None = None,
) -> Observations:
    """Group per-point (cell key, beam, [incidence bin], raw bin) into unique combinations with counts; keep the
    cells seen by >= ``min_beams`` beams."""
    keys = np.asarray(keys, dtype=np.int64)
    beam = np.asarray(beam, dtype=np.int64)
    raw_bin = np.asarray(raw_bin, dtype=np.int64)
    n_inc = 1 if inc_factor is None else len(inc_factor)
    inc = np.zeros_like(beam) if inc is None else np.asarray(inc, dtype=np.int64)
    cells, cell = np.unique(keys, return_inverse=True)
    good = _keep_multi_beam(cell, beam, cells.size, n_beams, min_beams)
    sel = good[cell]
    cell = (np.cumsum(good) - 1)[cell[sel]]
    combo = ((cell * n_beams + beam[sel]) * n_inc + inc[sel]) * binning.n + raw_bin[sel]
    uniq, count = np.unique(combo, return_counts=True)
    rest, raw = np.divmod(uniq, binning.n)
    rest, inc_u = np.divmod(rest, n_inc)
    cell_u, beam_u = np.divmod(rest, n_beams)
    return Observations(
        cell=cell_u,
        beam=beam_u,
        raw_bin=raw,
        count=count.astype(np.int64),
        n_cells=int(good.sum()),
        n_beams=int(n_beams),
        binning=binning,
        inc=None if inc_factor is None else inc_u,
        inc_factor=None if inc_factor is None else np.asarray(inc_factor, dtype=np.float64),
        n_points=int(keys.size),
    )


def restrict_observations(obs: Observations, max_bin: int, min_beams: int = 2) -> Observations:
    """Only the combinations with ``raw_bin <= max_bin``, in cells still seen by ``min_beams`` beams."""
    keep = obs.raw_bin <= max_bin
    if keep.all():
        return obs
    cell, beam = obs.cell[keep], obs.beam[keep]
    good = _keep_multi_beam(cell, beam, obs.n_cells, obs.n_beams, min_beams)
    sel = good[cell]
    return replace(
        obs,
        cell=(np.cumsum(good) - 1)[cell[sel]],
        beam=beam[sel],
        raw_bin=obs.raw_bin[keep][sel],
        count=obs.count[keep][sel],
        inc=None if obs.inc is None else obs.inc[keep][sel],
        n_cells=int(good.sum()),
    )


def incidence_cosine(
    xyz: np.ndarray,
    origin: np.ndarray,
    cell_size: float = 0.5,
    min_points: int = 8,
    max_flatness: float = 0.05,
) -> np.ndarray:
    """|cos| of each point's incidence angle on the surface around it (NaN where the surface is not planar).

    ``xyz`` (N, 3) world points, ``origin`` (N, 3) the sensor position that saw each one. The surface normal of a
    point is the least-variance direction of all points in its ``cell_size`` cell of the registered map; cells
    with fewer than ``min_points`` points, or whose smallest eigenvalue exceeds ``max_flatness`` times the
    largest (not planar: foliage, edges), give NaN.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[0] == 0:
        return np.zeros(0)
    _, inv = np.unique(_cell_keys(xyz, cell_size, "calibration"), return_inverse=True)
    m = int(inv.max()) + 1
    n = np.bincount(inv, minlength=m).astype(np.float64)
    mean = np.stack([np.bincount(inv, xyz[:, i], m) for i in range(3)], axis=1) / n[:, None]
    d = xyz - mean[inv]
    cov = np.empty((m, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(inv, d[:, i] * d[:, j], m) / n
    val, vec = np.linalg.eigh(cov)
    normal = vec[:, :, 0]
    planar = (n >= min_points) & (val[:, 0] <= max_flatness * np.maximum(val[:, 2], 1e-12))
    view = xyz - np.asarray(origin, dtype=np.float64)
    cos = np.abs(np.einsum("ij,ij->i", normal[inv], view)) / np.maximum(np.linalg.norm(view, axis=1), 1e-9)
    return np.where(planar[inv], cos, np.nan)


@dataclass(frozen=True)
class RegisteredPoints:
    """The points of registered scans that calibration uses, in the world frame.

    ``xyz`` (N, 3) float32 world coordinates, ``scan`` (N,) int32 index into ``origins`` (S, 3) (the sensor
    position of each scan), ``range`` (N,) float32 sensor range, ``beam`` (N,) int16 ring, ``raw`` (N,) float32
    raw intensity.
    """

    xyz: np.ndarray
    scan: np.ndarray
    origins: np.ndarray
    range: np.ndarray
    beam: np.ndarray
    raw: np.ndarray
    n_beams: int
    intensity_max: float | None
    sensor: str = "unknown"
    name: str = "sequence"

    def __len__(self) -> int:
        return int(self.raw.shape[0])


def gather_points(
    seq: Sequence,
    params: CalibrationParams | None = None,
    on_scan: Callable[[int, int], None] | None = None,
) -> RegisteredPoints:
    """Every ``params.step``-th scan of ``seq`` (at most ``params.max_scans``) moved into the world frame with its
    pose, cropped to the intensity range ``[min_range, max_range]``; needs poses and per-point rings.
    ``on_scan(done, total)`` reports progress."""
    p = params or CalibrationParams()
    min_range, max_range = p.min_range, p.max_range
    poses = seq.poses
    if poses is None:
        raise ScanDataError(f"{seq.name}: intensity calibration needs poses (registered scans)")
    idx = np.arange(0, len(seq), p.step)
    if p.max_scans is not None:
        idx = idx[: p.max_scans]
    if idx.size == 0:
        raise ScanDataError(f"{seq.name}: no scans to calibrate on")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("xyz", "scan", "range", "beam", "raw")}
    origins = np.zeros((idx.size, 3))
    n_beams, intensity_max, sensor = 0, None, "unknown"
    for j, i in enumerate(idx):
        scan: Scan = seq[int(i)]
        where = scan.source or f"{seq.name}[{i}]"
        if scan.ring is None:
            raise ScanDataError(f"{where}: intensity calibration needs per-point ring (beam) indices")
        n_beams = max(n_beams, scan.sensor.n_beams or 0, int(scan.ring.max(initial=-1)) + 1)
        intensity_max = intensity_max or scan.sensor.intensity_max
        sensor = scan.sensor.name
        r = scan.ranges
        keep = np.isfinite(r) & np.isfinite(scan.intensity) & (r >= max(min_range, 1e-6)) & (scan.ring >= 0)
        if max_range is not None:
            keep &= r <= max_range
        T = as_pose(poses[int(i)])
        origins[j] = T[:3, 3]
        parts["xyz"].append((scan.xyz[keep].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
        parts["scan"].append(np.full(int(keep.sum()), j, dtype=np.int32))
        parts["range"].append(r[keep])
        parts["beam"].append(scan.ring[keep])
        parts["raw"].append(scan.intensity[keep])
        if on_scan is not None:
            on_scan(j + 1, idx.size)
    pts = {k: np.concatenate(v) for k, v in parts.items()}
    if pts["raw"].size == 0:
        raise ScanDataError(f"{seq.name}: no points within the intensity range cut-off {max_range} m")
    return RegisteredPoints(origins=origins, n_beams=n_beams, intensity_max=intensity_max, sensor=sensor,
                            name=seq.name, **pts)  # fmt: skip


def observations_from_points(pts: RegisteredPoints, params: CalibrationParams | None = None) -> Observations:
    """Group registered points into map-cell `Observations` (settings: `CalibrationParams`).

    A cell is a ``voxel_size`` voxel of the world map, split by range band (ranges within a factor
    ``range_band``); ``min_cos_incidence`` keeps only points seen within ``arccos(min_cos_incidence)`` of their
    surface normal (`incidence_cosine`), split into ``incidence_bins`` bins whose expected reflectivity factor is
    ``cos ** lambert_exponent`` (None: incidence not modelled). None disables the range band / incidence filter.
    """
    p = params or CalibrationParams()
    voxel_size, min_cos_incidence, range_band = p.voxel_size, p.min_cos_incidence, p.range_band
    incidence_bins, lambert_exponent, min_beams = p.incidence_bins, p.lambert_exponent, p.min_beams
    keep = np.ones(len(pts), dtype=bool)
    inc = inc_factor = None
    if min_cos_incidence is not None:
        cos = incidence_cosine(pts.xyz, pts.origins[pts.scan], p.normal_cell)
        keep = cos >= min_cos_incidence
        log.info("%s: %.1f%% of the points are seen within %.0f deg of their surface normal", pts.name,
                 100.0 * keep.mean(), np.degrees(np.arccos(min_cos_incidence)))  # fmt: skip
        if lambert_exponent is not None and incidence_bins > 1:
            edges = np.linspace(min_cos_incidence, 1.0, incidence_bins + 1)
            inc = np.clip(np.searchsorted(edges, cos[keep], side="right") - 1, 0, incidence_bins - 1)
            centres = 0.5 * (edges[1:] + edges[:-1])
            inc_factor = centres**lambert_exponent
    keys = _cell_keys(pts.xyz[keep], voxel_size, pts.name)
    if range_band is not None:
        band = np.floor(np.log(pts.range[keep]) / np.log(range_band)).astype(np.int64)
        keys = (keys << 6) | np.clip(band - band.min(initial=0), 0, 63)
    binning = RawBinning.for_data(pts.intensity_max, float(pts.raw.max()), p.raw_bins)
    obs = group_observations(
        keys, pts.beam[keep], binning.index(pts.raw[keep]), pts.n_beams, binning, min_beams, inc, inc_factor
    )
    obs = replace(obs, sensor=pts.sensor)
    log.info("%s: %d points -> %d observations in %d cells seen by >= %d beams", pts.name, len(pts), obs.n_obs,
             obs.n_cells, min_beams)  # fmt: skip
    return obs


def collect_observations(seq: Sequence, params: CalibrationParams | None = None) -> Observations:
    """`gather_points` then `observations_from_points`."""
    return observations_from_points(gather_points(seq, params), params)
