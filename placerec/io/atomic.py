"""Atomic, versioned artifact files: write to a temporary file in the same folder, fsync, rename, fsync the folder.

Artifacts (databases, vocabularies, calibration tables, caches) are ``.npz`` archives holding a JSON header under
the key ``__header__`` with ``kind``, ``format_version`` and free metadata (e.g. the config that made them).
`load_artifact` reads them through `placerec.io.npz` (declared sizes checked against the artifact load cap of
`placerec.io.limits` before anything is read, stored members only, no pickles) and checks the header and, given a schema
(`placerec.io.artifact_schema`), every array; anything wrong is an `ArtifactError` naming the file.

Files get the permissions the user's umask gives new files (not `tempfile`'s 0600). A save's temporary file is
named ``.<target name>.<pid>.<random>.tmp`` beside the target; one left by a save that was interrupted (its
process has ended) is removed by the next save into the same folder.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from placerec.errors import ArtifactError, short_repr
from placerec.io.artifact_schema import Schema, check_members
from placerec.io.limits import check_size
from placerec.io.npz import read_npz_arrays

__all__ = ["atomic_write", "save_artifact", "load_artifact", "peek_artifact", "json_object", "HEADER_KEY"]

HEADER_KEY = "__header__"
_MAX_HEADER_BYTES = 16 << 20
_TMP_SUFFIX = ".tmp"
# a temporary file: "." + target name + "." + the saving process's pid + "." + mkstemp's 8 random characters + ".tmp"
_TMP_NAME = re.compile(r"^\.(?P<target>.+)\.(?P<pid>\d+)\.[a-z0-9_]{8}\.tmp$")
_in_flight: set[str] = set()  # temporary files this process is writing now
_seen: dict[str, int] = {}  # folder -> its mtime after this process's last save into it
_lock = threading.Lock()


def _umask() -> int:
    """The process's umask: from /proc where the kernel reports it, else by setting and restoring it (which,
    for a moment, applies 0o022 to files other threads create)."""
    with contextlib.suppress(OSError, ValueError), open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    with _lock:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists but belongs to someone else (or cannot be asked): leave its file alone
    return True


def _remove_stale_temps(folder: Path) -> None:
    """Remove the temporary files that saves into ``folder`` left behind: those whose process has ended, and this
    process's own that no save is writing. The folder is listed only if something other than this process's
    saves changed it since the last look (its mtime), so filling a cache of thousands of files stays cheap."""
    try:
        if _seen.get(str(folder)) == os.stat(folder).st_mtime_ns:
            return
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        match = _TMP_NAME.match(name)
        if match is None:
            continue
        pid, tmp = int(match["pid"]), os.path.join(os.path.abspath(folder), name)  # as mkstemp names it
        with _lock:
            busy = tmp in _in_flight
        if busy or (pid != os.getpid() and _pid_alive(pid)):
            continue
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


def _note_folder(folder: Path) -> None:
    """Remember ``folder``'s mtime after this process changed it (see `_remove_stale_temps`)."""
    with contextlib.suppress(OSError):
        _seen[str(folder)] = os.stat(folder).st_mtime_ns


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable; a no-op where folders cannot be opened or fsynced."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on success fsync it, rename it over ``path`` and fsync the folder.

    If the body raises, the temporary file is removed and ``path`` is left untouched. The file gets mode
    ``0o666 & ~umask``. Temporary files left in its folder by interrupted saves are removed first.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=_TMP_SUFFIX, dir=path.parent)
    with _lock:
        _in_flight.add(tmp)
    try:
        with os.fdopen(fd, mode) as fh:
            os.fchmod(fh.fileno(), 0o666 & ~_umask())
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
        _note_folder(path.parent)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    finally:
        with _lock:
            _in_flight.discard(tmp)


def save_artifact(
    path: str | Path,
    kind: str,
    format_version: int,
    arrays: dict[str, np.ndarray],
    meta: dict[str, Any] | None = None,
) -> None:
    """Write ``arrays`` and a JSON header atomically as an uncompressed ``.npz``."""
    header = {"kind": kind, "format_version": int(format_version), "meta": meta or {}}
    if HEADER_KEY in arrays:
        raise ArtifactError(f"array name {HEADER_KEY!r} is reserved")
    payload: dict[str, Any] = dict(arrays)
    payload[HEADER_KEY] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with atomic_write(path) as fh:
        np.savez(fh, **payload)


