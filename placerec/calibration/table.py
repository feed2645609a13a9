"""`CalibrationTable`: a per-beam lookup from raw intensity to calibrated reflectance in [0, 1].

Raw intensities are binned with a fixed step (``raw_step``; 1 for 8-bit Velodyne data, so bin ``a`` is raw value
``a``); ``values[b, a]`` is the calibrated intensity of beam ``b`` for raw bin ``a``, already rescaled to [0, 1]
(ISHOT paper, Sec. III-A: the saturation value, 100 for a VLP-16, maps to 1). Raw values between bin centres are
interpolated linearly, values beyond the last bin use the last bin.

Points farther than ``max_range`` (the intensity cut-off, 30 m by default) get NaN: their intensity is
unreliable (ISHOT paper, Fig. 2), and NaN is what `placerec.preprocess.remove_invalid` already drops.
The table is saved as a versioned artifact (`placerec.io.atomic.save_artifact`, kind ``intensity-calibration``).
"""

from __future__ import annotations

import functools
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from placerec.errors import ArtifactError, ScanDataError, short_repr
from placerec.io.artifact_schema import Member
from placerec.types import Scan

log = logging.getLogger(__name__)

__all__ = ["CalibrationTable", "load_calibration", "KIND", "FORMAT_VERSION"]

KIND = "intensity-calibration"
FORMAT_VERSION = 1
_SCHEMA = {
    "values": Member("f", ("n_beams", "n_raw"), finite=True),
    "counts": Member("iu", ("n_beams", "n_raw"), min_value=0),
}


