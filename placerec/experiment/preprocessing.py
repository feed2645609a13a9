"""A sequence's scans preprocessed as an experiment config's ``preprocess`` section says (`placerec.preprocess`)."""

from __future__ import annotations

import time

from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.types import Scan, Sequence

__all__ = ["preprocessed_scan"]


def preprocessed_scan(seq: Sequence, index: int, cfg: PreprocessParams) -> tuple[Scan, float]:
    """Scan ``index`` of ``seq`` preprocessed as ``cfg`` says (organised scans kept organised), and the
    milliseconds reading and preprocessing took."""
    t0 = time.perf_counter()
    scan = preprocess_scan(seq[index], cfg, keep_organized=True)
    return scan, (time.perf_counter() - t0) * 1e3
