"""KITTI odometry (`KittiSequence`): ``sequences/NN/velodyne/*.bin``, ``sequences/NN/calib.txt`` and
``poses/NN.txt``.

KITTI's ground-truth poses are those of the left camera (``T_cam0world_cam0(i)``); `KittiSequence` converts them
to LiDAR poses ``inv(Tr) @ P @ Tr`` with ``Tr`` (velodyne -> camera 0) from ``calib.txt``, i.e. poses of the
LiDAR expressed in the frame of the first LiDAR scan. Opened as ``dataset="kitti"`` (`open_kitti_odometry`), the
conversion is required: ground-truth poses without a ``calib.txt`` holding ``Tr`` are an error, since using the
camera poses for LiDAR scans is the common mistake this loader exists to prevent.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanFormatError
from placerec.io._common import ascii_digits, natural_key, read_bytes
from placerec.io.file_sequence import FileSequence, read_times
from placerec.io.poses import read_poses
from placerec.types import rigid_problem

__all__ = ["KittiSequence", "read_kitti_calib", "open_kitti_odometry", "detect_kitti", "KITTI_LAYOUT"]

KITTI_LAYOUT = "sequences/NN/velodyne/*.bin + sequences/NN/calib.txt (Tr) + poses/NN.txt"


def read_kitti_calib(path: str | Path) -> dict[str, np.ndarray]:
    """Read a KITTI ``calib.txt`` (``KEY: 12 numbers`` lines) into 4x4 matrices (P0..P3, Tr)."""
    p, buf = read_bytes(path, "KITTI calib.txt")
    out: dict[str, np.ndarray] = {}
    for no, line in enumerate(buf.decode("utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        try:
            vals = np.array(rest.split(), dtype=np.float64)
        except ValueError:
            raise ScanFormatError(f"{p}:{no}: calibration values are not numbers") from None
        if not sep or vals.size != 12:
            raise ScanFormatError(f"{p}:{no}: expected 'KEY: 12 numbers', got {line[:60]!r}")
        T = np.vstack([vals.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
        k = key.strip()
        if k in out and not np.array_equal(out[k], T):
            raise ScanFormatError(f"{p}:{no}: a second, different {k!r} line (which one holds is unknowable)")
        out[k] = T
    return out


def check_rigid(T: np.ndarray, what: str) -> None:
    """ScanFormatError unless the 4x4 ``T`` is a rigid transform (`placerec.types.rigid_problem`)."""
    problem = rigid_problem(np.asarray(T, np.float64)[None])
    if problem is not None:
        raise ScanFormatError(
            f"{what} is not a rigid transform ({problem[1]}); expected the velodyne -> camera 0 calibration"
        )


class KittiSequence(FileSequence):
    """A KITTI odometry sequence folder: ``root/velodyne/*.bin``, optional poses, ``times.txt``, ``calib.txt``.

    Poses come from ``poses`` when given, else ``root/poses.txt``, else the official layout's
    ``root/../../poses/<root name>.txt``. KITTI's ground-truth poses are those of the left camera
    (``T_cam0world_cam0(i)``); when ``calib.txt`` holds ``Tr`` (velodyne -> camera 0) they are converted to LiDAR
    poses ``inv(Tr) @ P @ Tr``, i.e. expressed in the frame of the first LiDAR scan. ``poses_in_camera_frame``:
    None converts when Tr is available, True requires Tr, False never converts (poses already in LiDAR frame,
    as the simulator writes them). Also reads ``sensor.yaml`` and ``ring/`` files (module docstring).
    """

    def __init__(
        self,
        root: str | Path,
        poses: str | Path | None = None,
        *,
        poses_in_camera_frame: bool | None = None,
        layout: tuple[int, int, str] | None = None,
        organized: bool = False,
    ) -> None:
        root = Path(root)
        velo = root / "velodyne"
        if not velo.is_dir():
            raise ScanFormatError(f"{root}: not a KITTI sequence folder (no velodyne/ folder)")
        files = sorted((f for f in velo.glob("*.bin") if f.is_file()), key=natural_key)
        opts: dict[str, Any] = {"format": "kitti", "organized": organized}
        if layout is not None:
            opts["layout"] = layout
        super().__init__(root, files, root.name, opts)
        if poses is None:
            for cand in (root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"):
                if cand.is_file():
                    poses = cand
                    break
        calib_path = root / "calib.txt"
        self.Tr = read_kitti_calib(calib_path).get("Tr") if calib_path.is_file() else None
        if self.Tr is not None:
            check_rigid(self.Tr, f"{calib_path}: Tr")
        if poses is not None:
            P, _ = read_poses(poses, format="kitti")
            if poses_in_camera_frame and self.Tr is None:
                raise ScanFormatError(f"{root}: poses_in_camera_frame=True needs calib.txt with a Tr line")
            if self.Tr is not None and poses_in_camera_frame is not False:
                P = np.linalg.inv(self.Tr) @ P @ self.Tr
            self._set_poses(P, poses)
        if (root / "times.txt").is_file():
            self._timestamps = read_times(root / "times.txt", len(self._files))


def _sequence_root(path: Path, sequence: str | int | None) -> Path:
    """The sequence folder: ``path`` itself (it holds ``velodyne/``) or ``path/sequences/<sequence>``."""
    if (path / "velodyne").is_dir():
        if sequence is not None and path.name != _seq_name(sequence):
            raise ConfigError(f"{path}: is sequence {path.name!r}, but sequence={sequence!r} was asked for")
        return path
    if (path / "sequences").is_dir():
        if sequence is None:
            found = sorted(p.name for p in (path / "sequences").iterdir() if (p / "velodyne").is_dir())
            raise ConfigError(f"{path}: a KITTI odometry root; pass sequence= (one of {found})")
        root = path / "sequences" / _seq_name(sequence)
        if not (root / "velodyne").is_dir():
            raise ScanFormatError(f"{root}: no such KITTI sequence (no velodyne/ folder)")
        return root
    raise ScanFormatError(f"{path}: not a KITTI odometry layout ({KITTI_LAYOUT})")


def _seq_name(sequence: str | int) -> str:
    return (
        f"{int(sequence):02d}" if isinstance(sequence, int) or ascii_digits(str(sequence)) else str(sequence)
    )


def detect_kitti(path: Path) -> bool:
    """A KITTI odometry sequence folder (``velodyne/`` and ``calib.txt``) or dataset root (``sequences/``)."""
    return path.is_dir() and (
        ((path / "velodyne").is_dir() and (path / "calib.txt").is_file()) or (path / "sequences").is_dir()
    )


def open_kitti_odometry(
    path: str | Path, sequence: str | int | None = None, poses: str | Path | None = None
) -> KittiSequence:
    """A KITTI odometry sequence with LiDAR-frame poses: ``path`` is a sequence folder or the dataset root (then
    ``sequence``, e.g. ``"00"``). Poses (``poses`` or the layout's own file) need ``calib.txt`` with ``Tr``:
    `ScanFormatError` naming it otherwise; a pose count other than the scan count names the pose file."""
    root = _sequence_root(Path(path), sequence)
    seq = KittiSequence(root, poses, poses_in_camera_frame=None)
    if seq.poses is not None and seq.Tr is None:
        raise ScanFormatError(
            f"{root / 'calib.txt'}: missing or without a 'Tr:' line; KITTI ground-truth poses are camera poses "
            "and need Tr (velodyne -> camera 0) to become LiDAR poses"
        )
    return seq
