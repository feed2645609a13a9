"""Summaries of scans and sequences (what ``placerec info`` prints)."""

from __future__ import annotations

from typing import Any

import numpy as np

from placerec.types import Scan, Sequence

__all__ = ["estimate_beams", "scan_summary", "sequence_summary"]

_PCTS = (1, 5, 25, 50, 75, 95, 99)


def estimate_beams(scan: Scan, bin_deg: float = 0.05, min_share: float = 0.001) -> tuple[int, str]:
    """Number of beams (rows) of a scan and how it was found: ring index, organised shape or elevation peaks.

    Without ring or shape, elevation angles are histogrammed in ``bin_deg`` bins; runs of bins holding at least
    ``min_share`` of the points each count as one beam (works for spinning sensors with distinct elevations).
    """
    if scan.ring is not None and len(scan):
        return int(np.unique(scan.ring).size), "ring index"
    if scan.shape is not None:
        return scan.shape[0], "organised shape"
    xyz = scan.xyz[np.isfinite(scan.xyz).all(axis=1)]
    r = np.linalg.norm(xyz, axis=1)
    xyz, r = xyz[r > 1e-3], r[r > 1e-3]
    if r.size == 0:
        return 0, "no valid points"
    elev = np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))
    lo, hi = float(elev.min()), float(elev.max())
    nbins = max(1, int(np.ceil((hi - lo) / bin_deg)) + 1)
    hist, _ = np.histogram(elev, bins=nbins, range=(lo, lo + nbins * bin_deg))
    occupied = hist >= max(1, min_share * r.size)
    runs = int(np.count_nonzero(occupied[1:] & ~occupied[:-1]) + int(occupied[0]))
    return runs, "elevation histogram (estimate)"


def _percentiles(values: np.ndarray) -> dict[str, float]:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {}
    return {f"p{p}": float(v) for p, v in zip(_PCTS, np.percentile(values, _PCTS), strict=True)}


def scan_summary(scan: Scan) -> dict[str, Any]:
    """Point count, fields, percentiles of intensity and range, beams, organisation and sensor of one scan."""
    finite = np.isfinite(scan.xyz).all(axis=1)
    valid = finite & np.any(scan.xyz != 0, axis=1)
    beams, how = estimate_beams(scan)
    return {
        "source": scan.source,
        "points": len(scan),
        "valid_points": int(valid.sum()),
        "nonfinite_points": int((~finite).sum()),
        "fields": scan.fields,
        "organised_shape": scan.shape,
        "beams": beams,
        "beams_from": how,
        "sensor": scan.sensor.name,
        "intensity_percentiles": _percentiles(scan.intensity[valid]),
        "range_percentiles": _percentiles(scan.ranges[valid]),
    }


def sequence_summary(seq: Sequence) -> dict[str, Any]:
    """Length, poses, timestamps, trajectory length and the first scan's summary of a sequence."""
    poses = seq.poses
    out: dict[str, Any] = {"name": seq.name, "scans": len(seq), "poses": None, "timestamps": None}
    if poses is not None:
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        out["poses"] = {"count": int(len(poses)), "trajectory_length_m": float(steps.sum())}
    ts = seq.timestamps
    if ts is not None and len(ts):
        out["timestamps"] = {"first": float(ts[0]), "last": float(ts[-1]), "count": int(len(ts))}
    if len(seq):
        out["first_scan"] = scan_summary(seq[0])
    return out
