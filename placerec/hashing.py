"""Short stable hashes of JSON-serialisable configuration, used to key caches and artifacts."""

from __future__ import annotations

import hashlib
import json
from typing import Any

__all__ = ["stable_hash"]


def stable_hash(obj: Any) -> str:
    """The first 12 hex digits of the SHA-1 of ``obj`` as sorted-key JSON (non-JSON values via ``str``)."""
    blob = json.dumps(obj, sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:12]
