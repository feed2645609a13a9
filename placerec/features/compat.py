"""OpenCV version differences for the 2D feature back ends.

* BRISK: ``cv2.BRISK_create`` in OpenCV 4, ``cv2.xfeatures2d.BRISK_create`` in OpenCV 5 (contrib).
* SURF: ``cv2.xfeatures2d.SURF_create`` exists in contrib wheels but raises (patented, not built): placerec
  uses its own NumPy SURF (`placerec.features.surf`) everywhere.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from placerec.errors import DependencyError

__all__ = ["brisk_create", "fast_create", "keypoint_xy", "orb_create", "orb_score_type"]


def brisk_create(threshold: int = 30, octaves: int = 3, pattern_scale: float = 1.0) -> Any:
    """A ``cv2.BRISK`` from whichever module this OpenCV build has it in."""
    for owner in (cv2, getattr(cv2, "xfeatures2d", None)):
        factory = getattr(owner, "BRISK_create", None) if owner is not None else None
        if factory is not None:
            return factory(int(threshold), int(octaves), float(pattern_scale))
    raise DependencyError(
        f"OpenCV {cv2.__version__} has no BRISK (neither cv2.BRISK_create nor cv2.xfeatures2d.BRISK_create); "
        "install opencv-contrib-python-headless"
    )


def fast_create(threshold: int = 40, nonmax_suppression: bool = True) -> Any:
    """FAST-9/16 corner detector (``cv2.FastFeatureDetector``)."""
    return cv2.FastFeatureDetector_create(  # type: ignore[attr-defined]  # not in cv2's stubs
        int(threshold), bool(nonmax_suppression), cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
    )


def keypoint_xy(kps: Any) -> np.ndarray:
    """(N, 2) float32 positions of a sequence of ``cv2.KeyPoint`` (``cv2.KeyPoint_convert``)."""
    return cv2.KeyPoint_convert(kps)  # type: ignore[attr-defined]  # not in cv2's stubs


def orb_score_type(name: str) -> int:
    """OpenCV's constant for ORB's ranking score, ``"harris"`` or ``"fast"``."""
    const = {"harris": "ORB_HARRIS_SCORE", "fast": "ORB_FAST_SCORE"}[name]
    value = getattr(cv2, const, None)
    if value is None:  # very old bindings spell it as a class attribute
        value = getattr(cv2.ORB, const.split("_", 1)[1])
    return int(value)


def orb_create(
    nfeatures: int,
    scale_factor: float,
    n_levels: int,
    edge_threshold: int,
    first_level: int,
    wta_k: int,
    score_type: str,
    patch_size: int,
    fast_threshold: int,
) -> Any:
    """``cv2.ORB`` with named arguments (the positional order is the same in OpenCV 4 and 5)."""
    return cv2.ORB_create(  # type: ignore[attr-defined]  # not in cv2's stubs
        int(nfeatures),
        float(scale_factor),
        int(n_levels),
        int(edge_threshold),
        int(first_level),
        int(wta_k),
        orb_score_type(score_type),
        int(patch_size),
        int(fast_threshold),
    )
