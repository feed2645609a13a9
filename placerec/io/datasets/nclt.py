"""NCLT (Carlevaris-Bianco et al., IJRR 2016): ``<date>/velodyne_sync/<utime>.bin`` and the ground truth
``groundtruth_<date>.csv`` (found in ``<date>/``, ``<date>/../ground_truth/`` or given as ``poses``).

Scans are read by `placerec.io.nclt.read_nclt_bin`. NCLT's frames are z-down (x forward, y right, z down: the
Segway's body frame, whose axes ``velodyne_sync`` points already share); placerec's are z-up, so points and poses
are turned by ``F = diag(1, -1, -1)`` (x, -y, -z), the beam elevations negated with them. The ground truth's rows
are ``utime, x, y, z, roll, pitch, yaw`` (microseconds, metres, radians; ``R = Rz(yaw) Ry(pitch) Rx(roll)``), poses
of the body; the rows with NaN the files start with are skipped (a NaN row after them is an error), and
the times must increase strictly. Each scan's pose is interpolated at its time
(the file name), scans outside the ground truth's span are left out, and the LiDAR pose is
``F @ T_world_body @ T_body_velodyne @ F`` with the body -> Velodyne lever arm of the NCLT paper (0.002, -0.004,
-0.957 m; roll 0.807, pitch 0.166 deg; its -90.703 deg yaw is already applied to ``velodyne_sync`` points).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io.datasets.trajectory import (
    TimedSequence,
    interpolate_poses,
    pose_from_xyz_rpy,
    read_table,
    stamped_files,
)
from placerec.io.nclt import NCLT_SENSOR, read_nclt_bin
from placerec.types import Scan

__all__ = ["NcltSequence", "detect_nclt", "NCLT_LAYOUT", "NCLT_T_BODY_VELODYNE"]

NCLT_LAYOUT = (
    "<date>/velodyne_sync/<utime>.bin + groundtruth_<date>.csv (in <date>/ or <date>/../ground_truth/)"
)
NCLT_T_BODY_VELODYNE = pose_from_xyz_rpy([0.002, -0.004, -0.957], np.radians([0.807, 0.166, 0.0]))[0]
_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])
_SENSOR = replace(
    NCLT_SENSOR,
    name="velodyne-hdl32e (nclt, z up)",
    beam_elevations_deg=tuple(-e for e in NCLT_SENSOR.beam_elevations_deg or ()),
)


def detect_nclt(path: Path) -> bool:
    """A folder with ``velodyne_sync/``."""
    return path.is_dir() and (path / "velodyne_sync").is_dir()


def _ground_truth(root: Path) -> Path:
    name = f"groundtruth_{root.name}.csv"
    for cand in (root / name, root.parent / "ground_truth" / name, root / "ground_truth" / name):
        if cand.is_file():
            return cand
    found = sorted(root.glob("groundtruth_*.csv"))
    if len(found) == 1:
        return found[0]
    raise ScanFormatError(
        f"{root}: no NCLT ground truth {name} (looked in {root}, {root.parent / 'ground_truth'}); pass poses="
    )


class NcltSequence(TimedSequence):
    """An NCLT session (module docstring); ``poses`` names the ground-truth CSV when it is elsewhere."""

    def __init__(self, path: str | Path, poses: str | Path | None = None) -> None:
        root = Path(path)
        files, stamps = stamped_files(root / "velodyne_sync", ".bin", 1e-6, "NCLT velodyne_sync scans")
        pose_file = Path(poses) if poses is not None else _ground_truth(root)
        gt = read_table(
            pose_file, 7, "NCLT ground truth (utime, x, y, z, roll, pitch, yaw)", drop_leading_nan=True
        )
        back = np.flatnonzero(np.diff(gt[:, 0]) <= 0)
        if back.size:
            i = int(back[0]) + 1
            raise ScanFormatError(
                f"{pose_file}: ground-truth time {gt[i, 0]:.0f} us does not come after {gt[i - 1, 0]:.0f} us "
                f"(finite row {i + 1}); times must increase strictly"
            )
        body = pose_from_xyz_rpy(gt[:, 1:4], gt[:, 4:7])
        lidar, inside = interpolate_poses(gt[:, 0] * 1e-6, body @ NCLT_T_BODY_VELODYNE, stamps, pose_file)
        if not inside.any():
            raise ScanFormatError(f"{pose_file}: no scan of {root} falls within the ground truth's time span")
        keep = np.flatnonzero(inside)
        super().__init__(
            root,
            [files[i] for i in keep],
            stamps[keep],
            _FLIP @ lidar @ _FLIP,
            pose_file,
            root.name,
            {},
            dropped=int((~inside).sum()),
        )

    def _read_file(self, path: Path) -> Scan:
        scan = read_nclt_bin(path)
        return replace(scan, xyz=scan.xyz * np.array([1.0, -1.0, -1.0], np.float32), sensor=_SENSOR)
