"""Retrieval back ends: databases that store image/scan descriptions and return the most similar places.

* `placerec.retrieval.hbst` — HBST (Hamming binary search tree) for binary local descriptors (ORB, BRISK).
* `placerec.retrieval.bits` — popcount and bit-layout helpers for packed binary descriptors.

Import from the submodules; the names below are re-exported lazily so importing this package costs nothing.
"""

from __future__ import annotations

from typing import Any

__all__ = ["HBST", "HBSTParams", "HBSTResult", "ImageScores"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from placerec.retrieval import hbst

        return getattr(hbst, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
