"""Intensity calibration: the unsupervised per-beam calibration of Levinson & Thrun used by the ISHOT paper.

::

    from placerec.calibration import CalibrationParams, calibrate_sequence, load_calibration
    table = calibrate_sequence(seq, CalibrationParams(max_range=30.0))   # seq: poses + per-point rings
    table.save("vlp16_calibration.npz")
    scan = load_calibration("vlp16_calibration.npz").apply(scan)        # intensity in [0, 1], NaN beyond 30 m

See docs/calibration.md for the model, the gauge and the verification on the simulator.
"""

from __future__ import annotations

from placerec.calibration.calibrate import (
    calibrate_observations,
    calibrate_points,
    calibrate_sequence,
    default_saturation,
)
from placerec.calibration.levinson import LevinsonFit, fit_levinson
from placerec.calibration.observations import (
    Observations,
    RawBinning,
    RegisteredPoints,
    collect_observations,
    gather_points,
    group_observations,
    incidence_cosine,
    observations_from_points,
    restrict_observations,
)
from placerec.calibration.params import CalibrationParams
from placerec.calibration.table import CalibrationTable, load_calibration

__all__ = [
    "CalibrationParams",
    "CalibrationTable",
    "LevinsonFit",
    "Observations",
    "RawBinning",
    "RegisteredPoints",
    "calibrate_observations",
    "calibrate_points",
    "calibrate_sequence",
    "collect_observations",
    "default_saturation",
    "fit_levinson",
    "gather_points",
    "group_observations",
    "incidence_cosine",
    "load_calibration",
    "observations_from_points",
    "restrict_observations",
]
