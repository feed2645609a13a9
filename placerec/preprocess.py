"""Scan preprocessing: invalid-point removal, range/height crops, voxel downsampling, intensity normalisation.

All functions are vectorised, return new `Scan` objects and never modify their input.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from placerec.config import PreprocessConfig
from placerec.errors import ConfigError, ScanDataError
from placerec.types import Scan

log = logging.getLogger(__name__)

__all__ = [
    "remove_invalid",
    "crop",
    "voxel_downsample",
    "normalize_intensity",
    "INTENSITY_NORMALIZERS",
    "SENSOR_INTENSITY_DEFAULTS",
    "IntensitySpec",
    "default_intensity_spec",
    "preprocess_scan",
]


def _keep(scan: Scan, keep: np.ndarray, keep_organized: bool) -> Scan:
    """Select ``keep``; an organised scan with ``keep_organized`` keeps its grid and zeroes the dropped points."""
    if keep_organized and scan.shape is not None:
        if keep.all():
            return scan
        xyz = np.where(keep[:, None], scan.xyz, np.float32(0.0))
        return replace(scan, xyz=xyz, intensity=np.where(keep, scan.intensity, np.float32(0.0)))
    if keep.all() and scan.shape is None:
        return scan
    return scan.select(keep)


def remove_invalid(scan: Scan, keep_organized: bool = False) -> tuple[Scan, dict[str, int]]:
    """Drop points with NaN/inf coordinates or intensity and points at the origin (no return).

    Returns the cleaned scan and counts ``{"nonfinite": ..., "zero": ...}``. Organised scans become unorganised
    unless ``keep_organized``, which zeroes invalid points in place (the organised convention for no return).
    """
    finite = np.isfinite(scan.xyz).all(axis=1) & np.isfinite(scan.intensity)
    zero = finite & ~np.any(scan.xyz != 0.0, axis=1)
    keep = finite & ~zero
    counts = {"nonfinite": int((~finite).sum()), "zero": int(zero.sum())}
    if counts["nonfinite"] or counts["zero"]:
        log.debug(
            "%s: removed %d non-finite and %d zero points",
            scan.source or "scan",
            counts["nonfinite"],
            counts["zero"],
        )
    return _keep(scan, keep, keep_organized), counts


def crop(
    scan: Scan,
    min_range: float | None = None,
    max_range: float | None = None,
    min_z: float | None = None,
    max_z: float | None = None,
    keep_organized: bool = False,
) -> Scan:
    """Keep points with ``min_range <= |p| <= max_range`` and ``min_z <= z <= max_z`` (None = unbounded)."""
    keep = np.ones(len(scan), dtype=bool)
    if min_range is not None or max_range is not None:
        r = scan.ranges
        if min_range is not None:
            keep &= r >= min_range
        if max_range is not None:
            keep &= r <= max_range
    z = scan.xyz[:, 2]
    if min_z is not None:
        keep &= z >= min_z
    if max_z is not None:
        keep &= z <= max_z
    return _keep(scan, keep, keep_organized)


def voxel_downsample(scan: Scan, voxel_size: float) -> Scan:
    """One point per occupied voxel: the centroid of its points, with their mean intensity.

    The ring (and time) of the voxel is that of the point nearest to the centroid, so the result still tells
    which beam saw the surface. Voxels are aligned to the origin of the scan frame.
    """
    if voxel_size <= 0:
        raise ScanDataError(f"voxel_size must be positive, got {voxel_size}")
    n = len(scan)
    if n == 0:
        return scan.select(np.zeros(0, dtype=bool))
    if not np.isfinite(scan.xyz).all():
        raise ScanDataError(
            f"{scan.source or 'scan'}: voxel_downsample needs finite points; call remove_invalid first"
        )
    cells = np.floor(scan.xyz * np.float32(1.0 / voxel_size)).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    counts = np.diff(np.r_[starts, n]).astype(np.float64)
    xyz_sorted = scan.xyz[order].astype(np.float64)
    centroids = np.add.reduceat(xyz_sorted, starts, axis=0) / counts[:, None]
    intensity = np.add.reduceat(scan.intensity[order].astype(np.float64), starts) / counts
    ring = time = None
    if scan.ring is not None or scan.time is not None:
        group = np.repeat(np.arange(starts.size), counts.astype(np.int64))
        diff = xyz_sorted - centroids[group]
        d2 = np.einsum("ij,ij->i", diff, diff)
        # nearest point of each voxel: the first point whose distance equals its voxel's minimum
        ties = np.flatnonzero(d2 <= np.minimum.reduceat(d2, starts)[group])
        first = ties[np.r_[True, group[ties[1:]] != group[ties[:-1]]]]
        rep = order[first]
        ring = None if scan.ring is None else scan.ring[rep]
        time = None if scan.time is None else scan.time[rep]
    return replace(
        scan,
        xyz=centroids.astype(np.float32),
        intensity=intensity.astype(np.float32),
        ring=ring,
        time=time,
        shape=None,
    )


# --- intensity normalisation -------------------------------------------------------------------------------


@dataclass(frozen=True)
class IntensitySpec:
    """How to map raw intensity to [0, 1]: ``mode`` is a key of `INTENSITY_NORMALIZERS`.

    ``saturation``: raw value mapped to 1 by ``linear`` (values above are clipped); ``percentile``: the
    percentile of the scan's own intensities mapped to 1 by ``percentile``.
    """

    mode: str = "raw"
    saturation: float | None = None
    percentile: float = 99.0


def _raw(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    return values


def _linear(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    if spec.saturation is None or spec.saturation <= 0:
        raise ConfigError("intensity mode 'linear' needs a positive 'saturation' value")
    return np.clip(values / np.float32(spec.saturation), 0.0, 1.0).astype(np.float32)


def _percentile(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    if not 0 < spec.percentile <= 100:
        raise ConfigError(f"intensity 'percentile' must be in (0, 100], got {spec.percentile}")
    if values.size == 0:
        return values
    top = float(np.percentile(values, spec.percentile))
    if top <= 0:
        return np.zeros_like(values)
    return np.clip(values / np.float32(top), 0.0, 1.0).astype(np.float32)


INTENSITY_NORMALIZERS: dict[str, Callable[[np.ndarray, IntensitySpec], np.ndarray]] = {
    "raw": _raw,
    "linear": _linear,
    "percentile": _percentile,
}

#: Defaults per sensor name (prefix match on `SensorInfo.name`). VLP-16: the ISHOT paper maps raw >= 100 to 1.
#: KITTI's HDL-64 reflectance is already in [0, 1]. Ouster 16-bit reflectivity and 8-bit Velodyne HDL sensors
#: are scaled by a high percentile of each scan, which is robust to retro-reflector outliers.
SENSOR_INTENSITY_DEFAULTS: dict[str, IntensitySpec] = {
    "vlp16": IntensitySpec("linear", saturation=100.0),
    "hdl64": IntensitySpec("percentile", percentile=99.0),
    "hdl32": IntensitySpec("percentile", percentile=99.0),
    "kitti": IntensitySpec("linear", saturation=1.0),
    "os": IntensitySpec("percentile", percentile=99.0),
}


def default_intensity_spec(sensor_name: str) -> IntensitySpec:
    """The per-sensor default (`SENSOR_INTENSITY_DEFAULTS`), ``percentile`` 99 for unknown sensors."""
    name = sensor_name.lower()
    for prefix, spec in SENSOR_INTENSITY_DEFAULTS.items():
        if name.startswith(prefix):
            return spec
    return IntensitySpec("percentile", percentile=99.0)


def normalize_intensity(scan: Scan, spec: IntensitySpec | None = None) -> Scan:
    """Map the scan's intensity to [0, 1] with ``spec`` (default: the sensor's default spec)."""
    spec = spec or default_intensity_spec(scan.sensor.name)
    try:
        fn = INTENSITY_NORMALIZERS[spec.mode]
    except KeyError:
        raise ConfigError(
            f"unknown intensity mode {spec.mode!r}; allowed: {sorted(INTENSITY_NORMALIZERS)}"
        ) from None
    return scan.with_intensity(fn(scan.intensity, spec))


def preprocess_scan(scan: Scan, cfg: PreprocessConfig, keep_organized: bool = False) -> Scan:
    """Apply a `PreprocessConfig`: remove invalid points, crop, normalise (or calibrate) intensity, voxelise.

    With ``keep_organized`` an organised scan keeps its grid (dropped points zeroed) and is not voxelised, which
    is what image-based pipelines need.
    """
    scan, _ = remove_invalid(scan, keep_organized)
    scan = crop(scan, cfg.min_range, cfg.max_range, cfg.min_z, cfg.max_z, keep_organized)
    ic = cfg.intensity
    if ic.calibration:
        # per-beam calibration table: output already in [0, 1]; NaN (beyond its range cut-off) -> dropped
        from placerec.calibration import load_calibration

        scan = load_calibration(ic.calibration).apply(scan)
        scan = _keep(scan, np.isfinite(scan.intensity), keep_organized)
    else:
        spec = (
            default_intensity_spec(scan.sensor.name)
            if ic.mode == "auto"
            else IntensitySpec(ic.mode, saturation=ic.saturation, percentile=ic.percentile)
        )
        scan = normalize_intensity(scan, spec)
    if cfg.voxel_size and not (keep_organized and scan.shape is not None):
        scan = voxel_downsample(scan, cfg.voxel_size)
    return scan
