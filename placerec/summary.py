"""Summaries of scans and sequences (what ``placerec info`` prints)."""

from __future__ import annotations

from typing import Any

import numpy as np

from placerec.types import Scan, Sequence

__all__ = ["estimate_beams", "scan_summary", "sequence_summary", "artifact_summary"]

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


def artifact_summary(path: Any, arrays: dict[str, np.ndarray], header: dict[str, Any]) -> dict[str, Any]:
    """A saved artifact (`placerec.io.atomic.peek_artifact`): kind, version, entries, members and, for a database
    with verification clouds, what each entry costs: on disk, in RAM when built (in its ``verify.cloud_store``
    form: ``int16-zlib`` measured by packing up to 32 of its clouds), and how many entries' clouds the default
    ``verify.cloud_budget_mb`` keeps in RAM before spilling (a database loaded memory-mapped keeps its clouds as
    file pages instead)."""
    from pathlib import Path

    from placerec.quantise import PackedCloud
    from placerec.verify.candidates import CLOUDS_SHARE, VerifiedParams

    size = Path(path).stat().st_size
    out: dict[str, Any] = {
        "file": str(path),
        "kind": header["kind"],
        "format_version": header["format_version"],
        "file_mb": round(size / 1e6, 3),
    }
    ids = arrays.get("ids")
    n = int(ids.shape[0]) if ids is not None and ids.ndim == 1 else None
    if n:
        out["entries"] = n
        out["file_kib_per_entry"] = round(size / n / 1024, 2)
    out["members"] = {k: f"{a.dtype} {tuple(a.shape)}" for k, a in sorted(arrays.items())}
    counts, xyz = arrays.get("cloud_counts"), arrays.get("cloud_xyz")
    if counts is None or xyz is None or counts.ndim != 1 or not counts.size or int(counts.sum()) != len(xyz):
        return out
    verify = ((header.get("meta") or {}).get("params") or {}).get("verify") or {}
    form = verify.get("cloud_store", "int16-zlib")
    pts = float(counts.mean())
    ends = np.cumsum(counts)
    sample = np.unique(np.linspace(0, counts.size - 1, min(32, counts.size)).astype(int))
    packed = [
        PackedCloud.encode(np.asarray(xyz[ends[i] - counts[i] : ends[i]], np.float32), level=2).nbytes
        for i in sample
        if counts[i]
    ]
    per_entry = {
        "float32": 12 * pts,
        "int16": 6 * pts + 32,
        "int16-zlib": float(np.mean(packed)) if packed else 0.0,
    }
    ram = per_entry.get(form, per_entry["float32"])
    budget = VerifiedParams().cloud_budget_mb
    out["clouds"] = {
        "points_per_entry": round(pts, 1),
        "file_kib_per_entry": round(12 * pts / 1024, 2),
        "cloud_store": form,
        "ram_kib_per_entry_built": round(ram / 1024, 2),
        "default_cloud_budget_mb": budget,
        "entries_in_ram_within_budget": int(budget * 1e6 * CLOUDS_SHARE // ram) if budget and ram else None,
        "when_loaded": "memory-mapped: the clouds stay file pages, read when a candidate reaches ICP",
    }
    return out
