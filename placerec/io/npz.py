"""Bounded decoding of ``.npy`` arrays and ``.npz`` archives, for scans and artifacts alike.

Nothing is decompressed or allocated before its declared size is checked: a ``.npz`` member table's uncompressed
sizes against the load cap (`placerec.io.limits`), each member's ``.npy`` header (shape x itemsize) against the
member's size, only stored (or, where allowed, deflated) members, no pickled (object) arrays. Every failure raises
the caller's placerec error class naming the file (and member) and what was expected.
"""

from __future__ import annotations

import contextlib
import contextvars
import io
import math
import struct
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, cast

import numpy as np

from placerec.errors import PlacerecError, short_repr
from placerec.io.limits import FileClass, check_size

__all__ = ["parse_npy", "read_npz_arrays", "mapped_without_crc"]

_CODECS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate"}
#: set by `mapped_without_crc`: memory-mapped members are not read for their CRC-32
_SKIP_MAPPED_CRC: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "placerec_skip_mapped_crc", default=False
)


@contextlib.contextmanager
def mapped_without_crc() -> Iterator[None]:
    """Inside this block, memory-mapped members (``mmap=True``) are not read for their CRC-32, so opening a large
    archive reads none of its data: for a caller that vouches for the bytes another way (a map folder's manifest
    lists every file's SHA-256, checked with ``placerec info MAP --check``). Every structural check still runs."""
    token = _SKIP_MAPPED_CRC.set(True)
    try:
        yield
    finally:
        _SKIP_MAPPED_CRC.reset(token)


_CRC_CHUNK = 64 << 20
# what corrupt bytes can raise inside zipfile / zlib / numpy's header parser
_ZIP_ERRORS = (
    zipfile.BadZipFile,
    zlib.error,
    EOFError,
    OSError,
    struct.error,
    NotImplementedError,
    RuntimeError,
)


def _read_header(
    fp: IO[bytes], where: str, error: type[PlacerecError]
) -> tuple[tuple[int, ...], bool, np.dtype]:
    try:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise error(f"{where}: unsupported .npy format version {version}")
    except PlacerecError:
        raise
    except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, tokenize.TokenError, ...
        raise error(f"{where}: not a valid .npy array ({type(exc).__name__}: {exc})") from None
    if not all(type(v) is int and v >= 0 for v in shape):  # numpy takes negative sizes, and True for 1
        raise error(
            f"{where}: .npy header declares shape {short_repr(shape)}; expected non-negative integers"
        )
    if dtype.hasobject:
        raise error(f"{where}: .npy holds Python objects (pickles are not loaded)")
    if dtype.itemsize == 0:
        raise error(f"{where}: .npy dtype {dtype} has no bytes per element")
    return tuple(int(v) for v in shape), bool(fortran), dtype


def _nbytes(shape: tuple[int, ...], dtype: np.dtype) -> int:
    return math.prod(shape) * dtype.itemsize


def parse_npy(
    buf: bytes,
    where: str | Path,
    error: type[PlacerecError],
    cls: FileClass = "scan",
    limit: int | None = None,
) -> np.ndarray:
    """Decode the bytes of one ``.npy`` file (no pickles) after checking its header against the data size and the
    load cap of ``cls``. The array is a read-only view of ``buf``."""
    f = io.BytesIO(buf)
    shape, fortran, dtype = _read_header(f, str(where), error)
    need = check_size(
        _nbytes(shape, dtype), where, f".npy header (shape {shape} of {dtype})", error, cls, limit
    )
    have = len(buf) - f.tell()
    if have < need:
        raise error(
            f"{where}: .npy data truncated: {have} bytes, expected {need} for shape {shape} of {dtype}"
        )
    arr = np.frombuffer(buf, dtype=dtype, count=math.prod(shape), offset=f.tell())
    return arr.reshape(shape, order="F" if fortran else "C")


