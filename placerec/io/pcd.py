"""PCD v0.7 point clouds (PCL): ``DATA ascii``, ``binary`` and ``binary_compressed``.

Reading: any field order; ``SIZE``/``TYPE``/``COUNT`` give each field's numpy type (``F`` 4/8, ``I`` and ``U``
1/2/4/8, little-endian); fields with ``COUNT > 1`` are read but not used. Intensity comes from a field named
intensity, reflectivity or i; ring from ``ring``; per-point time from ``t`` or ``time`` (integer types are taken
as nanoseconds). ``binary`` data are one structured ``np.frombuffer``; ``binary_compressed`` data are LZF
(see `placerec.io.lzf`) then one contiguous block per field. With ``organized=True`` and ``HEIGHT > 1`` the
scan keeps ``shape=(HEIGHT, WIDTH)`` and NaN points (PCL's invalid marker) become zeros.
"""

from __future__ import annotations

import io
import logging
import struct
from pathlib import Path

import numpy as np

from placerec.errors import ConfigError, ScanFormatError
from placerec.io._common import (
    checked_ints,
    columns_to_scan,
    guard,
    header_lines,
    read_bytes,
    structured_columns,
)
from placerec.io.atomic import atomic_write
from placerec.io.limits import check_size
from placerec.io.lzf import LZFError, lzf_compress, lzf_decompress
from placerec.types import Scan

log = logging.getLogger(__name__)

__all__ = ["read_pcd", "write_pcd", "PcdHeader", "parse_pcd_header"]

_KINDS = {("F", 4): "<f4", ("F", 8): "<f8"}
_KINDS.update({("I", s): f"<i{s}" for s in (1, 2, 4, 8)})
_KINDS.update({("U", s): f"<u{s}" for s in (1, 2, 4, 8)})
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
_MAX_HEADER_LINES = 200


class PcdHeader:
    """The parsed header of a PCD file."""

    def __init__(
        self,
        fields: list[str],
        dtypes: list[np.dtype],
        counts: list[int],
        width: int,
        height: int,
        points: int,
        data: str,
        data_offset: int,
    ) -> None:
        self.fields, self.dtypes, self.counts = fields, dtypes, counts
        self.width, self.height, self.points, self.data, self.data_offset = (
            width,
            height,
            points,
            data,
            data_offset,
        )

    def point_dtype(self) -> np.dtype:
        """Packed structured dtype of one point (unique names; PCL's ``_`` padding fields renamed)."""
        names: list[str] = []
        for k, f in enumerate(self.fields):
            names.append(f if f not in names and f != "_" else f"_pad{k}")
        formats = [dt if c == 1 else (dt, (c,)) for dt, c in zip(self.dtypes, self.counts, strict=True)]
        return np.dtype({"names": names, "formats": formats})


def _ints(vals: list[str], key: str, where: Path) -> list[int]:
    try:
        out = [int(v) for v in vals]
    except ValueError:
        raise ScanFormatError(f"{where}: PCD header {key} must be integers, got {' '.join(vals)!r}") from None
    if any(v < 0 for v in out):
        raise ScanFormatError(f"{where}: PCD header {key} must not be negative, got {' '.join(vals)!r}")
    return out


def _one(entries: dict[str, list[str]], key: str, default: int | None, where: Path) -> int:
    vals = entries.get(key)
    if vals is None and default is not None:
        return default
    if not vals or len(vals) != 1:
        raise ScanFormatError(f"{where}: PCD header {key} needs exactly one integer, got {vals!r}")
    return _ints(vals, key, where)[0]


