"""Caps on how many bytes one file may make placerec read or allocate, checked before reading.

Every file is checked from what it *declares* (its size on disk, a zip member's uncompressed size, a ``.npy``
header's shape x itemsize, a PCD/PLY point count, a vocabulary's array table), so a zip bomb, a lying header or a
sparse file gives a placerec error instead of a `MemoryError` or minutes of decompression. Two caps:

* ``"scan"``: scan, pose and sequence files, `DEFAULT_MAX_SCAN_BYTES` (1 GiB; a 128-beam scan is ~10 MB),
  overridden by the environment variable ``PLACEREC_MAX_SCAN_BYTES``;
* ``"artifact"``: databases, vocabularies, calibration tables, caches, `DEFAULT_MAX_ARTIFACT_BYTES` (4 GiB),
  overridden by ``PLACEREC_MAX_ARTIFACT_BYTES``.

Functions that take a ``limit`` argument use it instead of either.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from placerec.errors import ConfigError, PlacerecError

__all__ = [
    "DEFAULT_MAX_SCAN_BYTES",
    "DEFAULT_MAX_ARTIFACT_BYTES",
    "ENV_VARS",
    "FileClass",
    "max_load_bytes",
    "check_size",
]

DEFAULT_MAX_SCAN_BYTES = 1 << 30
DEFAULT_MAX_ARTIFACT_BYTES = 4 << 30
ENV_VARS = {"scan": "PLACEREC_MAX_SCAN_BYTES", "artifact": "PLACEREC_MAX_ARTIFACT_BYTES"}
_DEFAULTS = {"scan": DEFAULT_MAX_SCAN_BYTES, "artifact": DEFAULT_MAX_ARTIFACT_BYTES}

FileClass = Literal["scan", "artifact"]


def max_load_bytes(cls: FileClass, limit: int | None = None) -> int:
    """``limit`` if given, else the environment variable of ``cls`` (`ENV_VARS`), else its default."""
    if limit is not None:
        return int(limit)
    var = ENV_VARS[cls]
    raw = os.environ.get(var, "").strip()
    if not raw:
        return _DEFAULTS[cls]
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if value <= 0:
        raise ConfigError(f"environment variable {var}={raw[:40]!r} must be a positive number of bytes")
    return value


def check_size(
    nbytes: int,
    where: str | Path,
    what: str,
    error: type[PlacerecError],
    cls: FileClass,
    limit: int | None = None,
) -> int:
    """``nbytes`` if it is within the cap of ``cls``; else ``error`` naming ``where``, what declared the size and
    the cap."""
    cap = max_load_bytes(cls, limit)
    if nbytes > cap:
        hint = "" if limit is not None else f" (set {ENV_VARS[cls]} to raise it)"
        raise error(f"{where}: {what} declares {nbytes} bytes, over the {cls} load cap of {cap} bytes{hint}")
    return nbytes
