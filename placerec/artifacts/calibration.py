"""The intensity calibration table (kind ``intensity-calibration``): registered scans of one sensor through
`placerec.calibration.calibrate_sequence`, saved as a `placerec.calibration.CalibrationTable`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pydantic import Field

from placerec.artifacts.sources import FilePath, SequenceSource
from placerec.calibration import CalibrationParams, calibrate_sequence
from placerec.params import Params

__all__ = ["CalibrationBuild", "build_calibration"]


class CalibrationBuild(Params):
    """What ``placerec calibrate`` builds: the table of ``source``'s sensor (poses and rings needed; a simulated
    world gives its whole route), calibrated with ``params``, written to ``out``."""

    source: SequenceSource
    out: FilePath
    params: CalibrationParams = Field(default_factory=CalibrationParams)


def build_calibration(config: CalibrationBuild, progress: Callable[[int, int], None] | None = None) -> Path:
    """Calibrate and write the table (atomically); returns its path. ``progress(done, total)`` counts the scans
    read."""
    seq = config.source.route()
    calibrate_sequence(seq, config.params, progress).save(config.out)
    return config.out
