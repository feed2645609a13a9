"""Per-scan description cache, keyed by the dataset + preprocessing config and the pipeline's front end.

Each entry keeps the time the front end took to compute it, so reported describe times do not depend on whether
a run found its descriptions in the cache. An entry is used only when it is whole: the front-end key it was made
for, a finite describe time >= 0, and arrays of the recorded names, dtypes and shapes whose SHA-1 matches the one
stored with them. Anything else (a corrupt, truncated, edited or older entry) is recomputed with a warning.
"""

from __future__ import annotations

import hashlib
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError, ConfigError, short_repr
from placerec.hashing import stable_hash
from placerec.io.atomic import load_artifact, save_artifact
from placerec.types import Description

log = logging.getLogger(__name__)

__all__ = ["DescriptionCache", "config_hash"]

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
        self.root = None if root is None else Path(root) / data_key
        self.hits = 0
        self.misses = 0

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
        save_artifact(self._path(frontend_key, index), _KIND, _VERSION, arrays, meta)


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
