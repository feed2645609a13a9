"""Helpers shared by the scan readers: file checks, error wrapping and named-column to `Scan` conversion."""

from __future__ import annotations

import functools
import logging
import re
import struct
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TypeVar

import numpy as np
import numpy.typing as npt

from placerec.errors import ConfigError, DependencyError, ScanDataError, ScanFormatError
from placerec.io.limits import check_size
from placerec.types import Scan, SensorInfo

log = logging.getLogger(__name__)

#: Field names recognised as intensity, in order of preference.
INTENSITY_NAMES = ("intensity", "reflectivity", "scalar_intensity", "i")
#: Field names recognised as the beam index.
RING_NAMES = ("ring",)
#: Field names recognised as per-point time. Integer fields are taken as nanoseconds, floats as seconds.
TIME_NAMES = ("t", "time")

_F = TypeVar("_F", bound=Callable[..., Scan])

# Exceptions that malformed bytes can provoke deep inside numpy / struct / zipfile; readers turn them into
# ScanFormatError so that callers only ever see placerec's own error for a bad file.
_DECODE_ERRORS = (
    ValueError,
    IndexError,
    KeyError,
    TypeError,
    OverflowError,
    EOFError,
    struct.error,
    UnicodeDecodeError,
    zipfile.BadZipFile,
    ScanDataError,
)


def check_file(path: str | Path, what: str) -> Path:
    """The path as a `Path`; ScanFormatError if it is missing, not a file, empty, larger than the scan load cap
    (`placerec.io.limits`: 1 GiB unless ``PLACEREC_MAX_SCAN_BYTES`` says otherwise) or cannot be opened for
    reading (permissions: the file is opened once here, so that no reader meets a bare `PermissionError`)."""
    p = Path(path)
    try:
        if not p.exists():
            raise ScanFormatError(f"{p}: no such {what} file")
        if not p.is_file():
            raise ScanFormatError(f"{p}: expected a {what} file, found a directory or special file")
        size = p.stat().st_size
        if size == 0:
            raise ScanFormatError(f"{p}: empty file, expected {what} data")
        check_size(size, p, f"{what} file size", ScanFormatError, "scan")
        with open(p, "rb"):
            pass
    except OSError as exc:
        raise ScanFormatError(f"{p}: cannot read {what} file ({unreadable(exc)})") from None
    return p


def unreadable(exc: OSError) -> str:
    """Why a file could not be opened or read, for a message that already names the file."""
    return exc.strerror if exc.strerror else f"{type(exc).__name__}: {exc}"


def check_count(count: int, item_bytes: int, available: int, where: str | Path, what: str) -> int:
    """``count`` if ``count`` items of ``item_bytes`` each fit in the ``available`` bytes of the file and in the
    scan load cap (`placerec.io.limits`); ScanFormatError naming the file and ``what`` declared the count otherwise."""
    need = check_size(
        count * item_bytes, where, f"{what} ({count} x {item_bytes} bytes)", ScanFormatError, "scan"
    )
    if count < 0 or need > available:
        raise ScanFormatError(
            f"{where}: {what} declares {count} items of {item_bytes} bytes ({need} bytes), the file holds {available}"
        )
    return count


def read_bytes(path: str | Path, what: str) -> tuple[Path, bytes]:
    p = check_file(path, what)
    try:
        return p, p.read_bytes()
    except OSError as exc:
        raise ScanFormatError(f"{p}: cannot read {what} file ({unreadable(exc)})") from exc


def guard(what: str) -> Callable[[_F], _F]:
    """Decorator: convert low-level decoding errors of a reader into ScanFormatError naming file and format."""

    def deco(fn: _F) -> _F:
        @functools.wraps(fn)
        def wrapper(path: str | Path, *args: object, **kwargs: object) -> Scan:
            try:
                return fn(path, *args, **kwargs)
            except (ScanFormatError, ConfigError, DependencyError):
                raise
            except OSError as exc:  # e.g. permissions changed after `check_file`, or an I/O error
                raise ScanFormatError(f"{path}: cannot read {what} file ({unreadable(exc)})") from exc
            except _DECODE_ERRORS as exc:
                raise ScanFormatError(
                    f"{path}: not a valid {what} file ({type(exc).__name__}: {exc})"
                ) from exc

        return wrapper  # type: ignore[return-value]

    return deco


def header_lines(buf: bytes, where: Path, kind: str, end: str, max_lines: int) -> Iterator[tuple[str, int]]:
    """The stripped lines of an ASCII header at the start of ``buf``, each with the byte offset just after it, up to
    ``max_lines`` lines. ScanFormatError (naming the file, the ``kind`` of file and the ``end`` line expected) when
    the bytes run out before a newline or a line is not ASCII."""
    pos = 0
    for _ in range(max_lines):
        nl = buf.find(b"\n", pos)
        if nl < 0:
            raise ScanFormatError(
                f"{where}: {kind} header has no {end} line (truncated or not a {kind} file)"
            )
        try:
            line = buf[pos:nl].decode("ascii").strip()
        except UnicodeDecodeError:
            raise ScanFormatError(
                f"{where}: {kind} header line at byte {pos} is not ASCII; not a {kind} file?"
            ) from None
        pos = nl + 1
        yield line, pos


