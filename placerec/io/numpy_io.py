"""Scans stored as numpy ``.npy`` / ``.npz`` files.

``.npy``: an (N, 3) or (N, 4) array (x, y, z[, intensity]); an (H, W, 3|4) array (organised when
``organized=True``); or a structured array with named fields (x, y, z, intensity/reflectivity/i, ring, t/time).

``.npz``: keys ``xyz`` (N, 3), optional ``intensity`` (N,), ``ring`` (N,), ``time`` (N,), ``shape`` (2,) for an
organised scan, ``timestamp`` (scalar) and ``sensor`` (UTF-8 JSON of `SensorInfo.to_dict`, as uint8).

Arrays are decoded by `placerec.io.npz`: headers and zip member sizes are checked against the data and the load
cap (`placerec.io.limits`) before anything is decompressed, so a truncated, lying or zip-bomb file gives
ScanFormatError instead of a huge allocation; pickled (object) arrays are refused.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io._common import columns_to_scan, guard, read_bytes, structured_columns
from placerec.io.atomic import atomic_write
from placerec.io.npz import parse_npy, read_npz_arrays
from placerec.types import Scan, SensorInfo

__all__ = ["read_npy", "read_npz", "write_npz"]

_NPZ_KEYS = ("xyz", "intensity", "ring", "time", "shape", "timestamp", "sensor")


@guard(".npy")
def read_npy(path: str | Path, *, organized: bool = False) -> Scan:
    """Read a scan from a ``.npy`` array (see the module docstring for the accepted shapes)."""
    p, buf = read_bytes(path, ".npy")
    arr = parse_npy(buf, p, ScanFormatError)
    if arr.dtype.names:
        if arr.ndim not in (1, 2):
            raise ScanFormatError(
                f"{p}: structured .npy must be 1-D or 2-D (organised), got shape {arr.shape}"
            )
        shape = (int(arr.shape[0]), int(arr.shape[1])) if arr.ndim == 2 and organized else None
        return columns_to_scan(structured_columns(arr), p, shape=shape)
    if arr.dtype.kind not in "fiu":
        raise ScanFormatError(f"{p}: .npy array of {arr.dtype} cannot be a scan (expected numbers)")
    shape = None
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        shape = (int(arr.shape[0]), int(arr.shape[1])) if organized else None
        arr = arr.reshape(-1, arr.shape[2])
    if arr.ndim != 2 or arr.shape[1] not in (3, 4):
        raise ScanFormatError(
            f"{p}: .npy array has shape {arr.shape}; expected (N, 3), (N, 4), (H, W, 3|4) "
            "or a structured array with x, y, z fields"
        )
    intensity = arr[:, 3] if arr.shape[1] == 4 else np.zeros(arr.shape[0], np.float32)
    cols = {"x": arr[:, 0], "y": arr[:, 1], "z": arr[:, 2], "intensity": intensity}
    return columns_to_scan(cols, p, shape=shape)


@guard(".npz")
def read_npz(path: str | Path, *, organized: bool = False) -> Scan:
    """Read a scan from an ``.npz`` archive with keys xyz, intensity, ring, time, shape, timestamp, sensor."""
    p, buf = read_bytes(path, ".npz")
    arrays = read_npz_arrays(buf, p, ScanFormatError, "scan", keys=_NPZ_KEYS)
    if "xyz" not in arrays:
        raise ScanFormatError(
            f"{p}: .npz has no 'xyz' array (keys found: {sorted(arrays)}; expected {_NPZ_KEYS})"
        )
    xyz = arrays["xyz"]
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype.kind not in "fiu":
        raise ScanFormatError(f"{p}: .npz 'xyz' must be an (N, 3) numeric array, got {xyz.shape} {xyz.dtype}")
    n = xyz.shape[0]
    cols: dict[str, np.ndarray] = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    for key in ("intensity", "ring", "time"):
        if key in arrays:
            a = arrays[key]
            if a.dtype.kind not in "fiu" or a.size != n:
                raise ScanFormatError(f"{p}: .npz {key!r} must hold {n} numbers, got {a.shape} {a.dtype}")
            cols[key] = a.reshape(-1) if key != "time" else a.reshape(-1).astype(np.float32)
    shape = None
    if "shape" in arrays and organized:
        s = arrays["shape"].reshape(-1)
        if s.size != 2 or s.dtype.kind not in "iu" or (s < 1).any() or int(s[0]) * int(s[1]) != n:
            raise ScanFormatError(f"{p}: .npz 'shape' {s.tolist()} is not (rows, cols) of the {n} points")
        shape = (int(s[0]), int(s[1]))
    sensor = None
    if "sensor" in arrays:
        try:
            sensor = SensorInfo.from_dict(json.loads(arrays["sensor"].tobytes().decode("utf-8")))
        except (ValueError, AttributeError, TypeError) as exc:
            raise ScanFormatError(f"{p}: .npz 'sensor' is not a valid sensor description ({exc})") from None
    ts = None
    if "timestamp" in arrays:
        t = arrays["timestamp"].reshape(-1)
        if t.size != 1 or t.dtype.kind not in "fiu":
            raise ScanFormatError(f"{p}: .npz 'timestamp' must be one number")
        ts = float(t[0])
    return columns_to_scan(cols, p, shape=shape, sensor=sensor, timestamp=ts)


def write_npz(path: str | Path, scan: Scan) -> None:
    """Write every field of ``scan`` (and its sensor and timestamp) into an uncompressed ``.npz``; atomic."""
    arrays: dict[str, Any] = {"xyz": scan.xyz, "intensity": scan.intensity}
    if scan.ring is not None:
        arrays["ring"] = scan.ring
    if scan.time is not None:
        arrays["time"] = scan.time
    if scan.shape is not None:
        arrays["shape"] = np.asarray(scan.shape, dtype=np.int64)
    if scan.timestamp is not None:
        arrays["timestamp"] = np.asarray(scan.timestamp, dtype=np.float64)
    arrays["sensor"] = np.frombuffer(json.dumps(scan.sensor.to_dict()).encode("utf-8"), dtype=np.uint8)
    bio = io.BytesIO()
    np.savez(bio, **arrays)
    with atomic_write(path) as fh:
        fh.write(bio.getbuffer())
