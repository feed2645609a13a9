"""MulRan (Kim et al., ICRA 2020): ``<seq>/sensor_data/Ouster/<ns>.bin`` (or ``<seq>/Ouster/``) and
``<seq>/global_pose.csv``.

Scans are KITTI-style float32 records (x, y, z, intensity) of the Ouster OS1-64; a file of 64 x 1024 points is
organised, stored column-major (each block of 64 consecutive points is one column). ``global_pose.csv`` holds
``timestamp_ns, r11 r12 r13 tx r21 ... tz`` (the top 3x4 of ``T_world_base``, row-major) at its own rate: the
pose of each scan is interpolated at the scan's time (its file name), and scans outside the ground truth's time
span are left out. Poses are of the LiDAR: ``T_world_base @ T_base_lidar`` with the ``calib_base2ouster``
extrinsic (translation 1.7042, -0.021, 1.8047 m; roll, pitch, yaw 0.0001, 0.0003, 179.6654 deg), and their
positions are shifted so that the first scan is at the origin (the UTM coordinates are ~10^6 m).
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
from placerec.io.kitti import KITTI_RECORD_SIZE
from placerec.io.registry import read_scan
from placerec.types import Scan, SensorInfo, rigid_problem

__all__ = ["MulranSequence", "detect_mulran", "MULRAN_LAYOUT", "MULRAN_T_BASE_LIDAR"]

MULRAN_LAYOUT = "<seq>/sensor_data/Ouster/<ns>.bin (or <seq>/Ouster/) + <seq>/global_pose.csv"
MULRAN_T_BASE_LIDAR = pose_from_xyz_rpy([1.7042, -0.021, 1.8047], np.radians([0.0001, 0.0003, 179.6654]))[0]
_ROWS, _COLS = 64, 1024
_SENSOR = SensorInfo(name="ouster-os1-64 (mulran)", columns=_COLS)


def _scan_folder(root: Path) -> Path:
    for cand in (root / "sensor_data" / "Ouster", root / "Ouster"):
        if cand.is_dir():
            return cand
    raise ScanFormatError(
        f"{root}: no sensor_data/Ouster/ or Ouster/ folder (MulRan layout: {MULRAN_LAYOUT})"
    )


def detect_mulran(path: Path) -> bool:
    """A folder with ``global_pose.csv`` and an ``Ouster`` scan folder."""
    return (
        path.is_dir()
        and (path / "global_pose.csv").is_file()
        and any(p.is_dir() for p in (path / "sensor_data" / "Ouster", path / "Ouster"))
    )


class MulranSequence(TimedSequence):
    """A MulRan sequence (module docstring); ``poses`` replaces ``global_pose.csv``; ``organized`` keeps the
    64 x 1024 image structure of full scans."""

    def __init__(self, path: str | Path, poses: str | Path | None = None, *, organized: bool = False) -> None:
        root = Path(path)
        files, stamps = stamped_files(_scan_folder(root), ".bin", 1e-9, "MulRan Ouster scans")
        pose_file = Path(poses) if poses is not None else root / "global_pose.csv"
        gt = read_table(pose_file, 13, "MulRan global_pose.csv (timestamp_ns + 3x4 pose)")
        P = np.tile(np.eye(4), (gt.shape[0], 1, 1))
        P[:, :3, :] = gt[:, 1:].reshape(-1, 3, 4)
        problem = rigid_problem(P)  # here, to name the file's row (and before scipy's Rotation sees it)
        if problem is not None:
            raise ScanFormatError(
                f"{pose_file}: ground-truth data row {problem[0] + 1} is no rigid motion: {problem[1]}"
            )
        order = np.argsort(gt[:, 0], kind="stable")
        lidar, inside = interpolate_poses(
            gt[order, 0] * 1e-9, P[order] @ MULRAN_T_BASE_LIDAR, stamps, pose_file
        )
        if not inside.any():
            raise ScanFormatError(f"{pose_file}: no scan of {root} falls within the ground truth's time span")
        lidar[:, :3, 3] -= lidar[0, :3, 3]
        keep = np.flatnonzero(inside)
        super().__init__(
            root,
            [files[i] for i in keep],
            stamps[keep],
            lidar,
            pose_file,
            root.name,
            {"organized": organized},
            dropped=int((~inside).sum()),
        )

    def _read_file(self, path: Path) -> Scan:
        full = path.stat().st_size == _ROWS * _COLS * KITTI_RECORD_SIZE
        layout = (_ROWS, _COLS, "column-major") if full else None
        scan = read_scan(path, format="kitti", layout=layout, organized=self._options["organized"] and full)
        return replace(scan, sensor=_SENSOR)
