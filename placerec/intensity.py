"""Intensity normalisation: raw sensor intensity mapped to [0, 1], with a default per sensor.

`IntensitySpec` says how (`INTENSITY_NORMALIZERS`); `default_intensity_spec` gives a sensor's default. Per-beam
calibration tables (`placerec.calibration`) replace this mapping when a sensor has been calibrated.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from placerec.params import Params
from placerec.types import Scan

__all__ = [
    "IntensitySpec",
    "INTENSITY_NORMALIZERS",
    "SENSOR_INTENSITY_DEFAULTS",
    "default_intensity_spec",
    "normalize_intensity",
]


class IntensitySpec(Params):
    """How to map raw intensity to [0, 1]: ``mode`` is a key of `INTENSITY_NORMALIZERS`.

    ``saturation``: raw value mapped to 1 by ``linear`` (values above are clipped); ``percentile``: the
    percentile of the scan's own intensities mapped to 1 by ``percentile``.
    """

    mode: Literal["raw", "linear", "percentile"] = Field("raw", description="raw, linear or percentile")
    saturation: float | None = Field(None, gt=0, description="raw value mapped to 1 (mode linear)")
    percentile: float = Field(99.0, gt=0, le=100, description="percentile mapped to 1 (mode percentile)")

    @model_validator(mode="after")
    def _saturation_for_linear(self) -> IntensitySpec:
        if self.mode == "linear" and self.saturation is None:
            raise ValueError("mode 'linear' needs a 'saturation' value")
        return self


def _raw(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    return values


def _linear(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    return np.clip(values / np.float32(spec.saturation), 0.0, 1.0).astype(np.float32)


def _percentile(values: np.ndarray, spec: IntensitySpec) -> np.ndarray:
    if values.size == 0:
        return values
    top = float(np.percentile(values, spec.percentile))
    if top <= 0:
        return np.zeros_like(values)
    return np.clip(values / np.float32(top), 0.0, 1.0).astype(np.float32)


INTENSITY_NORMALIZERS: dict[str, Callable[[np.ndarray, IntensitySpec], np.ndarray]] = {
    "raw": _raw,
    "linear": _linear,
    "percentile": _percentile,
}

#: Defaults per sensor name (prefix match on `SensorInfo.name`). VLP-16: the ISHOT paper maps raw >= 100 to 1.
#: KITTI's HDL-64 reflectance is already in [0, 1]. Ouster 16-bit reflectivity and 8-bit Velodyne HDL sensors
#: are scaled by a high percentile of each scan, which is robust to retro-reflector outliers.
SENSOR_INTENSITY_DEFAULTS: dict[str, IntensitySpec] = {
    "vlp16": IntensitySpec(mode="linear", saturation=100.0),
    "hdl64": IntensitySpec(mode="percentile", percentile=99.0),
    "hdl32": IntensitySpec(mode="percentile", percentile=99.0),
    "kitti": IntensitySpec(mode="linear", saturation=1.0),
    "os": IntensitySpec(mode="percentile", percentile=99.0),
}


def default_intensity_spec(sensor_name: str) -> IntensitySpec:
    """The per-sensor default (`SENSOR_INTENSITY_DEFAULTS`), ``percentile`` 99 for unknown sensors."""
    name = sensor_name.lower()
    for prefix, spec in SENSOR_INTENSITY_DEFAULTS.items():
        if name.startswith(prefix):
            return spec
    return IntensitySpec(mode="percentile", percentile=99.0)


def normalize_intensity(scan: Scan, spec: IntensitySpec | None = None) -> Scan:
    """Map the scan's intensity to [0, 1] with ``spec`` (default: the sensor's default spec)."""
    spec = spec or default_intensity_spec(scan.sensor.name)
    return scan.with_intensity(INTENSITY_NORMALIZERS[spec.mode](scan.intensity, spec))
