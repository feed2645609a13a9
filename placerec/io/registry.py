"""The scan format registry: `SCAN_READERS` / `SCAN_WRITERS` map a format name to its function, `EXTENSIONS` a
file suffix to its default format. `read_scan` and `write_scan` dispatch through them.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from placerec.errors import ConfigError, ScanFormatError
from placerec.io.bin_sniff import sniff_bin_format
from placerec.io.kitti import read_kitti_bin, write_kitti_bin
from placerec.io.nclt import read_nclt_bin
from placerec.io.numpy_io import read_npy, read_npz, write_npz
from placerec.io.pcd import read_pcd, write_pcd
from placerec.io.ply import read_ply, write_ply
from placerec.types import Scan, SensorInfo

__all__ = [
    "SCAN_READERS",
    "SCAN_WRITERS",
    "EXTENSIONS",
    "read_scan",
    "write_scan",
    "scan_format_of",
    "read_format_of",
]

#: format name -> reader ``(path, *, organized=False, **format_options) -> Scan``
SCAN_READERS: dict[str, Callable[..., Scan]] = {
    "kitti": read_kitti_bin,
    "nclt": read_nclt_bin,
    "pcd": read_pcd,
    "ply": read_ply,
    "npy": read_npy,
    "npz": read_npz,
}

#: format name -> writer ``(path, scan, **format_options) -> None``
SCAN_WRITERS: dict[str, Callable[..., None]] = {
    "kitti": write_kitti_bin,
    "pcd": write_pcd,
    "ply": write_ply,
    "npz": write_npz,
}

#: file suffix -> default format name (a ``.bin`` read without a format is checked for NCLT: `sniff_bin_format`)
EXTENSIONS: dict[str, str] = {".bin": "kitti", ".pcd": "pcd", ".ply": "ply", ".npy": "npy", ".npz": "npz"}


def scan_format_of(path: str | Path, format: str | None, table: dict[str, Any] | None = None) -> str:
    """The format name to use for ``path``: ``format`` when given (checked), else from the suffix."""
    table = SCAN_READERS if table is None else table
    if format is not None:
        if format not in table:
            raise ConfigError(f"unknown scan format {format!r}; known formats: {sorted(table)}")
        return format
    fmt = EXTENSIONS.get(Path(path).suffix.lower())
    if fmt is None or fmt not in table:
        known = sorted(k for k, v in EXTENSIONS.items() if v in table)
        raise ScanFormatError(
            f"{path}: cannot tell the scan format from the suffix (known: {known}; a .pcap, .bag, .db3 or .mcap"
            f" is a sequence, read with open_sequence); name one of {sorted(table)}: --format on the command"
            " line, format= in Python"
        )
    return fmt


def read_format_of(path: str | Path, format: str | None, options: dict[str, Any] | None = None) -> str:
    """The reader `read_scan` uses for ``path``: `scan_format_of`, then, for a ``.bin`` given neither ``format``
    nor a ``layout`` option, KITTI or NCLT as its bytes say (`sniff_bin_format`)."""
    fmt = scan_format_of(path, format)
    if format is None and fmt == "kitti" and "layout" not in (options or {}):
        fmt = sniff_bin_format(Path(path))
    return fmt


def _check_options(fn: Callable[..., Any], options: dict[str, Any], fmt: str) -> None:
    params = inspect.signature(fn).parameters
    allowed = {k for k, v in params.items() if v.kind is inspect.Parameter.KEYWORD_ONLY or k == "data"}
    allowed.discard("organized")
    unknown = set(options) - allowed
    if unknown:
        raise ConfigError(
            f"format {fmt!r} does not take option(s) {sorted(unknown)}; it takes {sorted(allowed)}"
        )


def read_scan(
    path: str | Path,
    *,
    organized: bool = False,
    format: str | None = None,
    sensor: SensorInfo | None = None,
    **options: Any,
) -> Scan:
    """Read one scan, choosing the reader by ``format`` or by the file suffix.

    A ``.bin`` without ``format`` (and without ``layout``) is read as KITTI unless its bytes are implausible as
    KITTI and plausible as NCLT ``velodyne_sync`` (`placerec.io.bin_sniff`); neither is a `ScanFormatError`.

    ``organized=True`` keeps the image structure when the file has one (PCD HEIGHT > 1, ``.npz`` shape,
    ``layout=`` for KITTI-style ``.bin``). ``sensor`` replaces the reader's `SensorInfo`. Other keyword
    options go to the reader, e.g. ``layout=(64, 1024, "column-major")`` for an organised ``.bin``.
    """
    fmt = read_format_of(path, format, options)
    reader = SCAN_READERS[fmt]
    _check_options(reader, options, fmt)
    scan = reader(path, organized=organized, **options)
    return scan if sensor is None else replace(scan, sensor=sensor)


def write_scan(path: str | Path, scan: Scan, format: str | None = None, **options: Any) -> None:
    """Write ``scan`` atomically in ``format`` (or the suffix's): kitti ``.bin``, pcd (``data="binary"``,
    ``"binary_compressed"`` or ``"ascii"``), ply (binary) or npz.
    """
    fmt = scan_format_of(path, format, SCAN_WRITERS)
    writer = SCAN_WRITERS[fmt]
    _check_options(writer, options, fmt)
    writer(path, scan, **options)
