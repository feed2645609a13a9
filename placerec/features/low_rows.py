"""Images with few rows (16- and 32-beam sensors) and images that yield too few features.

A VLP-16 intensity image has 16 rows: ORB's Table I settings (``edge_threshold`` 15, a 31 px patch) leave no
row where a keypoint fits, so it gives no feature at all, and retrieval then finds nothing. Before extraction the
rows of an image lower than `LOW_ROWS` are interpolated linearly (``cv2.resize``) by the smallest integer factor
that makes it at least `UPSAMPLED_ROWS` tall (x8 for 16 rows: nearly square pixels for a VLP-16's 2 deg rows and
0.2 deg columns; x4 for 32 rows); keypoints are mapped back to the original rows. Images of 64 rows and more (the
VPR paper's sensors) are used as they are. The measurement behind the choice (feature counts and retrieval on
simulated VLP-16 sequences, against smaller detector patches and other factors) is in docs/intensity_images.md
(tools/eval_low_rows.py).
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

__all__ = [
    "LOW_ROWS",
    "UPSAMPLED_ROWS",
    "FEW_FEATURES",
    "row_factor",
    "upsample_rows",
    "rows_back",
    "warn_few_features",
]

log = logging.getLogger("placerec.features")

#: images with fewer rows are upsampled ...
LOW_ROWS = 64
#: ... to at least this many rows, by the smallest integer factor that reaches it
UPSAMPLED_ROWS = 128
#: an image giving fewer features than this is reported once per extractor (a logging warning)
FEW_FEATURES = 20


def row_factor(height: int, setting: int | None) -> int:
    """The row upsampling factor for an image ``height`` rows tall: ``setting`` when given (1 = off), else 1 from
    `LOW_ROWS` rows up and below that the smallest integer that makes it at least `UPSAMPLED_ROWS` rows tall."""
    if setting is not None:
        return int(setting)
    if height >= LOW_ROWS:
        return 1
    return math.ceil(UPSAMPLED_ROWS / max(height, 1))


def upsample_rows(image: np.ndarray, mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """The image with ``factor`` times as many rows (linear interpolation) and its mask (nearest row)."""
    h, w = image.shape
    up = cv2.resize(image, (w, h * factor), interpolation=cv2.INTER_LINEAR)
    up_mask = np.repeat(mask, factor, axis=0)
    return up, up_mask


def rows_back(v: np.ndarray, factor: int) -> np.ndarray:
    """Row coordinates in the upsampled image -> rows of the original (pixel centres at integers in both)."""
    if factor == 1:
        return v
    return (v + 0.5) / factor - 0.5


def warn_few_features(owner: object, name: str, n: int, shape: tuple[int, int], nfeatures: int) -> None:
    """Log a warning, once per ``owner`` (an extractor), when an image gave fewer than `FEW_FEATURES` features."""
    if n >= min(FEW_FEATURES, nfeatures) or getattr(owner, "_warned_few_features", False):
        return
    owner._warned_few_features = True  # type: ignore[attr-defined]
    log.warning(
        "features.%s: only %d features in a %d x %d intensity image (a blank image, or too few rows or too little "
        "texture for the detector settings); place recognition on such images finds few or no matches. "
        "This is reported once per extractor.",
        name,
        n,
        shape[0],
        shape[1],
    )
