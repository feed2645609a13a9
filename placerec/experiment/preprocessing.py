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
        None
        if ic.mode == "auto"
        else IntensitySpec(mode=ic.mode, saturation=ic.saturation, percentile=ic.percentile)
    )
    return PreprocessParams(
        min_range=cfg.min_range,
        max_range=cfg.max_range,
        min_z=cfg.min_z,
        max_z=cfg.max_z,
        voxel_size=cfg.voxel_size,
        intensity=spec,
        calibration=ic.calibration,
    )
