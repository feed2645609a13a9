"""Atomic, versioned artifact files: write to a temporary file in the same folder, fsync, rename.

Artifacts (databases, vocabularies, calibration tables, caches) are ``.npz`` archives holding a JSON header under
the key ``__header__`` with ``kind``, ``format_version`` and free metadata (e.g. the config that made them).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from placerec.errors import ArtifactError

__all__ = ["atomic_write", "save_artifact", "load_artifact"]


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "wb") -> Iterator[BinaryIO]:
    """Open a temporary file beside ``path``; on success fsync it and rename it over ``path``.

    If the body raises, the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def save_artifact(
    path: str | Path,
    kind: str,
    format_version: int,
    arrays: dict[str, np.ndarray],
    meta: dict[str, Any] | None = None,
) -> None:
    """Write ``arrays`` and a JSON header atomically as an uncompressed ``.npz``."""
    header = {"kind": kind, "format_version": int(format_version), "meta": meta or {}}
    if "__header__" in arrays:
        raise ArtifactError("array name '__header__' is reserved")
    buf = io.BytesIO()
    payload = dict(arrays)
    payload["__header__"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    np.savez(buf, **payload)
    with atomic_write(path) as fh:
        fh.write(buf.getbuffer())


def load_artifact(
    path: str | Path, kind: str, supported_versions: tuple[int, ...]
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read an artifact written by `save_artifact`; checks kind and version. Returns (arrays, header)."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such artifact file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if "__header__" not in z.files:
                raise ArtifactError(f"{path}: not a placerec artifact (no header)")
            header = json.loads(bytes(z["__header__"]).decode("utf-8"))
            arrays = {k: z[k] for k in z.files if k != "__header__"}
    except ArtifactError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as exc:
        raise ArtifactError(f"{path}: corrupt artifact ({exc})") from exc
    if header.get("kind") != kind:
        raise ArtifactError(f"{path}: artifact is a {header.get('kind')!r}, expected a {kind!r}")
    if header.get("format_version") not in supported_versions:
        raise ArtifactError(
            f"{path}: {kind} format version {header.get('format_version')} is not supported "
            f"(this placerec reads {list(supported_versions)})"
        )
    return arrays, header
