"""NCLT ``velodyne_sync`` scans (Velodyne HDL-32E).

Each point is 8 bytes, little-endian: uint16 x, y, z (metres = value * 0.005 - 100), uint8 intensity, uint8 laser
id. The laser id becomes ``ring``; ``SensorInfo.beam_elevations_deg`` lists the HDL-32E elevations indexed by
laser id (the lasers are interleaved: even ids go up from -30.67 deg, odd ids from -9.33 deg).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io._common import check_file, guard
from placerec.types import Scan, SensorInfo

__all__ = ["read_nclt_bin", "NCLT_RECORD_SIZE", "HDL32E_ELEVATIONS_DEG"]

NCLT_RECORD_SIZE = 8
NCLT_SCALE = 0.005
NCLT_OFFSET = -100.0
_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])


def _hdl32e_elevations() -> tuple[float, ...]:
    ids = np.arange(32)
    base = np.where(ids % 2 == 0, -30.67, -9.33)
    return tuple(float(v) for v in np.round(base + (ids // 2) * 4.0 / 3.0, 2))


HDL32E_ELEVATIONS_DEG = _hdl32e_elevations()
NCLT_SENSOR = SensorInfo(
    name="velodyne-hdl32e (nclt)",
    beam_elevations_deg=HDL32E_ELEVATIONS_DEG,
    columns=None,
    intensity_max=255.0,
)


@guard("NCLT velodyne_sync .bin")
def read_nclt_bin(path: str | Path, *, organized: bool = False) -> Scan:
    """Read an NCLT ``velodyne_sync`` scan; ``ring`` is the laser id (0..31). Always unorganised."""
    p = check_file(path, "NCLT velodyne_sync .bin")
    size = p.stat().st_size
    if size % NCLT_RECORD_SIZE:
        raise ScanFormatError(
            f"{p}: size {size} bytes is not a multiple of the NCLT record size {NCLT_RECORD_SIZE} "
            "(uint16 x, y, z, uint8 intensity, uint8 laser id)"
        )
    raw = np.fromfile(p, dtype=_DTYPE)
    if raw["l"].max() >= 32:
        raise ScanFormatError(
            f"{p}: laser id {int(raw['l'].max())} out of range 0..31; not an NCLT HDL-32E velodyne_sync file?"
        )
    xyz = np.empty((raw.shape[0], 3), dtype=np.float32)
    for j, c in enumerate("xyz"):
        xyz[:, j] = raw[c] * np.float32(NCLT_SCALE) + np.float32(NCLT_OFFSET)
    return Scan(xyz=xyz, intensity=raw["i"], ring=raw["l"], sensor=NCLT_SENSOR, source=str(p))