@dataclass(frozen=True, eq=False)
class CalibrationTable:
    """Per-beam lookup ``values`` (n_beams, n_raw) float32 in [0, 1] over raw bins of width ``raw_step``.

    ``counts`` (n_beams, n_raw) holds the observations behind each entry (0: filled by interpolation);
    ``sensor`` is the sensor name the table was made for; ``max_range`` the intensity cut-off in metres (None:
    none); ``meta`` the parameters and statistics of the calibration run (saved with the table).
    """

    values: np.ndarray
    raw_step: float = 1.0
    sensor: str = "unknown"
    max_range: float | None = 30.0
    counts: np.ndarray | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.values, dtype=np.float32)
        if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 2:
            raise ScanDataError(f"calibration values must have shape (n_beams, n_raw >= 2), got {v.shape}")
        if not np.all(np.isfinite(v)) or v.min() < 0.0 or v.max() > 1.0:
            raise ScanDataError("calibration values must be finite and in [0, 1]")
        if not self.raw_step > 0:
            raise ScanDataError(f"calibration raw_step must be positive, got {self.raw_step}")
        object.__setattr__(self, "values", v)
        if self.counts is None:
            object.__setattr__(self, "counts", np.zeros(v.shape, dtype=np.int64))
        else:
            c = np.ascontiguousarray(self.counts, dtype=np.int64)
            if c.shape != v.shape:
                raise ScanDataError(f"calibration counts have shape {c.shape}, values {v.shape}")
            object.__setattr__(self, "counts", c)

    @property
    def n_beams(self) -> int:
        return int(self.values.shape[0])

    @property
    def n_raw(self) -> int:
        return int(self.values.shape[1])

    @property
    def raw_values(self) -> np.ndarray:
        """The raw intensity at the centre of each bin, (n_raw,) float64."""
        return np.arange(self.n_raw) * float(self.raw_step)

    def lookup(self, raw: np.ndarray, beam: np.ndarray) -> np.ndarray:
        """Calibrated intensity (float32, [0, 1]) of raw values ``raw`` measured by beams ``beam``."""
        raw = np.asarray(raw, dtype=np.float64)
        beam = np.asarray(beam, dtype=np.int64)
        if beam.size and (beam.min() < 0 or beam.max() >= self.n_beams):
            raise ScanDataError(
                f"ring index {int(beam.min() if beam.min() < 0 else beam.max())} outside the calibration "
                f"table's {self.n_beams} beams"
            )
        pos = np.clip(np.nan_to_num(raw / self.raw_step, nan=0.0), 0.0, self.n_raw - 1)
        lo = np.minimum(pos.astype(np.int64), self.n_raw - 2)
        frac = (pos - lo).astype(np.float32)
        flat = self.values.reshape(-1)
        base = beam * self.n_raw + lo
        return flat[base] * (1.0 - frac) + flat[base + 1] * frac

    def apply(
        self,
        scan: Scan,
        max_range: float | None | Literal["table"] = "table",
        beyond: Literal["nan", "zero", "drop"] = "nan",
    ) -> Scan:
        """The scan with its raw intensity mapped through its beams' tables (rescaled to [0, 1]).

        ``max_range``: the intensity cut-off ("table": the table's own; None: none). Points beyond it get NaN
        (``beyond="nan"``), 0 (``"zero"``) or are removed (``"drop"``). Zero-range points of organised scans (no
        return) keep intensity 0. Raises `ScanDataError` if the scan has no ring or its sensor has another number
        of beams than the table.
        """
        where = scan.source or "scan"
        if scan.ring is None:
            raise ScanDataError(f"{where}: intensity calibration needs per-point ring (beam) indices")
        n_sensor = scan.sensor.n_beams
        if n_sensor is not None and n_sensor != self.n_beams:
            raise ScanDataError(
                f"{where}: sensor {scan.sensor.name!r} has {n_sensor} beams, the calibration table "
                f"(made for {self.sensor!r}) has {self.n_beams}"
            )
        if scan.sensor.name not in ("unknown", self.sensor):
            log.warning(
                "%s: calibration table made for %r applied to sensor %r", where, self.sensor, scan.sensor.name
            )
        try:
            out = self.lookup(scan.intensity, scan.ring)
        except ScanDataError as exc:
            raise ScanDataError(f"{where}: {exc}") from None
        limit = self.max_range if max_range == "table" else max_range
        far = None
        if limit is not None:
            far = scan.ranges > np.float32(limit)
        if scan.shape is not None:
            out = np.where(np.any(scan.xyz != 0.0, axis=1), out, np.float32(0.0))
        if far is None or not far.any():
            return scan.with_intensity(out)
        if beyond == "drop":
            return scan.with_intensity(out).select(~far)
        if beyond not in ("nan", "zero"):
            raise ScanDataError(f"beyond must be 'nan', 'zero' or 'drop', got {beyond!r}")
        fill = np.float32(np.nan if beyond == "nan" else 0.0)
        return scan.with_intensity(np.where(far, fill, out).astype(np.float32))

    def header_meta(self) -> dict[str, Any]:
        return {
            "sensor": self.sensor,
            "n_beams": self.n_beams,
            "n_raw": self.n_raw,
            "raw_step": float(self.raw_step),
            "max_range": None if self.max_range is None else float(self.max_range),
            **{
                k: v
                for k, v in self.meta.items()
                if k not in {"sensor", "n_beams", "n_raw", "raw_step", "max_range"}
            },
        }

    def save(self, path: str | Path) -> None:
        """Write the table atomically (kind ``intensity-calibration``, format version 1)."""
        from placerec.io.atomic import save_artifact

        assert self.counts is not None  # set by __post_init__
        save_artifact(
            path, KIND, FORMAT_VERSION, {"values": self.values, "counts": self.counts}, self.header_meta()
        )
        log.info("wrote %s (%d beams x %d raw bins, sensor %s)", path, self.n_beams, self.n_raw, self.sensor)

    @classmethod
    def load(cls, path: str | Path) -> CalibrationTable:
        """Read a table written by `save`; `ArtifactError` naming the file and key on any inconsistency."""
        from placerec.io.atomic import load_artifact

        arrays, header = load_artifact(path, KIND, (FORMAT_VERSION,), _SCHEMA)
        meta = dict(header["meta"])
        for key in ("sensor", "n_beams", "n_raw", "raw_step"):
            if key not in meta:
                raise ArtifactError(f"{path}: calibration header has no key {key!r}")
        shape = arrays["values"].shape
        if (meta["n_beams"], meta["n_raw"]) != shape:
            raise ArtifactError(
                f"{path}: 'values' has shape {shape}, the header says n_beams={short_repr(meta['n_beams'])}, "
                f"n_raw={short_repr(meta['n_raw'])}"
            )
        if not isinstance(meta["sensor"], str):
            raise ArtifactError(
                f"{path}: calibration header 'sensor' must be a string, got {short_repr(meta['sensor'])}"
            )
        for key, value in (("raw_step", meta["raw_step"]), ("max_range", meta.get("max_range"))):
            if not (value is None and key == "max_range") and not _positive_number(value):
                raise ArtifactError(
                    f"{path}: calibration header {key!r} must be a positive number, got {short_repr(value)}"
                )
        try:
            return cls(
                values=arrays["values"],
                raw_step=float(meta.pop("raw_step")),
                sensor=meta.pop("sensor"),
                max_range=meta.pop("max_range", None),
                counts=arrays["counts"],
                meta={k: v for k, v in meta.items() if k not in ("n_beams", "n_raw")},
            )
        except ScanDataError as exc:
            raise ArtifactError(f"{path}: invalid calibration table ({exc})") from None


def _positive_number(value: object) -> bool:
    return (
        isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    )


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int, size: int) -> CalibrationTable:
    return CalibrationTable.load(path)


def load_calibration(path: str | Path) -> CalibrationTable:
    """`CalibrationTable.load` with a cache keyed on the file's path, size and modification time."""
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError:
        raise ArtifactError(f"{p}: no such calibration table") from None
    return _load_cached(str(p.resolve()), st.st_mtime_ns, st.st_size)
