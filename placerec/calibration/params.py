"""`CalibrationParams`: every setting of the intensity calibration, validated (`placerec.params.Params`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from placerec.params import Params

__all__ = ["CalibrationParams"]


class CalibrationParams(Params):
    """Settings of `placerec.calibration.calibrate_sequence` (see docs/calibration.md for the choices).

    Data: points within ``[min_range, max_range]`` (the intensity cut-off, 30 m: ISHOT paper) of every ``step``-th
    scan; map cells of ``voxel_size`` split by ``range_band``; only points seen within ``arccos(min_cos_incidence)``
    of their surface normal, compared under a ``cos ** lambert_exponent`` factor in ``incidence_bins`` bins.
    Model: ``levels`` latent reflectivities, response curves smoothed over ``smoothing`` levels, EM for at most
    ``iterations`` or until the log-likelihood per observation gains less than ``tolerance``. Table: ``estimate``
    per (beam, raw) (``ml``: the inverse response curve, i.e. the maximum-likelihood reflectivity of one reading;
    ``mean``: posterior mean; ``map``: posterior mode), entries with fewer than ``min_count`` observations
    interpolated, scale fixed by ``gauge``, raw ``saturation`` mapped to 1.
    """

    voxel_size: float = Field(0.25, gt=0, description="map cell size (m) in the world frame")
    min_range: float = Field(1.0, ge=0, description="ignore points closer than this (near-field)")
    max_range: float | None = Field(
        30.0, gt=0, description="intensity range cut-off (m), also used by apply()"
    )
    range_band: float | None = Field(
        1.3, gt=1, description="compare beams only at ranges within this factor (None: at any range)"
    )
    min_cos_incidence: float | None = Field(
        0.5,
        ge=0,
        le=1,
        description="only points seen within arccos(this) of their surface normal (None: all)",
    )
    normal_cell: float = Field(0.5, gt=0, description="map cell size (m) for surface normals")
    incidence_bins: int = Field(
        6, ge=1, description="incidence-angle bins of the EM (1: incidence not modelled)"
    )
    lambert_exponent: float | None = Field(
        1.0, ge=0, description="reflectivity factor cos^k per incidence bin (None: incidence not modelled)"
    )
    min_beams: int = Field(2, ge=2, description="a cell must be seen by this many different beams")
    raw_bins: int | None = Field(
        None, ge=2, description="raw bins (None: one per value for 8-bit data, else 256)"
    )
    saturation: float | None = Field(
        None, gt=0, description="raw value mapped to 1 (None: 100 for 8-bit data, else the 99th percentile)"
    )
    fit_range: float = Field(1.5, ge=1, description="fit raw values up to this multiple of the saturation")
    levels: int = Field(128, ge=8, le=1024, description="latent reflectivity levels")
    smoothing: float = Field(
        2.0, ge=0, description="kernel width (levels, per 128) of the response-curve M-step"
    )
    iterations: int = Field(100, ge=1, description="maximum EM iterations")
    tolerance: float = Field(
        1e-5, ge=0, description="stop when the log-likelihood per observation gains less"
    )
    estimate: Literal["ml", "mean", "map"] = "ml"
    min_count: int = Field(
        5, ge=1, description="observations a (beam, raw) entry needs; others are interpolated"
    )
    gauge: Literal["mean"] | int = Field(
        "mean", description="'mean' (average beam = identity) or a beam index"
    )
    step: int = Field(1, ge=1, description="use every step-th scan")
    max_scans: int | None = Field(None, ge=1)
