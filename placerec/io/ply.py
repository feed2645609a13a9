"""PLY point clouds: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``.

Only the ``vertex`` element is read (x, y, z and, when present, an intensity property named intensity,
reflectivity, scalar_intensity or i — any case —, ``ring`` and ``t``/``time``). Elements after it (faces) are
ignored; elements before it must have only scalar properties in binary files. A list property inside
``vertex`` is not supported. Own parser: open3d's PLY reader drops intensity.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io._common import (
    checked_ints,
    columns_to_scan,
    guard,
    header_lines,
    read_bytes,
    structured_columns,
)
from placerec.io.atomic import atomic_write
from placerec.types import Scan

__all__ = ["read_ply", "write_ply"]

_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER_LINES = 1000


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name, self.count = name, count
        self.props: list[tuple[str, str]] = []  # (name, numpy type) for scalars
        self.has_list = False


def _parse_header(buf: bytes, where: Path) -> tuple[str, list[_Element], int]:
    if not buf.startswith(b"ply"):
        raise ScanFormatError(f"{where}: not a PLY file (does not start with 'ply')")
    fmt = None
    elements: list[_Element] = []
    pos = 0
    for line, pos in header_lines(buf, where, "PLY", "end_header", _MAX_HEADER_LINES):  # noqa: B007 (pos: data offset)
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in _FORMATS:
                raise ScanFormatError(
                    f"{where}: PLY format {line!r} not supported (expected {list(_FORMATS)})"
                )
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ScanFormatError(
                    f"{where}: bad PLY element line {line!r} (expected 'element NAME COUNT')"
                )
            elements.append(_Element(parts[1], int(parts[2])))
        elif parts[0] == "property":
            if not elements:
                raise ScanFormatError(f"{where}: PLY property before any element: {line!r}")
            if len(parts) == 5 and parts[1] == "list":
                elements[-1].has_list = True
            elif len(parts) == 3 and parts[1] in _TYPES:
                elements[-1].props.append((parts[2], _TYPES[parts[1]]))
            else:
                raise ScanFormatError(f"{where}: unsupported PLY property {line!r} (types: {sorted(_TYPES)})")
        else:
            raise ScanFormatError(f"{where}: unexpected PLY header line {line!r}")
    else:
        raise ScanFormatError(f"{where}: no end_header in the first {_MAX_HEADER_LINES} PLY header lines")
    if fmt is None:
        raise ScanFormatError(f"{where}: PLY header lacks a format line")
    return fmt, elements, pos


def _dtype(el: _Element, order: str, where: Path) -> np.dtype:
    names = [n for n, _ in el.props]
    if len(set(names)) != len(names):
        raise ScanFormatError(f"{where}: PLY element {el.name!r} repeats a property name")
    return np.dtype([(n, order + t) for n, t in el.props])


@guard("PLY")
def read_ply(path: str | Path, *, organized: bool = False) -> Scan:
    """Read the vertex element of a PLY file into an unorganised `Scan`."""
    p, buf = read_bytes(path, "PLY")
    fmt, elements, off = _parse_header(buf, p)
    idx = next((k for k, e in enumerate(elements) if e.name == "vertex"), None)
    if idx is None:
        raise ScanFormatError(f"{p}: PLY file has no 'vertex' element")
    vertex = elements[idx]
    if vertex.has_list:
        raise ScanFormatError(f"{p}: list properties in the PLY vertex element are not supported")
    order = _FORMATS[fmt]
    n = vertex.count
    if fmt == "ascii":
        skip = sum(e.count for e in elements[:idx])
        parts = buf[off:].split(b"\n", skip + n)
        if len(parts) < skip + n:
            raise ScanFormatError(f"{p}: PLY ascii data has {len(parts)} lines, expected at least {skip + n}")
        tokens = b" ".join(parts[skip : skip + n]).split()
        k = len(vertex.props)
        if len(tokens) != n * k:
            raise ScanFormatError(f"{p}: PLY ascii vertex data has {len(tokens)} values, expected {n} x {k}")
        try:
            vals = np.array([t.decode("ascii") for t in tokens], dtype=np.float64).reshape(n, k)
        except ValueError as exc:
            raise ScanFormatError(f"{p}: PLY ascii vertex data contains a non-number ({exc})") from None
        cols = {
            name: vals[:, j].astype(t)
            if t[0] == "f"
            else checked_ints(vals[:, j], t, p, f"PLY ascii integer property {name!r}")
            for j, (name, t) in enumerate(vertex.props)
        }
    else:
        for e in elements[:idx]:
            if e.has_list:
                raise ScanFormatError(
                    f"{p}: PLY element {e.name!r} before 'vertex' has a list property; "
                    "cannot skip it in binary data"
                )
            off += e.count * _dtype(e, order, p).itemsize
        dt = _dtype(vertex, order, p)
        need = n * dt.itemsize
        if len(buf) - off < need:
            raise ScanFormatError(
                f"{p}: PLY binary vertex data truncated: {max(len(buf) - off, 0)} bytes, "
                f"expected {need} ({n} vertices x {dt.itemsize} bytes)"
            )
        arr = np.frombuffer(buf, dtype=dt, count=n, offset=off)
        cols = {k: v.astype(v.dtype.newbyteorder("=")) for k, v in structured_columns(arr).items()}
    return columns_to_scan(cols, p)


def write_ply(path: str | Path, scan: Scan) -> None:
    """Write ``scan`` as binary little-endian PLY (float x y z intensity, [ushort ring], [float t]); atomic."""
    fields: list[tuple[str, str, str, np.ndarray]] = [
        (c, "float", "<f4", scan.xyz[:, j]) for j, c in enumerate("xyz")
    ]
    fields.append(("intensity", "float", "<f4", scan.intensity))
    if scan.ring is not None:
        fields.append(("ring", "short", "<i2", scan.ring))
    if scan.time is not None:
        fields.append(("t", "float", "<f4", scan.time))
    rec = np.empty(len(scan), dtype=[(f[0], f[2]) for f in fields])
    for name, _, _, arr in fields:
        rec[name] = arr
    header = "ply\nformat binary_little_endian 1.0\ncomment written by placerec\n"
    header += f"element vertex {len(scan)}\n" + "".join(f"property {t} {n}\n" for n, t, _, _ in fields)
    header += "end_header\n"
    with atomic_write(path) as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
