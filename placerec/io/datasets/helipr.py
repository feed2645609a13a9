"""HeLiPR (Jung et al., IJRR 2024): ``<root>/LiDAR/<sensor>/<ns>.bin`` and ``<root>/LiDAR_GT/<sensor>_gt.txt``
for the sensors Ouster (OS2-128), Velodyne (VLP-16), Aeva (Aeries II) and Avia (Livox).

Each sensor's ``.bin`` is a packed record per point (HeLiPR file player's layouts):

* Ouster: x, y, z, intensity float32, t uint32, reflectivity, ring, ambient uint16 (26 bytes);
* Velodyne: x, y, z, intensity float32, ring uint16, time float32 (22 bytes);
* Aeva: x, y, z, reflectivity, velocity float32, time offset int32, line index uint8, intensity float32
  (29 bytes; 25 bytes without intensity for scans up to 1691936557946849179 ns, as the file player reads them;
  placerec takes the size that divides the file's, and for a size that both divide, the layout under which the
  points are plausible, refusing the file when that does not decide);
* Avia: x, y, z float32, reflectivity, tag, line uint8, offset time uint32 (19 bytes).

The ground truth ``<sensor>_gt.txt`` has rows ``timestamp_ns x y z qx qy qz qw`` (space-separated): poses of
that LiDAR. A scan is kept when a row lies within ``max_gap`` seconds of its time; positions are shifted so that
the first scan is at the origin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from placerec.errors import ConfigError, ScanFormatError
from placerec.io._common import ascii_digits, check_file, columns_to_scan, guard, structured_columns
from placerec.io.datasets.trajectory import (
    TimedSequence,
    match_nearest,
    pose_from_xyz_quat,
    read_table,
    stamped_files,
)
from placerec.types import Scan, SensorInfo

__all__ = ["HeliprSequence", "detect_helipr", "read_helipr_bin", "HELIPR_RECORDS", "HELIPR_LAYOUT"]

HELIPR_LAYOUT = "<root>/LiDAR/<sensor>/<ns>.bin + <root>/LiDAR_GT/<sensor>_gt.txt"


def _packed(*fields: tuple[str, str]) -> np.dtype:
    return np.dtype([(n, "<" + t) for n, t in fields])


_F = [("x", "f4"), ("y", "f4"), ("z", "f4")]
#: sensor -> (record dtype, intensity field, intensity_max)
HELIPR_RECORDS: dict[str, tuple[np.dtype, str, float | None]] = {
    "Ouster": (
        _packed(
            *_F, ("intensity", "f4"), ("t", "u4"), ("reflectivity", "u2"), ("ring", "u2"), ("ambient", "u2")
        ),
        "intensity",
        None,
    ),
    "Velodyne": (_packed(*_F, ("intensity", "f4"), ("ring", "u2"), ("time", "f4")), "intensity", 255.0),
    "Aeva": (
        _packed(
            *_F,
            ("reflectivity", "f4"),
            ("velocity", "f4"),
            ("time_offset", "i4"),
            ("line", "u1"),
            ("intensity", "f4"),
        ),
        "intensity",
        None,
    ),
    "Avia": (
        _packed(*_F, ("reflectivity", "u1"), ("tag", "u1"), ("line", "u1"), ("offset_time", "u4")),
        "reflectivity",
        255.0,
    ),
}
_AEVA_NO_INTENSITY_UNTIL = 1691936557946849179
_AEVA_OLD = _packed(*_F, ("reflectivity", "f4"), ("velocity", "f4"), ("time_offset", "i4"), ("line", "u1"))


#: Aeva points farther than this (m), or faster (m/s), are not returns: a sign of the wrong record layout.
AEVA_PLAUSIBLE_M = 1000.0
#: Share of an Aeva file's points that must be plausible under a record layout for that layout to be taken.
AEVA_PLAUSIBLE_SHARE = 0.95


def _aeva_plausible(rec: np.ndarray) -> float:
    """Share of the records whose fields are plausible Aeva values: finite x, y, z within `AEVA_PLAUSIBLE_M`,
    finite reflectivity (and intensity), a finite velocity within `AEVA_PLAUSIBLE_M` m/s."""
    if len(rec) == 0:
        return 0.0
    with np.errstate(invalid="ignore", over="ignore"):
        ok = np.ones(len(rec), dtype=bool)
        for c in ("x", "y", "z", "velocity"):
            ok &= np.abs(rec[c]) < AEVA_PLAUSIBLE_M  # False for NaN
        for c in rec.dtype.names or ():
            if rec.dtype[c].kind == "f":
                ok &= np.isfinite(rec[c])
    return float(ok.mean())


def _aeva_records(p: Path) -> tuple[np.ndarray, str]:
    """An Aeva file's records and intensity field. The layout (29-byte records with intensity, or the 25-byte
    records of scans up to ``_AEVA_NO_INTENSITY_UNTIL``) is the one the file size allows; a size that fits both
    (a multiple of 725 bytes) is decided by the content: the layout under which nearly every point is plausible
    (`_aeva_plausible`). The file name's date only names the expected layout in messages."""
    new, old = HELIPR_RECORDS["Aeva"][0], _AEVA_OLD
    size = p.stat().st_size
    fits = [dt for dt in (new, old) if size % dt.itemsize == 0]
    dated_old = ascii_digits(p.stem) and int(p.stem) <= _AEVA_NO_INTENSITY_UNTIL
    expected = f"{old.itemsize} bytes by its date" if dated_old else f"{new.itemsize} bytes by its date"
    if not fits:
        raise ScanFormatError(
            f"{p}: size {size} bytes is a multiple of neither HeLiPR Aeva record size, {new.itemsize} "
            f"({', '.join(new.names or ())}) nor {old.itemsize} (without intensity; {expected})"
        )
    buf = p.read_bytes()
    parsed = {dt.itemsize: np.frombuffer(buf, dtype=dt) for dt in fits}
    if len(fits) == 2:
        share = {k: _aeva_plausible(v) for k, v in parsed.items()}
        good = [k for k, v in share.items() if v >= AEVA_PLAUSIBLE_SHARE]
        if len(good) != 1:
            raise ScanFormatError(
                f"{p}: size {size} bytes fits both HeLiPR Aeva record sizes ({new.itemsize} and {old.itemsize} "
                f"bytes; {expected}) and the content does not tell them apart: "
                + ", ".join(f"{share[k]:.0%} of the points plausible with {k}-byte records" for k in share)
                + f" (finite, within {AEVA_PLAUSIBLE_M:g} m; {AEVA_PLAUSIBLE_SHARE:.0%} needed)"
            )
        itemsize = good[0]
    else:
        itemsize = fits[0].itemsize
    return parsed[itemsize], "intensity" if itemsize == new.itemsize else "reflectivity"