def parse_pcd_header(buf: bytes, where: Path) -> PcdHeader:
    """Parse the header lines up to and including ``DATA``; ScanFormatError on anything inconsistent."""
    entries: dict[str, list[str]] = {}
    pos = 0
    for line, pos in header_lines(buf, where, "PCD", "DATA", _MAX_HEADER_LINES):  # noqa: B007 (pos: data offset)
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        entries[key.upper()] = vals
        if key.upper() == "DATA":
            break
    else:
        raise ScanFormatError(
            f"{where}: no DATA line in the first {_MAX_HEADER_LINES} lines; not a PCD file?"
        )
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH"):
        if key not in entries:
            raise ScanFormatError(f"{where}: PCD header lacks {key}")
    fields = entries["FIELDS"]
    sizes = _ints(entries["SIZE"], "SIZE", where)
    types = [t.upper() for t in entries["TYPE"]]
    counts = _ints(entries.get("COUNT", ["1"] * len(fields)), "COUNT", where)
    if not fields or not len(fields) == len(sizes) == len(types) == len(counts):
        raise ScanFormatError(
            f"{where}: PCD header FIELDS/SIZE/TYPE/COUNT have {len(fields)}/{len(sizes)}/{len(types)}/"
            f"{len(counts)} entries; they must match and be non-empty"
        )
    dtypes = []
    for f, t, s, c in zip(fields, types, sizes, counts, strict=True):
        if (t, s) not in _KINDS:
            raise ScanFormatError(
                f"{where}: PCD field {f!r} has unsupported TYPE {t} SIZE {s} "
                "(supported: F 4/8, I 1/2/4/8, U 1/2/4/8)"
            )
        if c == 0:
            raise ScanFormatError(f"{where}: PCD field {f!r} has COUNT 0")
        dtypes.append(np.dtype(_KINDS[(t, s)]))
    width = _one(entries, "WIDTH", None, where)
    height = _one(entries, "HEIGHT", 1, where)
    points = _one(entries, "POINTS", width * height, where)
    if points != width * height:
        raise ScanFormatError(
            f"{where}: PCD header says POINTS {points} but WIDTH x HEIGHT = {width} x {height}"
        )
    data = (entries["DATA"][:1] or [""])[0].lower()
    if data not in _DATA_KINDS:
        raise ScanFormatError(
            f"{where}: PCD DATA {data!r} not supported (expected one of {list(_DATA_KINDS)})"
        )
    return PcdHeader(fields, dtypes, counts, width, height, points, data, pos)


def _binary(buf: bytes, h: PcdHeader, where: Path) -> np.ndarray:
    dt = h.point_dtype()
    need = h.points * dt.itemsize
    have = len(buf) - h.data_offset
    if have < need:
        raise ScanFormatError(
            f"{where}: PCD binary data has {have} bytes, expected {need} "
            f"({h.points} points x {dt.itemsize} bytes)"
        )
    if have > need:  # PCL pads binary files to the page size; the padding is not data
        log.debug("%s: %d bytes after the %d declared points ignored", where, have - need, h.points)
    return np.frombuffer(buf, dtype=dt, count=h.points, offset=h.data_offset)


def _compressed(buf: bytes, h: PcdHeader, where: Path) -> dict[str, np.ndarray]:
    dt = h.point_dtype()
    off = h.data_offset
    if len(buf) < off + 8:
        raise ScanFormatError(f"{where}: PCD binary_compressed data lacks its 8-byte size header")
    comp, raw = struct.unpack_from("<II", buf, off)
    need = h.points * dt.itemsize
    if raw != need:
        raise ScanFormatError(
            f"{where}: PCD binary_compressed uncompressed size {raw} bytes, expected {need} "
            f"({h.points} points x {dt.itemsize} bytes)"
        )
    check_size(raw, where, "PCD binary_compressed uncompressed size", ScanFormatError, "scan")
    if len(buf) < off + 8 + comp:
        raise ScanFormatError(
            f"{where}: PCD binary_compressed data truncated: {len(buf) - off - 8} of "
            f"{comp} compressed bytes present"
        )
    try:
        data = lzf_decompress(memoryview(buf)[off + 8 : off + 8 + comp], raw)
    except LZFError as exc:
        raise ScanFormatError(f"{where}: PCD binary_compressed data corrupt ({exc})") from exc
    cols: dict[str, np.ndarray] = {}
    o = 0
    for name in dt.names or ():
        fdt = dt[name]
        cols[name] = (
            np.frombuffer(data, dtype=fdt, count=h.points, offset=o) if h.points else np.empty(0, fdt)
        )
        o += h.points * fdt.itemsize
    return cols


