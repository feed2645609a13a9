"""The experiment config's ``preprocess`` section as the parameters of `placerec.preprocess.preprocess_scan`."""

from __future__ import annotations

import time

from placerec.config import PreprocessConfig
from placerec.intensity import IntensitySpec
from placerec.preprocess import PreprocessParams, preprocess_scan
from placerec.types import Scan, Sequence

__all__ = ["preprocess_params", "preprocessed_scan"]


def preprocess_params(cfg: PreprocessConfig) -> PreprocessParams:
    """`PreprocessParams` for a validated config section (intensity mode ``auto``: the sensor's default)."""
    ic = cfg.intensity
    spec = (
        None if ic.mode == "auto" else IntensitySpec(**ic.model_dump(include=set(IntensitySpec.model_fields)))
    )
    return PreprocessParams(
        **cfg.model_dump(exclude={"intensity"}), intensity=spec, calibration=ic.calibration
    )


def preprocessed_scan(seq: Sequence, index: int, cfg: PreprocessConfig) -> tuple[Scan, float]:
    """Scan ``index`` of ``seq`` preprocessed as ``cfg`` says (organised scans kept organised), and the
    milliseconds reading and preprocessing took."""
    t0 = time.perf_counter()
    scan = preprocess_scan(seq[index], preprocess_params(cfg), keep_organized=True)
    return scan, (time.perf_counter() - t0) * 1e3
