"""2D local features for intensity images: our NumPy SURF and a registry of extractors with the VPR paper's
Table I defaults ("orb", "brisk", "fast-surf", "surf").

Names are resolved lazily, so ``import placerec.features`` costs nothing until a name is used::

    from placerec.features import make_extractor
    feats = make_extractor("orb").extract(image_u8)     # Features: uv, size, angle, response, descriptors
"""

from __future__ import annotations

from placerec._lazy import lazy_exports

__all__ = [
    "SURF",
    "Features",
    "FeatureExtractor",
    "EXTRACTORS",
    "available_extractors",
    "make_extractor",
]

_LAZY = {
    "SURF": "placerec.features.surf",
    "Features": "placerec.features.registry",
    "FeatureExtractor": "placerec.features.registry",
    "EXTRACTORS": "placerec.features.registry",
    "available_extractors": "placerec.features.registry",
    "make_extractor": "placerec.features.registry",
}


__getattr__ = lazy_exports(__name__, _LAZY)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
