"""What the dataset loaders share: numeric ground-truth tables, poses from (x, y, z, quaternion) or
(x, y, z, roll, pitch, yaw), poses matched or interpolated at scan times, and `TimedSequence`, a
`placerec.io.file_sequence.FileSequence` over scans named by their timestamp.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from placerec.errors import ConfigError, ScanFormatError, short_repr
from placerec.io._common import ascii_digits, check_file
from placerec.io.file_sequence import FileSequence
from placerec.io.poses import quat_to_matrix
from placerec.types import rigid_problem

__all__ = [
    "read_table",
    "pose_from_xyz_quat",
    "pose_from_xyz_rpy",
    "interpolate_poses",
    "match_nearest",
    "check_max_gap",
    "stamped_files",
    "TimedSequence",
]

log = logging.getLogger(__name__)


def read_table(
    path: str | Path, ncols: int, what: str, *, delimiter: str | None = ",", drop_leading_nan: bool = False
) -> np.ndarray:
    """The rows of a numeric text table (CSV with ``delimiter=","``, whitespace with None) as (N, ncols) float64.

    Blank lines and lines starting with ``#`` are skipped, and so is a first line of column names (a
    header). Any other row with another column count or a non-number is a `ScanFormatError` naming the file and
    line; so is a row with NaN/inf, unless ``drop_leading_nan`` and no finite row came before it (then it is
    skipped: NCLT's ground truth starts with NaN rows). ``what`` names the table in messages."""
    p = check_file(path, what)
    try:
        text = p.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as exc:
        raise ScanFormatError(f"{p}: cannot read the {what} as UTF-8 text ({exc})") from None
    rows: list[list[float]] = []
    seen_data = False
    for no, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [t.strip() for t in (s.split(delimiter) if delimiter else s.split())]
        try:
            vals = [float(t) for t in parts]
        except ValueError:
            if not seen_data and not any(_is_float(t) for t in parts):
                seen_data = True  # a header line: column names, no number
                continue
            bad = next(t for t in parts if not _is_float(t))
            raise ScanFormatError(f"{p}:{no}: {bad[:30]!r} is not a number ({what})") from None
        seen_data = True
        if len(vals) != ncols:
            raise ScanFormatError(f"{p}:{no}: {len(vals)} columns, expected {ncols} ({what})")
        if not np.isfinite(vals).all():
            if drop_leading_nan and not rows:
                continue
            raise ScanFormatError(f"{p}:{no}: NaN or inf in the {what}")
        rows.append(vals)
    if not rows:
        raise ScanFormatError(f"{p}: no rows in the {what}")
    return np.asarray(rows, dtype=np.float64)


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


#: how far from 1 a ground-truth quaternion's norm may be (files round them to a few digits; zero or scaled ones
#: are no rotations)
QUATERNION_TOLERANCE = 1e-2


def pose_from_xyz_quat(
    xyz: npt.ArrayLike, quat_xyzw: npt.ArrayLike, where: str | Path = "poses"
) -> np.ndarray:
    """(N, 4, 4) poses from (N, 3) positions and (N, 4) quaternions (qx, qy, qz, qw), normalised; a quaternion
    whose norm is not within `QUATERNION_TOLERANCE` of 1 (zero, scaled, not finite) is a `ScanFormatError` naming
    ``where`` and its row (0-based, in the order given)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quat_xyzw, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1)
    bad = ~(np.abs(norm - 1.0) <= QUATERNION_TOLERANCE)
    if bad.any():
        i = int(np.argmax(bad))
        raise ScanFormatError(
            f"{where}: quaternion of row {i} has norm {norm[i]:.6g}, expected 1 (a rotation)"
        )
    P = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    P[:, :3, :3] = quat_to_matrix(q)
    P[:, :3, 3] = xyz
    return P


def pose_from_xyz_rpy(xyz: npt.ArrayLike, rpy: npt.ArrayLike) -> np.ndarray:
    """(N, 4, 4) poses from positions and (roll, pitch, yaw) in radians, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    cr, cp, cy = np.cos(np.asarray(rpy, dtype=np.float64).reshape(-1, 3)).T
    sr, sp, sy = np.sin(np.asarray(rpy, dtype=np.float64).reshape(-1, 3)).T
    P = np.tile(np.eye(4), (xyz.shape[0], 1, 1))
    P[:, 0, :3] = np.c_[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr]
    P[:, 1, :3] = np.c_[sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr]
    P[:, 2, :3] = np.c_[-sp, cp * sr, cp * cr]
    P[:, :3, 3] = xyz
    return P


def interpolate_poses(
    times: np.ndarray, poses: np.ndarray, at: np.ndarray, where: str | Path
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at times ``at`` (positions linear, rotations slerp between the two ground-truth rows around each)
    and the mask of the ``at`` inside the ground truth's time span (the poses returned are those of these).
    ``times`` must increase strictly: `ScanFormatError` naming ``where`` otherwise."""
    from scipy.spatial.transform import Rotation, Slerp

    times = np.asarray(times, dtype=np.float64)
    if times.size < 2 or not np.isfinite(times).all() or np.any(np.diff(times) <= 0):
        raise ScanFormatError(
            f"{where}: ground-truth times must be finite and increase strictly (at least two rows)"
        )
    problem = rigid_problem(poses)
    if problem is not None:
        raise ScanFormatError(f"{where}: ground-truth row {problem[0]} is no rigid motion: {problem[1]}")
    at = np.asarray(at, dtype=np.float64)
    inside = (at >= times[0]) & (at <= times[-1])
    t = at[inside]
    out = np.tile(np.eye(4), (t.size, 1, 1))
    if t.size:
        for j in range(3):
            out[:, j, 3] = np.interp(t, times, poses[:, j, 3])
        out[:, :3, :3] = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(t).as_matrix()
    return out, inside


def check_max_gap(max_gap: object) -> float:
    """``max_gap`` (seconds a ground-truth row may be from a scan) as a float; `ConfigError` naming ``max_gap``
    unless it is a finite real number >= 0 (a bool or a string is no number of seconds)."""
    if isinstance(max_gap, bool) or not isinstance(max_gap, (int, float, np.integer, np.floating)):
        raise ConfigError(f"max_gap must be a number of seconds, got {short_repr(max_gap)}")
    gap = float(max_gap)
    if not (np.isfinite(gap) and gap >= 0):
        raise ConfigError(f"max_gap must be a finite number of seconds >= 0, got {short_repr(max_gap)}")
    return gap


def match_nearest(
    times: np.ndarray, at: np.ndarray, max_gap: float, where: str | Path
) -> tuple[np.ndarray, np.ndarray]:
    """For each time of ``at``, the index of the nearest of ``times`` (sorted increasing) and the mask of those
    within ``max_gap`` seconds of it (the indices returned are those of these)."""
    max_gap = check_max_gap(max_gap)
    times = np.asarray(times, dtype=np.float64)
    if not np.isfinite(times).all() or np.any(np.diff(times) < 0):
        raise ScanFormatError(f"{where}: ground-truth times must be finite and must not decrease")
    at = np.asarray(at, dtype=np.float64)
    hi = np.clip(np.searchsorted(times, at), 1, times.size - 1) if times.size > 1 else np.zeros(at.size, int)
    lo = np.maximum(hi - 1, 0)
    idx = np.where(np.abs(times[lo] - at) <= np.abs(times[hi] - at), lo, hi)
    ok = np.abs(times[idx] - at) <= max_gap
    return idx[ok], ok


class TimedSequence(FileSequence):
    """Scan files named by their acquisition time, each with a ground-truth pose; ordered by time.

    ``stamps`` (seconds) give each file's time; ``poses`` (N, 4, 4) are aligned with them. ``name`` is the
    sequence's name; ``read_options`` go to `placerec.io.registry.read_scan`. Subclasses may override
    `_read_file`. `dropped` counts the scans the loader left out (no ground truth at their time).
    """

    def __init__(
        self,
        root: Path,
        files: list[Path],
        stamps: np.ndarray,
        poses: np.ndarray | None,
        pose_source: Path | str,
        name: str,
        read_options: dict[str, Any],
        dropped: int = 0,
    ) -> None:
        order = np.argsort(stamps, kind="stable")
        super().__init__(root, [files[i] for i in order], name, read_options)
        self._timestamps = np.asarray(stamps, dtype=np.float64)[order]
        if poses is not None:
            self._set_poses(np.asarray(poses)[order], pose_source)
        self.dropped = dropped
        if dropped:
            log.warning(
                "%s: %d scan(s) left out: no ground truth at their time (%s)", root, dropped, pose_source
            )


def stamped_files(folder: Path, suffix: str, scale: float, what: str) -> tuple[list[Path], np.ndarray]:
    """The ``*<suffix>`` files of ``folder`` whose stem is an integer time, and those times x ``scale`` (seconds);
    the times are split into whole seconds and the rest before scaling, so nanosecond stems keep their precision.
    `ScanFormatError` when the folder is missing, holds no such file or a file named otherwise."""
    if not folder.is_dir():
        raise ScanFormatError(f"{folder}: no such folder ({what})")
    files = sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() == suffix)
    if not files:
        raise ScanFormatError(f"{folder}: no {suffix} scan files ({what})")
    bad = [f.name for f in files if not ascii_digits(f.stem)]
    if bad:
        raise ScanFormatError(f"{folder / bad[0]}: expected a file named by its integer timestamp ({what})")
    return files, integer_seconds([int(f.stem) for f in files], scale)


def integer_seconds(stamps: list[int], scale: float) -> np.ndarray:
    """Integer timestamps in units of ``scale`` seconds (1e-9: nanoseconds) as seconds, float64: split into whole
    seconds and the rest before scaling, so nanosecond stamps keep their precision."""
    per_second = round(1 / scale)
    return np.array([s // per_second + (s % per_second) * scale for s in stamps], dtype=np.float64)
