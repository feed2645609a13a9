"""`FileSequence`: the lazy `Sequence` over a sorted list of scan files that every folder and dataset loader
builds on, with the two files placerec's simulator writes beside its scans:

* ``sensor.yaml`` in the sequence root (keys name, beam_elevations_deg, columns, intensity_max, min_range,
  max_range): it becomes the `SensorInfo` of every scan. KITTI ``.bin`` files store intensity as a [0, 1]
  reflectance (KITTI's convention, which the simulator's export follows: raw / intensity_max); with a
  ``sensor.yaml`` giving ``intensity_max`` they are multiplied back to the sensor's raw units, so a loaded scan
  has the same intensities as the simulated one;
* per-scan ring files: for a scan ``<dir>/velodyne/000042.bin`` the file ``<dir>/ring/000042.npy`` (an int16
  array, one beam index per point) — in general a folder named ``ring`` beside the scan folder, same stem,
  ``.npy`` — is attached as ``Scan.ring`` when it exists.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ScanDataError, ScanFormatError
from placerec.io._common import read_bytes
from placerec.io.npz import parse_npy
from placerec.io.registry import read_scan
from placerec.safe_yaml import load_yaml
from placerec.types import Scan, SensorInfo, StoredSequenceInfo, check_poses

__all__ = ["FileSequence", "load_sensor_yaml", "read_times"]


def load_sensor_yaml(path: str | Path) -> SensorInfo:
    """Read a ``sensor.yaml`` sensor description (see `SensorInfo.from_dict`)."""
    p, buf = read_bytes(path, "sensor.yaml")
    d = load_yaml(buf, p, ScanFormatError)
    if not isinstance(d, dict):
        raise ScanFormatError(f"{p}: expected a mapping of sensor keys, got {type(d).__name__}")
    try:
        return SensorInfo.from_dict(d)
    except (ScanDataError, TypeError, ValueError) as exc:
        raise ScanFormatError(f"{p}: invalid sensor description ({exc})") from None


def read_times(path: Path, n: int) -> np.ndarray:
    """``n`` timestamps (seconds, one a line) from a ``times.txt``; ScanFormatError for another count, a value
    that is not finite, or one not later than the line before (two scans are never taken at the same time)."""
    p, buf = read_bytes(path, "times.txt")
    try:
        t = np.array(buf.decode("utf-8").split(), dtype=np.float64)
    except (ValueError, UnicodeDecodeError):
        raise ScanFormatError(f"{p}: expected one number (seconds) per line") from None
    if t.size != n:
        raise ScanFormatError(f"{p}: {t.size} timestamps for {n} scans")
    bad = ~np.isfinite(t)
    if bad.any():
        raise ScanFormatError(f"{p}:{int(np.argmax(bad)) + 1}: timestamp {t[bad][0]} is not a finite number")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ScanFormatError(
            f"{p}:{i + 1}: timestamp {float(t[i])!r} s does not come after the previous one ({float(t[i - 1])!r} s); "
            "timestamps must increase strictly"
        )
    return t


class FileSequence(StoredSequenceInfo):
    """A sorted list of scan files with optional poses and timestamps, ``sensor.yaml`` and ``ring/`` files.

    Subclasses set ``_poses`` (through `_set_poses`, which checks the count) and ``_timestamps``, and may
    override `_read_file` to decode a file their own way."""

    def __init__(self, root: Path, files: list[Path], name: str, read_options: dict[str, Any]) -> None:
        if not files:
            raise ScanFormatError(f"{root}: no scan files found")
        self._root = root
        self._files = files
        self._name = name
        self._options = read_options
        self._poses: np.ndarray | None = None
        self._timestamps: np.ndarray | None = None
        yaml_path = root / "sensor.yaml"
        self._sensor = load_sensor_yaml(yaml_path) if yaml_path.is_file() else None
        ring_dir = files[0].parent.parent / "ring"
        self._ring_dir = ring_dir if ring_dir.is_dir() else None

    def _set_poses(self, poses: np.ndarray | None, source: Path | str) -> None:
        if poses is not None and poses.shape[0] != len(self._files):
            raise ScanFormatError(
                f"{source}: {poses.shape[0]} poses for {len(self._files)} scans in {self._root}"
            )
        try:
            self._poses = None if poses is None else check_poses(poses, len(self._files), str(source))
        except ScanDataError as exc:  # the poses came from a file: a file error, naming it (check_poses does)
            raise ScanFormatError(str(exc)) from None

    def __len__(self) -> int:
        return len(self._files)

    def __getitem__(self, index: int) -> Scan:
        path = self._files[index]  # IndexError past the end, as Python sequences do
        scan = self._read_file(path)
        changes: dict[str, Any] = {}
        if self._sensor is not None:
            changes["sensor"] = self._sensor
            if (
                self._sensor.intensity_max
                and self._options.get("format", "kitti") == "kitti"
                and path.suffix == ".bin"
            ):
                changes["intensity"] = scan.intensity * np.float32(self._sensor.intensity_max)
        if self._timestamps is not None:
            changes["timestamp"] = float(self._timestamps[index])
        if self._ring_dir is not None:
            ring_path = self._ring_dir / f"{path.stem}.npy"
            if ring_path.is_file():
                changes["ring"] = self._read_ring(ring_path, len(scan))
        return replace(scan, **changes) if changes else scan

    def _read_file(self, path: Path) -> Scan:
        """One scan file as a `Scan` (here: `read_scan` with the sequence's read options)."""
        return read_scan(path, **self._options)

    @staticmethod
    def _read_ring(path: Path, n: int) -> np.ndarray:
        p, buf = read_bytes(path, "ring .npy")
        ring = parse_npy(buf, p, ScanFormatError)
        if ring.dtype.kind not in "iu" or ring.size != n:
            raise ScanFormatError(
                f"{p}: ring file must hold {n} integers (one per point), got {ring.shape} {ring.dtype}"
            )
        return ring.reshape(-1)

    @property
    def files(self) -> list[Path]:
        return list(self._files)
