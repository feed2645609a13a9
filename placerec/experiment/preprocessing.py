"""A sequence's scans preprocessed as an experiment config's ``preprocess`` section says (`placerec.preprocess`)."""

from __future__ import annotations

import time

from placerec.keyframes import KeyframeSequence
from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.types import Scan, Sequence

__all__ = ["preprocessed_scan"]


def preprocessed_scan(seq: Sequence, index: int, cfg: PreprocessParams) -> tuple[Scan, float]:
    """Scan ``index`` of ``seq`` preprocessed as ``cfg`` says (organised scans kept organised), and the
    milliseconds reading and preprocessing took. A `KeyframeSequence` that prepares its source scans (the
    experiment's, `placerec.experiment.datasets.keyframed`) gives its keyframe as it is: its scans were
    preprocessed one by one before they were accumulated, and the time is that of building the keyframe."""
    t0 = time.perf_counter()
    if isinstance(seq, KeyframeSequence) and seq.prepare is not None:
        scan = seq[index]
    else:
        scan = preprocess_scan(seq[index], cfg, keep_organized=True)
    return scan, (time.perf_counter() - t0) * 1e3
