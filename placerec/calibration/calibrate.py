"""Calibrating a sensor: registered scans -> observations -> EM (`placerec.calibration.levinson`) -> table."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from placerec.calibration.levinson import fit_levinson
from placerec.calibration.observations import (
    Observations,
    RegisteredPoints,
    gather_points,
    observations_from_points,
    restrict_observations,
)
from placerec.calibration.params import CalibrationParams
from placerec.calibration.table import CalibrationTable
from placerec.intensity import default_intensity_spec
from placerec.types import Sequence

log = logging.getLogger(__name__)

__all__ = ["calibrate_observations", "calibrate_points", "calibrate_sequence", "default_saturation"]


def default_saturation(obs: Observations, sensor: str = "unknown") -> float:
    """Raw value mapped to 1: the sensor's linear default (`placerec.intensity.SENSOR_INTENSITY_DEFAULTS`: VLP-16
    100 as in the ISHOT paper, KITTI 1.0), else the 99th percentile of the observed raw values."""
    spec = default_intensity_spec(sensor)
    if spec.mode == "linear" and spec.saturation:
        return float(spec.saturation)
    cdf = np.cumsum(np.bincount(obs.raw_bin, obs.count, obs.binning.n)) / max(obs.n_obs, 1)
    return float(max(int(np.searchsorted(cdf, 0.99)), 1) * obs.binning.step)


def calibrate_observations(
    obs: Observations, params: CalibrationParams | None = None, sensor: str = "unknown"
) -> CalibrationTable:
    """Fit the EM on grouped observations and build the [0, 1] table.

    Raw values above the saturation (``params.saturation`` or `default_saturation`) map to 1 (VLP-16: raw > 100
    are retro-reflectors, ISHOT paper Sec. III-A); the rest are divided by it. Only raw values up to
    ``params.fit_range`` times the saturation (and below the sensor's maximum) take part in the fit.
    """
    from placerec._version import __version__

    p = params or CalibrationParams()
    sat = p.saturation or default_saturation(obs, sensor)
    step = obs.binning.step
    top = int(np.floor(sat / step + 1e-9))
    # the fit sees raw values a little beyond the saturation (else the curves of bright beams are censored near
    # it), never the last bin (saturated readings)
    fit_top = min(int(np.floor(p.fit_range * sat / step + 1e-9)), obs.binning.n - 2)
    fit_obs = restrict_observations(obs, fit_top, p.min_beams)
    fit = fit_levinson(fit_obs, p)
    values = np.clip(fit.mapping * step / sat, 0.0, 1.0).astype(np.float32)
    values[:, top + 1 :] = 1.0  # beyond the saturation (VLP-16: retro-reflective returns) -> 1
    log.info("calibrated %d beams of %s on %d cells (%d observations)", obs.n_beams, sensor, fit_obs.n_cells,
             fit_obs.n_obs)  # fmt: skip
    meta = {
        "params": p.model_dump(mode="json"),
        "saturation": float(sat),
        "gauge": "mean response over beams = identity" if p.gauge == "mean" else f"beam {p.gauge} = identity",
        "estimate": p.estimate,
        "em_iterations": len(fit.likelihood),
        "log_likelihood": round(fit.likelihood[-1], 6),
        "outlier_fraction": round(fit.outliers, 5),
        "n_cells": fit_obs.n_cells,
        "n_observations": fit_obs.n_obs,
        "n_points": obs.n_points,
        "placerec_version": __version__,
    }
    return CalibrationTable(
        values, raw_step=step, sensor=sensor, max_range=p.max_range, counts=fit.counts, meta=meta
    )


def calibrate_points(pts: RegisteredPoints, params: CalibrationParams | None = None) -> CalibrationTable:
    """Calibrate from already gathered registered points (see `gather_points`)."""
    p = params or CalibrationParams()
    obs = observations_from_points(pts, p)
    table = calibrate_observations(obs, p, pts.sensor)
    table.meta["sequence"] = pts.name
    return table


def calibrate_sequence(
    seq: Sequence,
    params: CalibrationParams | None = None,
    on_scan: Callable[[int, int], None] | None = None,
) -> CalibrationTable:
    """Calibrate the intensity of ``seq``'s sensor from its registered scans (poses and per-point rings needed).

    ``placerec calibrate`` runs it (`placerec.artifacts.calibration.build_calibration`); ``on_scan(done, total)``
    reports progress while scans are read.
    """
    p = params or CalibrationParams()
    return calibrate_points(gather_points(seq, p, on_scan), p)
