"""Lazy `Sequence` loaders for scan folders: `KittiSequence`, `FolderSequence`, and the `open_sequence` factory.

Both folder loaders understand two files written by placerec's simulator:

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

import inspect
import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanDataError, ScanFormatError
from placerec.io._common import natural_key, read_bytes
from placerec.io.npz import parse_npy
from placerec.io.poses import read_poses
from placerec.io.registry import EXTENSIONS, read_format_of, read_scan
from placerec.safe_yaml import load_yaml
from placerec.types import Scan, SensorInfo, Sequence, check_poses

__all__ = ["KittiSequence", "FolderSequence", "open_sequence", "load_sensor_yaml", "read_kitti_calib"]

log = logging.getLogger(__name__)


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
        out[key.strip()] = np.vstack([vals.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    return out


def _check_rigid(T: np.ndarray, what: str, tol: float = 1e-2) -> None:
    """ScanFormatError unless the 4x4 ``T`` is a rigid transform (orthonormal rotation, determinant +1)."""
    R = T[:3, :3]
    if not np.isfinite(T).all() or not np.allclose(R @ R.T, np.eye(3), atol=tol) or np.linalg.det(R) < 0:
        raise ScanFormatError(
            f"{what} is not a rigid transform (rotation {np.round(R, 4).tolist()} is not orthonormal with "
            "determinant +1); expected the velodyne -> camera 0 calibration"
        )


def _read_times(path: Path, n: int) -> np.ndarray:
    p, buf = read_bytes(path, "times.txt")
    try:
        t = np.array(buf.decode("utf-8").split(), dtype=np.float64)
    except (ValueError, UnicodeDecodeError):
        raise ScanFormatError(f"{p}: expected one number (seconds) per line") from None
    if t.size != n:
        raise ScanFormatError(f"{p}: {t.size} timestamps for {n} scans")
    return t


class _FileSequence:
    """Shared machinery: a sorted file list, optional poses/timestamps, sensor.yaml and ring files."""

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
        self._poses = None if poses is None else check_poses(poses, len(self._files), str(source))

    def __len__(self) -> int:
        return len(self._files)

    def __getitem__(self, index: int) -> Scan:
        path = self._files[index]  # IndexError past the end, as Python sequences do
        scan = read_scan(path, **self._options)
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

    @property
    def poses(self) -> np.ndarray | None:
        return self._poses

    @property
    def timestamps(self) -> np.ndarray | None:
        return self._timestamps

    @property
    def name(self) -> str:
        return self._name


class KittiSequence(_FileSequence):
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
            _check_rigid(self.Tr, f"{calib_path}: Tr")
        if poses is not None:
            P, _ = read_poses(poses, format="kitti")
            if poses_in_camera_frame and self.Tr is None:
                raise ScanFormatError(f"{root}: poses_in_camera_frame=True needs calib.txt with a Tr line")
            if self.Tr is not None and poses_in_camera_frame is not False:
                P = np.linalg.inv(self.Tr) @ P @ self.Tr
            self._set_poses(P, poses)
        if (root / "times.txt").is_file():
            self._timestamps = _read_times(root / "times.txt", len(self._files))


class FolderSequence(_FileSequence):
    """A folder of scan files of one format, in natural order (``scan2`` before ``scan10``).

    ``pattern`` is a glob (default: every file with a known scan suffix; they must share one suffix).
    ``poses``: a KITTI or TUM trajectory file (a TUM file also gives the timestamps); without it
    ``root/poses.txt`` is used when present. ``format`` forces the reader (e.g. ``"nclt"`` for ``.bin``); other
    keyword options (``organized``, ``layout``) go to `read_scan`. Also reads ``sensor.yaml`` and ``ring/`` files.
    """

    def __init__(
        self,
        root: str | Path,
        pattern: str | None = None,
        poses: str | Path | None = None,
        format: str | None = None,
        **read_options: Any,
    ) -> None:
        root = Path(root)
        if not root.is_dir():
            raise ScanFormatError(f"{root}: not a folder of scans")
        if pattern is None:
            files = [f for f in root.iterdir() if f.is_file() and f.suffix.lower() in EXTENSIONS]
            suffixes = sorted({f.suffix.lower() for f in files})
            if len(suffixes) > 1:
                raise ScanFormatError(
                    f"{root}: scan files of several kinds {suffixes}; pass pattern= (e.g. '*.pcd')"
                )
        else:
            files = [f for f in root.glob(pattern) if f.is_file()]
        files.sort(key=natural_key)
        bad = set(read_options) - {"organized", "layout", "sensor"}
        if bad:
            raise ConfigError(
                f"FolderSequence got unknown option(s) {sorted(bad)}; allowed: organized, layout, sensor"
            )
        if (
            files
        ):  # decided once from the first file; an unknown suffix or format fails now, not on the first scan
            format = read_format_of(files[0], format, read_options)
        super().__init__(root, files, root.name, {"format": format, **read_options})
        if poses is None and (root / "poses.txt").is_file():
            poses = root / "poses.txt"
        if poses is not None:
            P, t = read_poses(poses)
            self._set_poses(P, poses)
            self._timestamps = t


def _bag_root(path: Path) -> Path | None:
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return path
    if path.is_file() and path.suffix == ".bag":
        return path
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return None


def _open(loader: type, path: Path, options: dict[str, Any]) -> Sequence:
    """``loader(path, **options)``; ConfigError naming the loader and the options it takes for any other option."""
    params = inspect.signature(loader.__init__).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        allowed = list(params)[2:]  # after self and the path
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            raise ConfigError(
                f"{path}: opened as {loader.__name__}, which does not take option(s) {unknown}; it takes {allowed}"
            )
    return loader(path, **options)


def open_sequence(path: str | Path, **options: Any) -> Sequence:
    """Open a sequence with the loader its path calls for; ``options`` go to that loader.

    * a folder with ``velodyne/`` -> `KittiSequence`;
    * a rosbag2 folder (``metadata.yaml``), a ``.db3``/``.mcap`` inside one, or a ROS1 ``.bag`` ->
      `placerec.io.rosbag.RosbagSequence` (option ``topic``);
    * a ``.pcap`` -> `placerec.io.ouster.OusterSequence` (option ``metadata``: the sensor JSON; default: the
      ``.json`` beside the capture whose name matches best; option ``poses``; default: the
      ``<stem>_poses_kitti.txt`` beside the capture, if any);
    * any other folder -> `FolderSequence`.

    An option the chosen loader does not take (e.g. ``format`` for a KITTI sequence folder) is a `ConfigError`.
    """
    p = Path(path)
    if not p.exists():
        raise ScanFormatError(f"{p}: no such sequence file or folder")
    bag = _bag_root(p)
    if bag is not None:
        from placerec.io.rosbag import RosbagSequence

        return _open(RosbagSequence, bag, options)
    if p.is_file() and p.suffix.lower() == ".pcap":
        from placerec.io.ouster import OusterSequence

        return _open(OusterSequence, p, options)
    if p.is_dir() and (p / "velodyne").is_dir():
        return _open(KittiSequence, p, options)
    if p.is_dir():
        return FolderSequence(p, **options)
    raise ScanFormatError(f"{p}: cannot open as a sequence (expected a folder, a rosbag or an Ouster .pcap)")
