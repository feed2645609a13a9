"""Per-scan description cache, keyed by the dataset + preprocessing config and the pipeline's front end.

Each entry keeps the time the front end took to compute it, so reported describe times do not depend on whether
a run found its descriptions in the cache.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError
from placerec.hashing import stable_hash
from placerec.io.atomic import load_artifact, save_artifact
from placerec.types import Description

log = logging.getLogger(__name__)

__all__ = ["DescriptionCache", "config_hash"]

_KIND = "description"
_VERSION = 2  # 2: the describe time is stored with the description


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
        self.root = None if root is None else Path(root) / data_key
        self.hits = 0
        self.misses = 0

    def _path(self, frontend_key: str, index: int) -> Path:
        assert self.root is not None
        return self.root / frontend_key / f"{index:06d}.npz"

    def get(self, frontend_key: str, index: int) -> tuple[Description, float] | None:
        """(description, the milliseconds its front end took), or None when absent or unreadable."""
        if self.root is None:
            return None
        path = self._path(frontend_key, index)
        if not path.is_file():
            self.misses += 1
            return None
        try:
            arrays, header = load_artifact(path, _KIND, (_VERSION,))
            describe_ms = float(header["meta"]["describe_ms"])
        except (ArtifactError, KeyError, TypeError, ValueError) as exc:
            log.warning("ignoring unreadable cache entry %s: %s", path, exc)
            self.misses += 1
            return None
        self.hits += 1
        return arrays, describe_ms

    def put(self, frontend_key: str, index: int, description: Description, describe_ms: float) -> None:
        """Store a description with the milliseconds its front end took to compute it."""
        if self.root is None:
            return
        arrays = {k: np.asarray(v) for k, v in description.items()}
        meta = {"frontend": frontend_key, "describe_ms": float(describe_ms)}
        save_artifact(self._path(frontend_key, index), _KIND, _VERSION, arrays, meta)
