"""Newer College (Ramezani et al., IROS 2020): ``<seq>/raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd`` and
``<seq>/ground_truth/registered_poses.csv``.

The ground truth's rows are ``sec, nsec, x, y, z, qx, qy, qz, qw`` (a header line is skipped), poses of the
sensor base; each scan takes the row nearest its time (its file name) if within ``max_gap`` seconds, and is left
out otherwise. Poses are of the LiDAR: ``T_world_base @ T_base_lidar`` with the base -> Ouster extrinsic of the
dataset (quaternion x, y, z, w = 0, 0, 0.924, 0.383, i.e. a 135 deg yaw; translation -0.084, -0.025, 0.050 m).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from placerec.errors import ScanFormatError, short_repr
from placerec.io.datasets.trajectory import TimedSequence, match_nearest, pose_from_xyz_quat, read_table

__all__ = ["NewerCollegeSequence", "detect_newer_college", "NEWER_COLLEGE_LAYOUT", "NCD_T_BASE_LIDAR"]

NEWER_COLLEGE_LAYOUT = (
    "<seq>/raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd + <seq>/ground_truth/registered_poses.csv"
)
NCD_T_BASE_LIDAR = pose_from_xyz_quat([-0.084, -0.025, 0.050], [0.0, 0.0, 0.924, 0.383])[0]
_NAME = re.compile(r"^cloud_([0-9]+)_([0-9]+)\.pcd$")
_NS_PER_S = 1_000_000_000


def detect_newer_college(path: Path) -> bool:
    """A folder with ``raw_format/ouster_scan/``."""
    return path.is_dir() and (path / "raw_format" / "ouster_scan").is_dir()


class NewerCollegeSequence(TimedSequence):
    """A Newer College sequence (module docstring); ``poses`` replaces ``ground_truth/registered_poses.csv``;
    ``organized`` keeps the PCD's image structure; ``max_gap``: seconds a ground-truth row may be from a scan."""

    def __init__(
        self,
        path: str | Path,
        poses: str | Path | None = None,
        *,
        organized: bool = False,
        max_gap: float = 0.05,
    ) -> None:
        root = Path(path)
        folder = root / "raw_format" / "ouster_scan"
        if not folder.is_dir():
            raise ScanFormatError(
                f"{root}: no raw_format/ouster_scan/ folder (layout: {NEWER_COLLEGE_LAYOUT})"
            )
        files, stamps = [], []
        for f in sorted(folder.glob("*.pcd")):
            m = _NAME.match(f.name)
            if m is None:
                raise ScanFormatError(f"{f}: expected a scan named cloud_<sec>_<nsec>.pcd")
            if int(m.group(2)) >= _NS_PER_S:
                raise ScanFormatError(
                    f"{f}: nanoseconds field {short_repr(m.group(2))} is not below 10^9 "
                    "(expected a scan named cloud_<sec>_<nsec>.pcd, 0 <= nsec < 10^9)"
                )
            files.append(f)
            stamps.append(int(m.group(1)) + int(m.group(2)) * 1e-9)
        if not files:
            raise ScanFormatError(f"{folder}: no cloud_<sec>_<nsec>.pcd scans")
        pose_file = Path(poses) if poses is not None else root / "ground_truth" / "registered_poses.csv"
        gt = read_table(pose_file, 9, "Newer College ground truth (sec, nsec, x, y, z, qx, qy, qz, qw)")
        bad = (gt[:, 0] < 0) | (gt[:, 1] < 0) | (gt[:, 1] >= _NS_PER_S)
        if bad.any():
            i = int(np.argmax(bad))
            raise ScanFormatError(
                f"{pose_file}: ground-truth data row {i + 1} has sec {gt[i, 0]:.10g}, nsec {gt[i, 1]:.10g}; expected "
                "sec >= 0 and 0 <= nsec < 10^9"
            )
        gt = gt[np.argsort(gt[:, 0] + gt[:, 1] * 1e-9, kind="stable")]
        t_gt = gt[:, 0] + gt[:, 1] * 1e-9
        P = pose_from_xyz_quat(gt[:, 2:5], gt[:, 5:9], pose_file) @ NCD_T_BASE_LIDAR
        t = np.asarray(stamps)
        idx, ok = match_nearest(t_gt, t, max_gap, pose_file)
        if not ok.any():
            raise ScanFormatError(
                f"{pose_file}: no ground-truth row within {max_gap} s of a scan of {folder}"
            )
        keep = np.flatnonzero(ok)
        super().__init__(
            root,
            [files[i] for i in keep],
            t[keep],
            P[idx],
            pose_file,
            root.name,
            {"format": "pcd", "organized": organized},
            dropped=int((~ok).sum()),
        )
