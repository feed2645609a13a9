"""Per-scan description cache, keyed by the dataset + preprocessing config and the pipeline's front end.

Each entry keeps the time the front end took to compute it, so reported describe times do not depend on whether
a run found its descriptions in the cache. An entry is used only when it is whole: the front-end key it was made
for, a finite describe time >= 0, and arrays of the recorded names, dtypes and shapes whose SHA-1 matches the one
stored with them. Anything else (a corrupt, truncated, edited or older entry) is recomputed with a warning.

Size limit: ``PLACEREC_CACHE_MAX_MB`` (default 2000 MB; ``0``/``off`` for none). A run that writes entries checks
the cache folder (``output.cache_dir``) after its first write and after each tenth of the limit it writes, and
evicts the least recently used entries (a hit counts as a use: it touches the entry's mtime) down to 90 % of the
limit, with a warning naming what went. `cache_info` and `clear_cache` are ``placerec cache info|clear``. Nothing
is removed from a folder holding anything the cache did not make (`scan_cache` refuses it): only
``<data key>/<front end>/<index>.npz`` entries, the atomic writes' temporary files and ``CACHEDIR.TAG``.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, ConfigError, short_repr
from placerec.hashing import stable_hash
from placerec.io.atomic import atomic_write, load_artifact, save_artifact
from placerec.types import Description

log = logging.getLogger(__name__)

__all__ = [
    "DescriptionCache",
    "config_hash",
    "CacheEntry",
    "LIMIT_ENV",
    "DEFAULT_LIMIT_MB",
    "cache_limit_mb",
    "scan_cache",
    "cache_info",
    "clear_cache",
    "trim_cache",
]

_KIND = "description"
_VERSION = 3  # 2: the describe time is stored with the description; 3: its layout and digest too


def config_hash(*parts: Any) -> str:
    """A short stable hash of JSON-serialisable config parts."""
    return stable_hash(list(parts))


class DescriptionCache:
    """Descriptions stored as ``root/<data_key>/<frontend_key>/<index>.npz`` (atomic, versioned).

    ``data_key`` must identify the scans (dataset + preprocessing config), ``frontend_key`` the front end and its
    parameters (`placerec.types.PlaceRecognizer.frontend_key`). A corrupt entry (or one of an older version) is
    recomputed. With ``root=None`` the cache is off.
    """

    def __init__(self, root: str | Path | None, data_key: str) -> None:
        if root is not None and Path(root).exists() and not Path(root).is_dir():
            raise ConfigError(
                f"output.cache_dir {str(root)!r} is a file, not a folder (null turns the cache off)"
            )
        self.cache_root = None if root is None else Path(root)
        self.root = None if root is None else Path(root) / data_key
        self.hits = 0
        self.misses = 0
        self._written = 0  # bytes written since the size limit was last kept
        self._trimmed = False  # whether this cache has kept the limit once (after its first write)
        self._trim_off = False  # the folder holds foreign files: never trimmed

    def _path(self, frontend_key: str, index: int) -> Path:
        assert self.root is not None
        return self.root / frontend_key / f"{index:06d}.npz"

    def has(self, frontend_key: str, index: int) -> bool:
        """Whether an entry is stored (not checked: `get` checks it)."""
        return self.root is not None and self._path(frontend_key, index).is_file()

    def get(self, frontend_key: str, index: int) -> tuple[Description, float] | None:
        """(description, the milliseconds its front end took), or None when absent or unusable (with a warning;
        the caller recomputes it)."""
        if self.root is None:
            return None
        path = self._path(frontend_key, index)
        if not path.is_file():
            self.misses += 1
            return None
        try:
            arrays, header = load_artifact(path, _KIND, (_VERSION,))
            describe_ms = _check_entry(path, frontend_key, arrays, header["meta"])
        except ArtifactError as exc:
            log.warning("recomputing the unusable cache entry %s: %s", path, exc)
            self.misses += 1
            return None
        self.hits += 1
        with contextlib.suppress(OSError):
            os.utime(path)  # a use: least recently used entries are evicted first
        return arrays, describe_ms

    def put(self, frontend_key: str, index: int, description: Description, describe_ms: float) -> None:
        """Store a description with the milliseconds its front end took to compute it."""
        if self.root is None:
            return
        arrays = {k: np.asarray(v) for k, v in description.items()}
        meta = {
            "frontend": frontend_key,
            "describe_ms": float(describe_ms),
            "layout": _layout(arrays),
            "sha1": _digest(arrays),
        }
        path = self._path(frontend_key, index)
        save_artifact(path, _KIND, _VERSION, arrays, meta)
        with contextlib.suppress(OSError):
            self._written += path.stat().st_size
        self._keep_limit()

    def _keep_limit(self) -> None:
        """After the first write and after each tenth of the size limit written: `trim_cache`."""
        assert self.cache_root is not None
        limit = cache_limit_mb()
        if limit is None or self._trim_off or (self._trimmed and self._written < limit * 1e6 / 10):
            return
        self._trimmed, self._written = True, 0
        try:
            trim_cache(self.cache_root, limit)
        except ConfigError as exc:
            log.warning("description cache not trimmed to its size limit: %s", exc)
            self._trim_off = True
            return
        tag = self.cache_root / _TAG
        if not tag.exists():
            with contextlib.suppress(OSError), atomic_write(tag, "w") as fh:
                fh.write(_TAG_TEXT)


def _layout(arrays: dict[str, np.ndarray]) -> dict[str, list]:
    return {k: [a.dtype.str, list(a.shape)] for k, a in sorted(arrays.items())}


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha1()
    for k, a in sorted(arrays.items()):
        h.update(f"{k}:{a.dtype.str}:{a.shape};".encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _check_entry(path: Path, frontend_key: str, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> float:
    """The entry's describe time (ms) after checking its front end, layout and digest; `ArtifactError` naming
    what is wrong otherwise."""
    if meta.get("frontend") != frontend_key:
        raise ArtifactError(f"{path}: made for front end {meta.get('frontend')!r}, not {frontend_key!r}")
    ms = meta.get("describe_ms")
    if not isinstance(ms, int | float) or isinstance(ms, bool) or not 0 <= ms < math.inf:
        raise ArtifactError(f"{path}: 'describe_ms' must be a finite number >= 0, got {short_repr(ms)}")
    if meta.get("layout") != _layout(arrays):
        raise ArtifactError(
            f"{path}: arrays {_layout(arrays)} differ from the recorded {meta.get('layout')!r:.200}"
        )
    if meta.get("sha1") != _digest(arrays):
        raise ArtifactError(f"{path}: the arrays' SHA-1 differs from the one recorded when it was stored")
    return float(ms)


#: The environment variable holding the cache's size limit in MB (``0``, ``off`` or ``none``: no limit).
LIMIT_ENV = "PLACEREC_CACHE_MAX_MB"
DEFAULT_LIMIT_MB = 2000.0
_TAG = "CACHEDIR.TAG"
_TAG_TEXT = (
    "Signature: 8a477f597d28d172789f06886806bc55\n"
    "# This file is a cache directory tag created by placerec (its description cache).\n"
    "# For information about cache directory tags see https://bford.info/cachedir/\n"
)
_ENTRY = re.compile(r"^\d{6,}\.npz$")
_TMP = re.compile(r"^\..+\.\d+\.[a-z0-9_]{8}\.tmp$")  # `placerec.io.atomic`'s temporary files


def cache_limit_mb() -> float | None:
    """The size limit in MB from ``PLACEREC_CACHE_MAX_MB`` (default 2000); None for no limit; `ConfigError` for a
    value that is not a number >= 0."""
    raw = os.environ.get(LIMIT_ENV, "").strip()
    if not raw:
        return DEFAULT_LIMIT_MB
    if raw.lower() in ("off", "none"):
        return None
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not 0 <= value < math.inf:
        raise ConfigError(f"{LIMIT_ENV}={short_repr(raw)}: expected a size in MB >= 0 (0 or off: no limit)")
    return None if value == 0 else value


@dataclass(frozen=True)
class CacheEntry:
    """One stored description: its file, data key, front-end key, size in bytes and last use (mtime, seconds)."""

    path: Path
    data_key: str
    frontend: str
    size: int
    mtime: float


def scan_cache(root: str | Path) -> list[CacheEntry]:
    """The entries of the cache folder ``root`` ([] when it does not exist); `ConfigError` when it holds anything
    the cache does not make (a file elsewhere than ``<data key>/<front end>/<index>.npz``, other than the atomic
    writes' temporary files and ``CACHEDIR.TAG``, or a link), so that nothing else is ever removed."""
    root = Path(root)
    if not root.exists():
        return []
    if not root.is_dir() or root.is_symlink():
        raise ConfigError(f"{root} is not a description cache folder (a file or a link)")
    entries, foreign = [], []
    with os.scandir(root) as top:
        for data in top:
            if data.name == _TAG and data.is_file(follow_symlinks=False):
                continue
            if not data.is_dir(follow_symlinks=False):
                foreign.append(data.path)
                continue
            # another process (a second worker trimming the same cache) may remove an entry, and the folders
            # it leaves empty, while they are listed here: what is gone is simply not listed
            with contextlib.suppress(FileNotFoundError), os.scandir(data.path) as fronts:
                for front in fronts:
                    if not front.is_dir(follow_symlinks=False):
                        foreign.append(front.path)
                        continue
                    with contextlib.suppress(FileNotFoundError), os.scandir(front.path) as files:
                        for f in files:
                            if _ENTRY.match(f.name) and f.is_file(follow_symlinks=False):
                                try:
                                    st = f.stat(follow_symlinks=False)
                                except FileNotFoundError:
                                    continue
                                entries.append(
                                    CacheEntry(Path(f.path), data.name, front.name, st.st_size, st.st_mtime)
                                )
                            elif not (_TMP.match(f.name) and f.is_file(follow_symlinks=False)):
                                foreign.append(f.path)
    if foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise ConfigError(
            f"{root} does not look like a description cache folder: it holds what the cache does not make"
            f" ({shown}); nothing removed (only <data key>/<front end>/<index>.npz entries are the cache's)"
        )
    return entries


def _frontend_name(key: str) -> str:
    """A front-end key without its parameter hash: ``scan-context-71346ec8a02c`` -> ``scan-context``."""
    return re.sub(r"-[0-9a-f]{12}$", "", key)


def cache_info(root: str | Path) -> dict[str, Any]:
    """Folder, size, limit, entries per front end (key: entries, MB) and oldest/newest last use of a cache."""
    entries = scan_cache(root)
    limit = cache_limit_mb()
    fronts: dict[str, dict[str, Any]] = {}
    for e in entries:
        f = fronts.setdefault(e.frontend, {"entries": 0, "mb": 0.0, "datasets": set()})
        f["entries"] += 1
        f["mb"] += e.size / 1e6
        f["datasets"].add(e.data_key)
    stamp = "%Y-%m-%d %H:%M:%S"
    return {
        "folder": str(Path(root).resolve()),
        "exists": Path(root).is_dir(),
        "entries": len(entries),
        "size_mb": round(sum(e.size for e in entries) / 1e6, 2),
        "limit_mb": limit if limit is not None else "none",
        "limit_from": f"{LIMIT_ENV} (default {DEFAULT_LIMIT_MB:g})",
        "datasets": len({e.data_key for e in entries}),
        "frontends": {
            k: {"entries": v["entries"], "mb": round(v["mb"], 2), "datasets": len(v["datasets"])}
            for k, v in sorted(fronts.items())
        },
        "oldest_use": time.strftime(stamp, time.localtime(min(e.mtime for e in entries)))
        if entries
        else None,
        "newest_use": time.strftime(stamp, time.localtime(max(e.mtime for e in entries)))
        if entries
        else None,
    }


def _remove(root: Path, entries: list[CacheEntry]) -> tuple[int, int]:
    """Remove ``entries`` (already checked to be the cache's), then their folders left empty; (count, bytes)."""
    count = size = 0
    for e in entries:
        try:
            e.path.unlink()
        except FileNotFoundError:
            continue  # another process evicted it
        count += 1
        size += e.size
    for folder in sorted(
        {e.path.parent for e in entries} | {e.path.parent.parent for e in entries}, reverse=True
    ):
        if folder != root and root in folder.parents:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty
    return count, size


def clear_cache(
    root: str | Path, older_than_days: float | None = None, frontend: str | None = None
) -> tuple[int, int]:
    """Remove the entries of the cache at ``root``: all, or those not used for ``older_than_days`` days, or of
    the front end ``frontend`` (a key, or a name such as ``scan-context`` for all its parameter sets); both
    given: those matching both. (entries removed, bytes freed)."""
    root = Path(root)
    entries = scan_cache(root)
    if older_than_days is not None:
        if not 0 <= older_than_days < math.inf:
            raise ConfigError(f"--older-than: expected a number of days >= 0, got {older_than_days}")
        cutoff = time.time() - older_than_days * 86400
        entries = [e for e in entries if e.mtime < cutoff]
    if frontend is not None:
        entries = [e for e in entries if frontend in (e.frontend, _frontend_name(e.frontend))]
    return _remove(root, entries)


def trim_cache(root: str | Path, limit_mb: float) -> tuple[int, int]:
    """Evict the least recently used entries of the cache at ``root`` until it holds at most 90 % of
    ``limit_mb`` when it holds more than ``limit_mb``; logged as a warning. (entries removed, bytes freed)."""
    root = Path(root)
    entries = sorted(scan_cache(root), key=lambda e: e.mtime)
    total = sum(e.size for e in entries)
    if total <= limit_mb * 1e6:
        return 0, 0
    goal = 0.9 * limit_mb * 1e6
    drop = []
    for e in entries:
        if total <= goal:
            break
        drop.append(e)
        total -= e.size
    count, size = _remove(root, drop)
    log.warning(
        "description cache %s was over its %g MB limit (%s): evicted %d least recently used entries (%.3g MB)",
        root,
        limit_mb,
        LIMIT_ENV,
        count,
        size / 1e6,
    )
    return count, size