def read_npz_arrays(
    source: str | Path | bytes,
    where: str | Path,
    error: type[PlacerecError],
    cls: FileClass,
    *,
    keys: Iterable[str] | None = None,
    allow_deflate: bool = True,
    limit: int | None = None,
    mmap: bool = False,
) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` archive (a path, or its bytes), by name without ``.npy``; with ``keys`` only
    those members are decoded (the others are still size-checked). Arrays are writable.

    ``mmap`` (``source`` a path): stored members are memory-mapped copy-on-write instead of read, so their pages
    are read once for their CRC-32 and can then be dropped by the kernel and paged in again on use (the load
    cap, which bounds allocations, applies only to the members read).

    Checks, before any member is decompressed: unique ``.npy`` member names, known codecs (stored, and deflate
    if ``allow_deflate``; a stored member's declared size equal to its stored size), no encryption, total
    declared size within the load cap of ``cls`` (or ``limit``); then for each member, that its ``.npy``
    header's shape x itemsize plus the header is exactly the member's declared size.
    """
    codecs = _CODECS if allow_deflate else {zipfile.ZIP_STORED: "stored"}
    wanted = None if keys is None else set(keys)
    src = io.BytesIO(source) if isinstance(source, bytes) else source
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(src) as zf:
            infos = zf.infolist()
            names = [info.filename for info in infos]
            if len(set(names)) != len(names):
                raise error(
                    f"{where}: .npz has duplicate members {sorted({n for n in names if names.count(n) > 1})}"
                )
            for info in infos:
                if not info.filename.endswith(".npy"):
                    raise error(f"{where}: .npz member {info.filename!r} is not a .npy array")
                if info.compress_type not in codecs:
                    raise error(
                        f"{where}: .npz member {info.filename!r} uses zip codec {info.compress_type}; "
                        f"expected {' or '.join(sorted(codecs.values()))}"
                    )
                if info.compress_type == zipfile.ZIP_STORED and info.file_size != info.compress_size:
                    raise error(
                        f"{where}: stored .npz member {info.filename!r} declares {info.file_size} bytes but "
                        f"stores {info.compress_size}"
                    )
                if info.flag_bits & 0x1:
                    raise error(f"{where}: .npz member {info.filename!r} is encrypted")
            mapped = mmap and not isinstance(source, bytes)
            read = [i for i in infos if not (mapped and i.compress_type == zipfile.ZIP_STORED)]
            check_size(sum(info.file_size for info in read), where, ".npz member table", error, cls, limit)
            for info in infos:
                key = info.filename[:-4]
                if wanted is None or key in wanted:
                    if info in read:
                        out[key] = _read_member(zf, info, f"{where}[{key}]", error)
                    else:
                        assert not isinstance(source, bytes)  # mapped members come from a path
                        out[key] = _map_member(Path(source), zf, info, f"{where}[{key}]", error)
    except PlacerecError:
        raise
    except (PermissionError, FileNotFoundError, IsADirectoryError) as exc:
        raise error(f"{where}: cannot read the file ({exc.strerror or type(exc).__name__})") from None
    except _ZIP_ERRORS as exc:
        raise error(f"{where}: not a valid .npz archive ({type(exc).__name__}: {exc})") from None
    return out


def _read_member(
    zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: str, error: type[PlacerecError]
) -> np.ndarray:
    with zf.open(info) as fh:
        shape, fortran, dtype = _read_header(fh, where, error)
        need = _nbytes(shape, dtype)
        if fh.tell() + need != info.file_size:
            raise error(
                f"{where}: .npy header declares shape {shape} of {dtype} ({need} bytes) but the member holds "
                f"{info.file_size - fh.tell()} data bytes"
            )
        data = bytearray(need)
        got = cast(io.BufferedIOBase, fh).readinto(data) if need else 0  # a zipfile.ZipExtFile
        if got != need:
            raise error(f"{where}: .npy data truncated: {got} bytes, expected {need}")
    arr = np.frombuffer(data, dtype=dtype, count=math.prod(shape))
    return arr.reshape(shape, order="F" if fortran else "C")


def _map_member(
    path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, where: str, error: type[PlacerecError]
) -> np.ndarray:
    """A stored member as a view of a copy-on-write memory map of ``path``, after checking its CRC-32 on the
    mapped bytes (read once, in chunks: the pages stay reclaimable page cache, nothing is allocated; not inside
    `mapped_without_crc`)."""
    with zf.open(info) as fh:
        shape, fortran, dtype = _read_header(fh, where, error)
        header_len = fh.tell()
    need = _nbytes(shape, dtype)
    if header_len + need != info.file_size:
        raise error(
            f"{where}: .npy header declares shape {shape} of {dtype} ({need} bytes) but the member holds "
            f"{info.file_size - header_len} data bytes"
        )
    with open(path, "rb") as raw:
        raw.seek(info.header_offset)
        local = raw.read(30)
    if len(local) != 30 or local[:4] != b"PK\x03\x04":
        raise error(f"{where}: no zip local header at offset {info.header_offset}")
    name_len, extra_len = struct.unpack("<HH", local[26:30])
    start = info.header_offset + 30 + name_len + extra_len
    if start + info.file_size > path.stat().st_size:
        raise error(f"{where}: .npy data truncated: the file ends before the member's {info.file_size} bytes")
    member = np.memmap(path, dtype=np.uint8, mode="c", offset=start, shape=(info.file_size,))
    if not _SKIP_MAPPED_CRC.get():
        crc = 0
        for k in range(0, info.file_size, _CRC_CHUNK):
            crc = zlib.crc32(member[k : k + _CRC_CHUNK].data, crc)
        if crc != info.CRC:
            raise error(f"{where}: CRC-32 mismatch (the member's bytes are corrupt)")
    arr = np.frombuffer(member, dtype=dtype, count=math.prod(shape), offset=header_len)
    return arr.reshape(shape, order="F" if fortran else "C")
