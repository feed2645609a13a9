"""Per-scan description cache, keyed by the dataset + preprocessing config and the pipeline's front end."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ArtifactError
from placerec.hashing import stable_hash
from placerec.io.atomic import load_artifact, save_artifact
from placerec.recognizer import Description

log = logging.getLogger(__name__)

__all__ = ["DescriptionCache", "config_hash"]

_KIND = "description"
_VERSION = 1


def config_hash(*parts: Any) -> str:
    """A short stable hash of JSON-serialisable config parts."""
    return stable_hash(list(parts))


class DescriptionCache:
    """Descriptions stored as ``root/<data_key>/<frontend_key>/<index>.npz`` (atomic, versioned).

    ``data_key`` must identify the scans (dataset + preprocessing config), ``frontend_key`` the front end and its
    parameters (`placerec.recognizer.DescribingRecognizer.frontend_key`). A corrupt entry is recomputed.
    With ``root=None`` the cache is off.
    """

    def __init__(self, root: str | Path | None, data_key: str) -> None:
        self.root = None if root is None else Path(root) / data_key
        self.hits = 0
        self.misses = 0

    def _path(self, frontend_key: str, index: int) -> Path:
        assert self.root is not None
        return self.root / frontend_key / f"{index:06d}.npz"

    def get(self, frontend_key: str, index: int) -> Description | None:
        if self.root is None:
            return None
        path = self._path(frontend_key, index)
        if not path.is_file():
            self.misses += 1
            return None
        try:
            arrays, _ = load_artifact(path, _KIND, (_VERSION,))
        except ArtifactError as exc:
            log.warning("ignoring unreadable cache entry: %s", exc)
            self.misses += 1
            return None
        self.hits += 1
        return arrays

    def put(self, frontend_key: str, index: int, description: Description) -> None:
        if self.root is None:
            return
        arrays = {k: np.asarray(v) for k, v in description.items()}
        save_artifact(self._path(frontend_key, index), _KIND, _VERSION, arrays, {"frontend": frontend_key})
