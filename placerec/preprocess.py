"""Scan preprocessing: invalid-point removal, range/height/elevation crops, voxel downsampling, then
`preprocess_scan` with intensity normalisation (`placerec.intensity`) or a per-beam calibration table
(`placerec.calibration`).

All functions are vectorised, return new `Scan` objects and never modify their input.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from pydantic import Field, SerializerFunctionWrapHandler, model_serializer, model_validator

from placerec.errors import ScanDataError
from placerec.intensity import IntensitySpec, normalize_intensity
from placerec.params import Params
from placerec.types import Scan, valid_points

log = logging.getLogger(__name__)

__all__ = ["remove_invalid", "crop", "voxel_downsample", "PreprocessParams", "preprocess_scan"]


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
    """Keep the valid points (`placerec.types.valid_points`, finite intensity included): drop points with NaN/inf
    coordinates or intensity and those with no return (at the origin, or at a fill-value range).

    Returns the cleaned scan and counts ``{"nonfinite": ..., "no_return": ...}``. Organised scans become
    unorganised unless ``keep_organized``, which zeroes invalid points in place (the organised convention for no
    return).
    """
    keep = valid_points(scan, intensity=True)
    return _keep(scan, keep, keep_organized), _invalid_counts(scan, keep)


def _invalid_counts(scan: Scan, valid: np.ndarray) -> dict[str, int]:
    """How many of the points outside ``valid`` are not finite and how many have no return (logged at debug)."""
    # a point that is not finite has no finite range, so it is among the invalid ones: only those are checked
    dropped = np.flatnonzero(~valid)
    finite = np.isfinite(scan.xyz[dropped]).all(axis=1) & np.isfinite(scan.intensity[dropped])
    counts = {"nonfinite": int((~finite).sum()), "no_return": int(finite.sum())}
    if dropped.size:
        log.debug(
            "%s: removed %d non-finite points and %d without a return",
            scan.source or "scan",
            counts["nonfinite"],
            counts["no_return"],
        )
    return counts


def crop(
    scan: Scan,
    min_range: float | None = None,
    max_range: float | None = None,
    min_z: float | None = None,
    max_z: float | None = None,
    keep_organized: bool = False,
    elevation_deg: Sequence[float] | None = None,
) -> Scan:
    """Keep points with ``min_range <= |p| <= max_range``, ``min_z <= z <= max_z`` and an elevation angle (degrees
    above the sensor's horizontal plane) within ``elevation_deg`` = (lowest, highest) (None = unbounded)."""
    r = scan.ranges if min_range is not None or max_range is not None else None
    keep = _crop_mask(scan, r, min_range, max_range, min_z, max_z, elevation_deg)
    return _keep(scan, keep, keep_organized)


def _crop_mask(
    scan: Scan,
    ranges: np.ndarray | None,
    min_range: float | None,
    max_range: float | None,
    min_z: float | None,
    max_z: float | None,
    elevation_deg: Sequence[float] | None = None,
) -> np.ndarray:
    """`crop`'s mask, from the scan's ``ranges`` (needed only with a range bound)."""
    keep = np.ones(len(scan), dtype=bool)
    if ranges is not None:
        if min_range is not None:
            keep &= ranges >= min_range
        if max_range is not None:
            keep &= ranges <= max_range
    z = scan.xyz[:, 2]
    if min_z is not None:
        keep &= z >= min_z
    if max_z is not None:
        keep &= z <= max_z
    if elevation_deg is not None:
        # tan is increasing on (-90, 90) deg: z / horizontal distance against the bounds' tangents, no arctan
        lo, hi = np.tan(np.radians(np.asarray(elevation_deg, dtype=np.float64)))
        xy = np.hypot(scan.xyz[:, 0], scan.xyz[:, 1]).astype(np.float64)
        zz = z.astype(np.float64)
        keep &= (zz >= lo * xy) & (zz <= hi * xy)
    return keep


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


class IntensityParams(IntensitySpec):
    """Intensity normalisation: a `placerec.intensity.IntensitySpec` whose ``mode`` may also be ``auto`` (the
    sensor's default, `placerec.intensity.default_intensity_spec`).

    ``calibration``: path of a per-beam calibration table (``placerec calibrate``); when set, each point's raw
    intensity is mapped through its beam's table (already in [0, 1], so ``mode`` is not applied) and points beyond
    the table's intensity range cut-off (30 m) are dropped (zeroed in organised scans).
    """

    mode: Literal["auto", "raw", "linear", "percentile"] = Field(  # type: ignore[assignment]
        "auto", description="auto (the sensor's default), raw, linear or percentile"
    )
    calibration: str | None = Field(None, description="per-beam calibration table file")

    def spec(self) -> IntensitySpec | None:
        """The normalisation to apply (None: the sensor's default)."""
        if self.mode == "auto":
            return None
        return IntensitySpec(**self.model_dump(include=set(IntensitySpec.model_fields)))


class PreprocessParams(Params):
    """What `preprocess_scan` does (None = no limit / not applied): points kept within ``[min_range, max_range]``,
    ``[min_z, max_z]`` and the elevation band ``elevation_deg``, intensity normalised or calibrated
    (``intensity``), voxel downsampling (``voxel_size``). An experiment config's ``preprocess`` section is one of
    these."""

    min_range: float | None = Field(None, ge=0, description="m; nearer points are dropped")
    max_range: float | None = Field(None, gt=0, description="m; farther points are dropped")
    min_z: float | None = Field(None, description="m; lower points are dropped")
    max_z: float | None = Field(None, description="m; higher points are dropped")
    elevation_deg: list[float] | None = Field(
        None,
        min_length=2,
        max_length=2,
        description="deg; (lowest, highest) elevation above the sensor's horizontal plane kept, e.g. the vertical "
        "field of view two sensors share, so that a map from one and queries from the other hold the same part of "
        "the scene (None = all)",
    )
    voxel_size: float | None = Field(None, gt=0, description="m; voxel downsampling (None = off)")
    intensity: IntensityParams = Field(default_factory=IntensityParams)

    @model_validator(mode="after")
    def _ranges_not_empty(self) -> PreprocessParams:
        for lo, hi in (("min_range", "max_range"), ("min_z", "max_z")):
            a, b = getattr(self, lo), getattr(self, hi)
            if a is not None and b is not None and a >= b:
                raise ValueError(f"{lo} ({a}) must be below {hi} ({b}): every point would be dropped")
        if self.elevation_deg is not None:
            a, b = self.elevation_deg
            if not -90.0 < a < b < 90.0:
                raise ValueError(
                    f"elevation_deg ({a}, {b}): the lowest must be below the highest, both within (-90, 90)"
                )
        return self

    @model_serializer(mode="wrap")
    def _dump(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """The fields, without ``elevation_deg`` when it is None: the dump of a run without the band (description
        cache keys, saved databases and maps, benchmark cells) stays what it was before the band existed."""
        data: dict[str, Any] = handler(self)
        if self.elevation_deg is None:
            data.pop("elevation_deg", None)
        return data


def preprocess_scan(scan: Scan, params: PreprocessParams | None = None, keep_organized: bool = False) -> Scan:
    """Remove invalid points, crop, normalise (or calibrate) intensity and voxelise, as ``params`` says.

    With ``keep_organized`` an organised scan keeps its grid (dropped points zeroed) and is not voxelised, which
    is what image-based pipelines need.
    """
    p = params or PreprocessParams()
    # `remove_invalid` then `crop` as one selection: the ranges computed once, the points copied once (a point's
    # range does not depend on the other points; a dropped point stays dropped, zeroed in an organised scan)
    r = scan.ranges
    keep = valid_points(scan, intensity=True, ranges=r)
    if log.isEnabledFor(logging.DEBUG):  # the counts are only logged here
        _invalid_counts(scan, keep)
    keep &= _crop_mask(scan, r, p.min_range, p.max_range, p.min_z, p.max_z, p.elevation_deg)
    scan = _keep(scan, keep, keep_organized)
    if p.intensity.calibration:
        # per-beam calibration table: output already in [0, 1]; NaN (beyond its range cut-off) -> dropped
        from placerec.calibration.table import load_calibration

        scan = load_calibration(p.intensity.calibration).apply(scan)
        scan = _keep(scan, np.isfinite(scan.intensity), keep_organized)
    else:
        scan = normalize_intensity(scan, p.intensity.spec())
    if p.voxel_size and not (keep_organized and scan.shape is not None):
        scan = voxel_downsample(scan, p.voxel_size)
    return scan