def _ascii(buf: bytes, h: PcdHeader, where: Path) -> dict[str, np.ndarray]:
    try:
        tokens = buf[h.data_offset :].decode("ascii").split()
    except UnicodeDecodeError:
        raise ScanFormatError(f"{where}: PCD ascii data is not ASCII text") from None
    per_point = sum(h.counts)
    if len(tokens) != h.points * per_point:
        raise ScanFormatError(
            f"{where}: PCD ascii data has {len(tokens)} values, expected {h.points} points x "
            f"{per_point} values"
        )
    try:
        vals = np.array(tokens, dtype=np.float64).reshape(h.points, per_point)
    except ValueError as exc:
        raise ScanFormatError(f"{where}: PCD ascii data contains a non-number ({exc})") from None
    dt = h.point_dtype()
    cols: dict[str, np.ndarray] = {}
    j = 0
    for name, c in zip(dt.names or (), h.counts, strict=True):
        if c == 1:
            col = vals[:, j]
            fdt = dt[name]
            if fdt.kind in "iu":
                col = checked_ints(col, fdt, where, f"PCD ascii integer field {name!r}")
            cols[name] = col
        j += c
    return cols


@guard("PCD")
def read_pcd(path: str | Path, *, organized: bool = False) -> Scan:
    """Read a PCD v0.7 file (ascii, binary or binary_compressed) into a `Scan`."""
    p, buf = read_bytes(path, "PCD")
    h = parse_pcd_header(buf, p)
    if h.data == "binary":
        cols = structured_columns(_binary(buf, h, p))
    elif h.data == "binary_compressed":
        cols = _compressed(buf, h, p)
    else:
        cols = _ascii(buf, h, p)
    cols = {k: v for k, v in cols.items() if not k.startswith("_pad")}
    shape = (h.height, h.width) if organized and h.height > 1 else None
    return columns_to_scan(cols, p, shape=shape)


def _scan_fields(scan: Scan) -> list[tuple[str, np.ndarray, str, int]]:
    fields = [(c, scan.xyz[:, j], "F", 4) for j, c in enumerate("xyz")]
    fields.append(("intensity", scan.intensity, "F", 4))
    if scan.ring is not None:
        unsigned = len(scan) == 0 or int(scan.ring.min()) >= 0
        fields.append(("ring", scan.ring.astype("<u2" if unsigned else "<i2"), "U" if unsigned else "I", 2))
    if scan.time is not None:
        fields.append(("t", scan.time, "F", 4))
    return fields


def write_pcd(path: str | Path, scan: Scan, data: str = "binary") -> None:
    """Write ``scan`` as PCD v0.7 (fields x y z intensity [ring] [t]); ``data``: binary, binary_compressed, ascii.

    Organised scans keep WIDTH = cols, HEIGHT = rows. The write is atomic.
    """
    if data not in _DATA_KINDS:
        raise ConfigError(f"PCD data kind must be one of {list(_DATA_KINDS)}, got {data!r}")
    fields = _scan_fields(scan)
    n = len(scan)
    height, width = scan.shape if scan.shape is not None else (1, n)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(f[0] for f in fields)}\nSIZE {' '.join(str(f[3]) for f in fields)}\n"
        f"TYPE {' '.join(f[2] for f in fields)}\nCOUNT {' '.join('1' for _ in fields)}\n"
        f"WIDTH {width}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode("ascii")
    dt = np.dtype([(f[0], _KINDS[(f[2], f[3])]) for f in fields])
    if data == "binary":
        rec = np.empty(n, dtype=dt)
        for name, arr, _, _ in fields:
            rec[name] = arr
        body = rec.tobytes()
    elif data == "binary_compressed":
        raw = b"".join(np.ascontiguousarray(arr, dtype=dt[name]).tobytes() for name, arr, _, _ in fields)
        comp = lzf_compress(raw)
        body = struct.pack("<II", len(comp), len(raw)) + comp
    else:
        sio = io.StringIO()
        cols = np.column_stack([arr.astype(np.float64) for _, arr, _, _ in fields]) if n else np.empty((0, 0))
        fmt = ["%d" if t in "IU" else "%.9g" for _, _, t, _ in fields]
        if n:
            np.savetxt(sio, cols, fmt=fmt)
        body = sio.getvalue().encode("ascii")
    with atomic_write(path) as fh:
        fh.write(header)
        fh.write(body)