@guard("HeLiPR .bin")
def read_helipr_bin(path: str | Path, sensor: str) -> Scan:
    """One HeLiPR scan of ``sensor`` (module docstring); intensity from the sensor's intensity field."""
    if sensor not in HELIPR_RECORDS:
        raise ConfigError(f"unknown HeLiPR sensor {sensor!r}; known: {sorted(HELIPR_RECORDS)}")
    p = check_file(path, f"HeLiPR {sensor} .bin")
    dtype, field, imax = HELIPR_RECORDS[sensor]
    if sensor == "Aeva":
        records, field = _aeva_records(p)
    else:
        size = p.stat().st_size
        if size % dtype.itemsize:
            raise ScanFormatError(
                f"{p}: size {size} bytes is not a multiple of the HeLiPR {sensor} record size {dtype.itemsize} "
                f"({', '.join(dtype.names or ())})"
            )
        records = np.fromfile(p, dtype=dtype)
    cols = structured_columns(records)
    named = {"x": cols["x"], "y": cols["y"], "z": cols["z"], "intensity": cols[field]}
    if "ring" in cols:
        named["ring"] = cols["ring"]
    sensor_info = SensorInfo(name=f"{sensor.lower()} (helipr)", intensity_max=imax)
    return columns_to_scan(named, p, sensor=sensor_info)


def _sensors(root: Path) -> list[str]:
    return sorted(s for s in HELIPR_RECORDS if (root / "LiDAR" / s).is_dir())


def detect_helipr(path: Path) -> bool:
    """A folder with ``LiDAR/`` holding a HeLiPR sensor folder, and ``LiDAR_GT/``."""
    return path.is_dir() and (path / "LiDAR_GT").is_dir() and bool(_sensors(path))


class HeliprSequence(TimedSequence):
    """A HeLiPR sequence of one LiDAR (module docstring). ``sensor``: Ouster, Velodyne, Aeva or Avia (may be left
    out when the folder has one); ``poses`` replaces ``LiDAR_GT/<sensor>_gt.txt``."""

    def __init__(
        self,
        path: str | Path,
        sensor: str | None = None,
        poses: str | Path | None = None,
        *,
        max_gap: float = 0.05,
    ) -> None:
        root = Path(path)
        found = _sensors(root)
        if sensor is None:
            if len(found) != 1:
                raise ConfigError(
                    f"{root}: HeLiPR sensors {found}; pass sensor= (one of {sorted(HELIPR_RECORDS)})"
                )
            sensor = found[0]
        if sensor not in HELIPR_RECORDS:
            raise ConfigError(f"unknown HeLiPR sensor {sensor!r}; known: {sorted(HELIPR_RECORDS)}")
        self.sensor = sensor
        files, stamps = stamped_files(root / "LiDAR" / sensor, ".bin", 1e-9, f"HeLiPR {sensor} scans")
        pose_file = Path(poses) if poses is not None else root / "LiDAR_GT" / f"{sensor}_gt.txt"
        gt = read_table(pose_file, 8, "HeLiPR ground truth (timestamp_ns x y z qx qy qz qw)", delimiter=None)
        gt = gt[np.argsort(gt[:, 0], kind="stable")]
        idx, ok = match_nearest(gt[:, 0] * 1e-9, stamps, max_gap, pose_file)
        if not ok.any():
            raise ScanFormatError(f"{pose_file}: no ground-truth row within {max_gap} s of a scan of {root}")
        P = pose_from_xyz_quat(gt[idx, 1:4], gt[idx, 4:8], pose_file)
        P[:, :3, 3] -= P[0, :3, 3]
        keep = np.flatnonzero(ok)
        super().__init__(
            root,
            [files[i] for i in keep],
            stamps[keep],
            P,
            pose_file,
            f"{root.name}:{sensor}",
            {},
            dropped=int((~ok).sum()),
        )

    def _read_file(self, path: Path) -> Scan:
        return read_helipr_bin(path, self.sensor)
