"""Telling the two ``.bin`` scan formats apart: KITTI (4 x float32, 16 bytes a point) and NCLT ``velodyne_sync``
(3 x uint16 + 2 x uint8, 8 bytes a point).

An NCLT file is often also a whole number of 16-byte records, and read as KITTI it gives half the points at
ranges of 1e11 m. `sniff_bin_format` therefore looks at the first records as KITTI floats: a LiDAR measures no
point 10 km away, so when more than a tenth of the finite points lie beyond that the file is not KITTI. It is
NCLT when its size is a whole number of 8-byte records and every laser id (the 8th byte) is below 32.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io.kitti import KITTI_RECORD_SIZE
from placerec.io.nclt import NCLT_RECORD_SIZE

__all__ = ["sniff_bin_format", "KITTI_MAX_PLAUSIBLE_M", "SNIFF_BYTES"]

log = logging.getLogger(__name__)

#: farther than any LiDAR measures: a KITTI-read coordinate beyond this means the bytes are not float32 points
KITTI_MAX_PLAUSIBLE_M = 1.0e4
#: fraction of implausible points above which a file is not KITTI
_MAX_IMPLAUSIBLE = 0.1
#: bytes looked at (1024 KITTI records, 2048 NCLT records)
SNIFF_BYTES = 16 * 1024


def _kitti_implausible_fraction(head: bytes) -> float:
    """Fraction of the finite KITTI-read points in ``head`` with a coordinate beyond `KITTI_MAX_PLAUSIBLE_M`."""
    n = len(head) // KITTI_RECORD_SIZE
    rec = np.frombuffer(head, "<f4", count=4 * n).reshape(n, 4)
    finite = np.isfinite(rec[:, :3]).all(axis=1)
    if not finite.any():
        return 0.0  # nothing to judge by: leave it to the KITTI reader
    far = (np.abs(rec[finite, :3]) > KITTI_MAX_PLAUSIBLE_M).any(axis=1)
    return float(far.mean())


def _nclt_plausible(head: bytes, size: int) -> bool:
    if size % NCLT_RECORD_SIZE:
        return False
    n = len(head) // NCLT_RECORD_SIZE
    laser = np.frombuffer(head, np.uint8, count=n * NCLT_RECORD_SIZE)[
        NCLT_RECORD_SIZE - 1 :: NCLT_RECORD_SIZE
    ]
    return bool(laser.size) and int(laser.max()) < 32


def sniff_bin_format(path: Path) -> str:
    """``"kitti"`` or ``"nclt"`` for a ``.bin`` scan file read without a format (see the module docstring).

    A file that is neither plausible KITTI nor plausible NCLT is a `ScanFormatError` that names both
    ``format=`` values; a file that cannot be read, or is too short to judge, is left to the KITTI reader.
    """
    if not path.is_file():  # a FIFO or device would block the read: the reader refuses it with a clear error
        return "kitti"
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(SNIFF_BYTES)
    except OSError:
        return "kitti"
    kitti_sized = size % KITTI_RECORD_SIZE == 0
    head = head[: len(head) - len(head) % KITTI_RECORD_SIZE]
    if kitti_sized and len(head) >= KITTI_RECORD_SIZE:
        far = _kitti_implausible_fraction(head)
        if far <= _MAX_IMPLAUSIBLE:
            return "kitti"
        why = f"read as KITTI float32 records, {far:.0%} of its first points lie beyond {KITTI_MAX_PLAUSIBLE_M:g} m"
    elif kitti_sized:
        return "kitti"
    else:
        why = f"size {size} bytes is not a multiple of the KITTI record size {KITTI_RECORD_SIZE}"
    if _nclt_plausible(head, size):
        log.info("%s: %s; reading it as an NCLT velodyne_sync scan (format='nclt')", path, why)
        return "nclt"
    if not kitti_sized:
        return "kitti"  # the KITTI reader reports the size mismatch
    raise ScanFormatError(
        f"{path}: not a KITTI .bin ({why}) and not an NCLT velodyne_sync .bin (8-byte records, laser ids 0..31); "
        "force a reader with --format kitti or --format nclt on the command line (format='kitti' or format='nclt'"
        " in Python)"
    )
