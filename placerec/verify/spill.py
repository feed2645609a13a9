"""An append-only file of byte records, read back by offset: where `placerec.verify.candidates.CloudStore` moves
the clouds beyond its RAM budget.

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
from typing import IO, NamedTuple

from placerec.errors import ConfigError, ScanDataError

__all__ = ["SpillRef", "SpillFile"]


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
