"""KITTI Velodyne ``.bin`` scans: records of four little-endian float32 (x, y, z, reflectance), 16 bytes each.

The same record layout is used by other datasets for *organised* scans (e.g. the MulRan-style Ouster OS1-64
files: 64 x 1024 points stored column-major). Pass ``layout=(rows, cols, order)`` to recover the image
structure; ``order`` says how the file walks the image: ``"row-major"`` (one row after the other) or
``"column-major"`` (each block of ``rows`` consecutive points is one column, top row first).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placerec.errors import ConfigError, ScanFormatError
from placerec.io._common import check_file, guard
from placerec.io.atomic import atomic_write
from placerec.types import Scan, SensorInfo

__all__ = ["read_kitti_bin", "write_kitti_bin", "KITTI_RECORD_SIZE", "Layout", "parse_layout"]

KITTI_RECORD_SIZE = 16
KITTI_SENSOR = SensorInfo(name="velodyne-hdl64e (kitti)", intensity_max=1.0)
_ORDERS = ("row-major", "column-major")
_CHUNK = 4096  # records per read: 64 KiB, small enough to be recycled by the allocator

Layout = tuple[int, int, str]


def parse_layout(layout: tuple[int, int] | tuple[int, int, str] | None) -> Layout | None:
    """Validate ``(rows, cols[, order])``; order defaults to ``"row-major"``."""
    if layout is None:
        return None
    if not isinstance(layout, (tuple, list)) or len(layout) not in (2, 3):
        raise ConfigError(f"layout must be (rows, cols) or (rows, cols, order), got {layout!r}")
    rows, cols = int(layout[0]), int(layout[1])
    order = str(layout[2]) if len(layout) == 3 else "row-major"
    if rows <= 0 or cols <= 0:
        raise ConfigError(f"layout rows and cols must be positive, got {rows} x {cols}")
    if order not in _ORDERS:
        raise ConfigError(f"layout order must be one of {list(_ORDERS)}, got {order!r}")
    return rows, cols, order


def organise(
    xyz: np.ndarray, values: dict[str, np.ndarray], layout: Layout, where: str | Path
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Reorder per-point arrays of a scan stored in ``layout`` into row-major order; also returns ring = row."""
    rows, cols, order = layout
    n = xyz.shape[0]
    if n != rows * cols:
        raise ScanFormatError(
            f"{where}: {n} points cannot be an organised {rows} x {cols} scan (expected {rows * cols} points)"
        )
    if order == "column-major":
        xyz = xyz.reshape(cols, rows, 3).transpose(1, 0, 2).reshape(n, 3)
        values = {k: v.reshape(cols, rows).T.reshape(n) for k, v in values.items()}
    ring = np.repeat(np.arange(rows, dtype=np.int16), cols)
    return np.ascontiguousarray(xyz), values, ring


def _read_records(path: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Stream the float32 records through a small reused buffer straight into contiguous xyz and intensity.

    As fast as ``np.fromfile`` plus the two copies a `Scan` needs anyway, without a third large temporary
    (large short-lived allocations cost more in page faults than the copies themselves).
    """
    xyz = np.empty((n, 3), dtype=np.float32)
    intensity = np.empty(n, dtype=np.float32)
    buf = np.empty((min(n, _CHUNK), 4), dtype="<f4")
    with open(path, "rb") as fh:
        for k in range(0, n, _CHUNK):
            view = buf[: min(_CHUNK, n - k)]
            got = fh.readinto(view.data.cast("B"))
            if got != view.nbytes:
                raise ScanFormatError(f"{path}: file shrank while reading ({got} of {view.nbytes} bytes)")
            xyz[k : k + len(view)] = view[:, :3]
            intensity[k : k + len(view)] = view[:, 3]
    return xyz, intensity


@guard("KITTI .bin")
def read_kitti_bin(
    path: str | Path,
    *,
    organized: bool = False,
    layout: tuple[int, int] | tuple[int, int, str] | None = None,
) -> Scan:
    """Read a KITTI ``.bin`` scan (x, y, z, reflectance float32).

    Without ``layout`` the scan is unorganised (``organized`` has no effect: the file carries no image
    structure). With ``layout=(rows, cols, order)`` every point gets ``ring`` = its row, and with
    ``organized=True`` the scan is returned row-major with ``shape=(rows, cols)``; zero points stay zeros.
    """
    lay = parse_layout(layout)
    p = check_file(path, "KITTI .bin")
    size = p.stat().st_size
    if size % KITTI_RECORD_SIZE:
        raise ScanFormatError(
            f"{p}: size {size} bytes is not a multiple of the KITTI record size {KITTI_RECORD_SIZE} "
            "(4 x float32: x, y, z, reflectance)"
        )
    xyz, intensity = _read_records(p, size // KITTI_RECORD_SIZE)
    if lay is None:
        return Scan(xyz=xyz, intensity=intensity, sensor=KITTI_SENSOR, source=str(p))
    xyz, vals, ring = organise(xyz, {"i": intensity}, lay, p)
    rows, cols, _ = lay
    sensor = SensorInfo(name="organised-bin", columns=cols)
    return Scan(
        xyz=xyz,
        intensity=vals["i"],
        ring=ring,
        shape=(rows, cols) if organized else None,
        sensor=sensor,
        source=str(p),
    )


def write_kitti_bin(path: str | Path, scan: Scan) -> None:
    """Write x, y, z, intensity as KITTI float32 records (atomic). Ring, time and organisation are not kept."""
    out = np.empty((len(scan), 4), dtype="<f4")
    out[:, :3] = scan.xyz
    out[:, 3] = scan.intensity
    with atomic_write(path) as fh:
        fh.write(out.tobytes())
