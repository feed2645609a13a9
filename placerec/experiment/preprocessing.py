"""The experiment config's ``preprocess`` section as the parameters of `placerec.preprocess.preprocess_scan`."""

from __future__ import annotations

from placerec.config import PreprocessConfig
from placerec.intensity import IntensitySpec
from placerec.preprocess import PreprocessParams

__all__ = ["preprocess_params"]


def preprocess_params(cfg: PreprocessConfig) -> PreprocessParams:
    """`PreprocessParams` for a validated config section (intensity mode ``auto``: the sensor's default)."""
    ic = cfg.intensity
    spec = (
        None if ic.mode == "auto" else IntensitySpec(**ic.model_dump(include=set(IntensitySpec.model_fields)))
    )
    return PreprocessParams(
        **cfg.model_dump(exclude={"intensity"}), intensity=spec, calibration=ic.calibration
    )