def load_artifact(
    path: str | Path,
    kind: str,
    supported_versions: tuple[int, ...],
    schema: Schema | None = None,
    *,
    limit: int | None = None,
    mmap: bool = False,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read an artifact written by `save_artifact`. Returns (arrays, header); arrays are writable.

    ``mmap``: the arrays are copy-on-write memory maps of the file (`placerec.io.npz.read_npz_arrays`): a large
    database costs RAM only for the pages used, which the kernel can drop again.

    Checks, raising `ArtifactError` naming the file: the archive (file and declared member sizes within the
    artifact load cap, `placerec.io.limits`, or ``limit``; stored members only, as `save_artifact` writes them,
    so nothing expands; no pickles), the header
    (a JSON object with ``kind`` == ``kind``, an integer ``format_version`` in ``supported_versions``, a ``meta``
    object) and, with ``schema``, every array (`placerec.io.artifact_schema.check_members`).
    """
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such artifact file")
    if not mmap:
        check_size(path.stat().st_size, path, "file size", ArtifactError, "artifact", limit)
    arrays = read_npz_arrays(
        path, path, ArtifactError, "artifact", allow_deflate=False, limit=limit, mmap=mmap
    )
    header = _parse_header(arrays.pop(HEADER_KEY, None), path)
    if header["kind"] != kind:
        raise ArtifactError(f"{path}: artifact is a {short_repr(header['kind'])}, expected a {kind!r}")
    if header["format_version"] not in supported_versions:
        raise ArtifactError(
            f"{path}: {kind} format version {short_repr(header['format_version'])} is not supported "
            f"(this placerec reads {list(supported_versions)})"
        )
    if schema is not None:
        check_members(arrays, schema, path)
    return arrays, header


def peek_artifact(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """(arrays memory-mapped, header) of the placerec artifact at ``path``, whatever its kind and version, or None
    for an ``.npz`` that has no header (e.g. a scan); for ``placerec info``. The archive checks of
    `load_artifact` apply (`ArtifactError`)."""
    path = Path(path)
    first = read_npz_arrays(path, path, ArtifactError, "artifact", keys=[HEADER_KEY], mmap=True)
    if HEADER_KEY not in first:
        return None
    arrays = read_npz_arrays(path, path, ArtifactError, "artifact", allow_deflate=False, mmap=True)
    return arrays, _parse_header(arrays.pop(HEADER_KEY), path)


def json_object(raw: bytes, where: str) -> dict[str, Any]:
    """``raw`` (UTF-8 JSON) as the object it must hold; `ArtifactError` starting with ``where`` otherwise."""
    try:
        data = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ArtifactError(f"{where} is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ArtifactError(f"{where} must be a JSON object, got {type(data).__name__}")
    return data


def _parse_header(raw: np.ndarray | None, path: Path) -> dict[str, Any]:
    if raw is None:
        raise ArtifactError(f"{path}: not a placerec artifact (no {HEADER_KEY!r} member)")
    if raw.dtype != np.uint8 or raw.ndim != 1 or raw.size > _MAX_HEADER_BYTES:
        raise ArtifactError(
            f"{path}: header must be UTF-8 JSON bytes (uint8, 1-D), got {raw.dtype} {raw.shape}"
        )
    header = json_object(raw.tobytes(), f"{path}: header")
    kind, version, meta = header.get("kind"), header.get("format_version"), header.get("meta", {})
    if not isinstance(kind, str):
        raise ArtifactError(f"{path}: header 'kind' must be a string, got {short_repr(kind)}")
    if not isinstance(version, int) or isinstance(version, bool):
        raise ArtifactError(f"{path}: header 'format_version' must be an integer, got {short_repr(version)}")
    if not isinstance(meta, dict):
        raise ArtifactError(f"{path}: header 'meta' must be a JSON object, got {type(meta).__name__}")
    header["meta"] = meta
    return header
