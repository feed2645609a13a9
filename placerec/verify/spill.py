"""An append-only file of byte records, read back by offset: where `placerec.verify.candidates.CloudStore` moves
the clouds beyond its RAM budget, and `SpilledArrays` (a mapping id -> array with a RAM budget) the arrays beyond
its own (the 2D pipelines' per-entry keypoints, their 3D points and descriptors).

::

    spill = SpillFile(folder=None)        # created on the first write, in the system's temporary folder
    ref = spill.write(cloud.data)         # a `SpillRef`: offset and length
    data = spill.read(ref)                # the same bytes

The file is opened unnamed (`tempfile.TemporaryFile`: on POSIX it has no directory entry), so it takes no space
once the process ends, however it ends. Reads use ``os.pread`` (no shared file position), so they are safe from
several threads; writes are serialised by a lock. A failed write (disk full, a folder that is not writable) is a
`ConfigError` naming the folder and ``verify.cloud_spill_dir``: nothing written so far is lost.
"""

from __future__ import annotations

import os
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from typing import IO, NamedTuple

import numpy as np

from placerec.errors import ConfigError, ScanDataError

__all__ = ["SpillRef", "SpillFile", "SpilledArrays", "memory_mapped"]


class SpillRef(NamedTuple):
    """Where a record lies in its `SpillFile`."""

    offset: int
    length: int


class SpillFile:
    """Byte records appended to one unnamed temporary file in ``folder`` (None: the system's temporary folder)."""

    def __init__(self, folder: str | None = None) -> None:
        self.folder = folder
        self._file: IO[bytes] | None = None
        self._size = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """Bytes written to the file so far."""
        return self._size

    def _open(self) -> IO[bytes]:
        if self._file is None:
            try:
                self._file = tempfile.TemporaryFile(prefix="placerec-clouds-", dir=self.folder, buffering=0)
            except OSError as exc:
                where = self.folder or tempfile.gettempdir()
                raise ConfigError(
                    f"verify.cloud_spill_dir: cannot create the spill file in {where!r}: {exc.strerror or exc}"
                ) from None
        return self._file

    def write(self, data: bytes) -> SpillRef:
        with self._lock:
            fh = self._open()
            offset = self._size
            try:
                done = 0
                view = memoryview(data)
                while done < len(view):
                    done += os.pwrite(fh.fileno(), view[done:], offset + done)
            except OSError as exc:
                where = self.folder or tempfile.gettempdir()
                raise ConfigError(
                    f"verify.cloud_spill_dir: writing the spill file in {where!r} failed: {exc.strerror or exc}"
                ) from None
            self._size += len(data)
            return SpillRef(offset, len(data))

    def read(self, ref: SpillRef) -> bytes:
        if self._file is None or ref.offset < 0 or ref.offset + ref.length > self._size:
            raise ScanDataError(f"spill record {ref} lies outside the spill file ({self._size} bytes)")
        fd = self._file.fileno()
        parts, done = [], 0
        while done < ref.length:
            chunk = os.pread(fd, ref.length - done, ref.offset + done)
            if not chunk:
                raise ScanDataError(f"spill file ended inside record {ref}")
            parts.append(chunk)
            done += len(chunk)
        return b"".join(parts)

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
                self._size = 0

    def __del__(self) -> None:
        f = getattr(self, "_file", None)
        if f is not None:
            f.close()


def memory_mapped(a: object) -> bool:
    """Whether ``a`` views the pages of a memory-mapped file (an `np.memmap` somewhere in its ``base`` chain)."""
    while a is not None:
        if isinstance(a, np.memmap):
            return True
        a = getattr(a, "base", None)
    return False


class _ArrayRef(NamedTuple):
    """An array moved to a `SpillFile`: where its bytes are, and its dtype and shape."""

    ref: SpillRef
    dtype: np.dtype
    shape: tuple[int, ...]


class SpilledArrays(Mapping[int, np.ndarray]):
    """A mapping id -> array that keeps at most ``budget_bytes`` of arrays in RAM (None: no limit): beyond it the
    oldest added move to ``spill`` and are read back (read-only) when looked up. Arrays viewing a memory-mapped
    file are kept as they are and not counted (their pages take no RAM until used)."""

    def __init__(self, budget_bytes: int | None, spill: SpillFile) -> None:
        self.budget_bytes = budget_bytes
        self._spill = spill
        self._items: dict[int, np.ndarray | _ArrayRef] = {}
        self._in_ram: OrderedDict[int, int] = OrderedDict()  # counted ids, oldest first -> their bytes
        self._ram = 0

    @property
    def nbytes(self) -> int:
        """Bytes of the counted arrays in RAM."""
        return self._ram

    def __setitem__(self, key: int, value: np.ndarray) -> None:
        key = int(key)
        self._ram -= self._in_ram.pop(key, 0)
        arr = np.asarray(value)
        self._items[key] = arr
        if memory_mapped(arr):
            return
        self._in_ram[key] = int(arr.nbytes)
        self._ram += int(arr.nbytes)
        if self.budget_bytes is not None:
            while self._ram > self.budget_bytes and self._in_ram:
                old, size = self._in_ram.popitem(last=False)
                a = np.ascontiguousarray(self._items[old])
                self._items[old] = _ArrayRef(self._spill.write(a.tobytes()), a.dtype, a.shape)
                self._ram -= size

    def __getitem__(self, key: int) -> np.ndarray:
        v = self._items[int(key)]
        if isinstance(v, _ArrayRef):
            return np.frombuffer(self._spill.read(v.ref), v.dtype).reshape(v.shape)
        return v

    def __iter__(self) -> Iterator[int]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: object) -> bool:
        return key in self._items