def pick(columns: Mapping[str, np.ndarray], names: tuple[str, ...]) -> tuple[str, np.ndarray] | None:
    """The first column whose (case-insensitive) name is in ``names``."""
    lower = {k.lower(): k for k in columns}
    for n in names:
        if n in lower:
            key = lower[n]
            return key, columns[key]
    return None


def checked_ints(values: np.ndarray, dtype: npt.DTypeLike, where: str | Path, what: str) -> np.ndarray:
    """``values`` (parsed as float64) as integers of ``dtype``; ScanFormatError naming ``where`` and ``what`` for
    NaN/inf, a fraction or a value outside the type's range (instead of a silent wrap-around)."""
    dt = np.dtype(dtype)
    info = np.iinfo(dt)
    bad = ~np.isfinite(values)
    if bad.any():
        raise ScanFormatError(f"{where}: {what} holds NaN/inf; expected {dt.name} integers")
    bad = (values < info.min) | (values > info.max) | (values != np.round(values))
    if bad.any():
        raise ScanFormatError(
            f"{where}: {what} holds {values[bad][0]:g} ({int(bad.sum())} value(s) in all); expected {dt.name} "
            f"integers in {info.min}..{info.max}"
        )
    return values.astype(dt)


def _ring(name: str, col: np.ndarray, where: str | Path) -> np.ndarray:
    """A ring column as placerec's int16; ScanFormatError when a value does not fit (or is not an integer)."""
    if col.dtype.kind in "iu" and np.can_cast(col.dtype, np.int16):
        return col.astype(np.int16)
    return checked_ints(
        np.asarray(col, np.float64), np.int16, where, f"ring field {name!r} ({col.dtype.name})"
    )


def intensity_max_of(dtype: np.dtype) -> float | None:
    """Saturation value implied by an integer intensity type (255 for uint8, 65535 for uint16)."""
    if dtype.kind == "u" and dtype.itemsize <= 2:
        return float(np.iinfo(dtype).max)
    return None


def time_seconds(arr: np.ndarray) -> np.ndarray:
    """Per-point time in seconds: integer fields (e.g. Ouster's uint32 ``t``) are nanoseconds."""
    if arr.dtype.kind in "iu":
        return (arr.astype(np.float64) * 1e-9).astype(np.float32)
    return arr.astype(np.float32)


def columns_to_scan(
    columns: Mapping[str, np.ndarray],
    where: str | Path,
    *,
    shape: tuple[int, int] | None = None,
    sensor: SensorInfo | None = None,
    timestamp: float | None = None,
) -> Scan:
    """Build a `Scan` from named 1-D columns (x, y, z required; intensity/ring/time looked up by name).

    With ``shape`` the scan is organised and non-finite xyz (PCL's marker of an invalid return) become zeros,
    placerec's convention for organised scans.
    """
    lower = {k.lower(): k for k in columns}
    missing = [c for c in "xyz" if c not in lower]
    if missing:
        raise ScanFormatError(f"{where}: no field(s) {missing}; expected x, y, z (found {sorted(columns)})")
    xyz = np.empty((len(columns[lower["x"]]), 3), dtype=np.float32)
    for j, c in enumerate("xyz"):
        xyz[:, j] = columns[lower[c]]
    n = xyz.shape[0]
    inten = pick(columns, INTENSITY_NAMES)
    imax = None
    if inten is None:
        log.debug("%s: no intensity field, using zeros", where)
        intensity = np.zeros(n, dtype=np.float32)
    else:
        imax = intensity_max_of(inten[1].dtype)
        intensity = inten[1].astype(np.float32)
    ring_col = pick(columns, RING_NAMES)
    ring = None if ring_col is None else _ring(*ring_col, where)
    time_col = pick(columns, TIME_NAMES)
    time = None if time_col is None else time_seconds(time_col[1])
    if shape is not None:
        bad = ~np.isfinite(xyz).all(axis=1)
        if bad.any():
            xyz[bad] = 0.0
            intensity[bad] = 0.0
    if sensor is None:
        sensor = SensorInfo(intensity_max=imax, columns=None if shape is None else shape[1])
    return Scan(
        xyz=xyz,
        intensity=intensity,
        ring=ring,
        time=time,
        shape=shape,
        sensor=sensor,
        timestamp=timestamp,
        source=str(where),
    )


def structured_columns(arr: np.ndarray) -> dict[str, np.ndarray]:
    """Named 1-D columns of a structured array (fields with a sub-array shape are skipped)."""
    out: dict[str, np.ndarray] = {}
    for name in arr.dtype.names or ():
        col = arr[name]
        if col.ndim == arr.ndim:
            out[name] = col.reshape(-1)
    return out


_NAT = re.compile(r"([0-9]+)")


def ascii_digits(text: str) -> bool:
    """Whether ``text`` is a non-empty run of the digits 0-9. (`str.isdigit` also takes superscripts such as
    ``'¹²³'``, on which `int` fails, and `str.isdecimal` other scripts' digits.)"""
    return text.isascii() and text.isdecimal()


def natural_key(path: Path) -> tuple[object, ...]:
    """Sort key ordering ``scan2`` before ``scan10``."""
    return tuple(int(t) if ascii_digits(t) else t.lower() for t in _NAT.split(path.name))
