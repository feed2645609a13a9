"""`FolderSequence` and the `open_sequence` factory; the dataset layouts it recognises are in
`placerec.io.datasets` (`KittiSequence` is re-exported from there)."""

from __future__ import annotations

import inspect
import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanFormatError
from placerec.io._common import ascii_digits, natural_key
from placerec.io.datasets import DATASET_LOADERS, dataset_loader, detect_dataset
from placerec.io.datasets.kitti import KittiSequence, read_kitti_calib
from placerec.io.datasets.trajectory import integer_seconds, match_nearest
from placerec.io.file_sequence import FileSequence, load_sensor_yaml
from placerec.io.poses import read_poses
from placerec.io.registry import EXTENSIONS, read_format_of
from placerec.types import Sequence

__all__ = ["KittiSequence", "FolderSequence", "open_sequence", "load_sensor_yaml", "read_kitti_calib"]

log = logging.getLogger(__name__)


class FolderSequence(FileSequence):
    """A folder of scan files of one format, in natural order (``scan2`` before ``scan10``).

    ``pattern`` is a glob (default: every file with a known scan suffix; they must share one suffix).
    ``poses``: a KITTI or TUM trajectory file (a TUM file also gives the timestamps); without it
    ``root/poses.txt`` is used when present. It holds one pose per scan in order, or — when it has more rows than
    there are scans and every scan file is named by its frame number (``000094.bin``: row 94, counted from 0) —
    the poses of the whole sequence the frames were picked from (`rows_by_frame_number`); any other count is a
    `ScanFormatError`. ``format`` forces the reader (e.g. ``"nclt"`` for ``.bin``); other
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
            rows = rows_by_frame_number(files, len(P))
            stamps = file_times(files) if rows is None and t is not None and len(P) != len(files) else None
            if rows is not None:  # frames picked out of a whole sequence, named by their frame number
                log.info("%s: %d poses of %s picked by the scans' frame numbers", root, len(rows), poses)
                P, t = P[rows], None if t is None else t[rows]
            elif stamps is not None and t is not None:  # scans named by their time, a TUM file's times
                idx, ok = match_nearest(t, stamps, POSE_TIME_GAP, poses)
                if not ok.all():
                    unmatched = files[int(np.argmin(ok))].name
                    raise ScanFormatError(
                        f"{poses}: no pose within {POSE_TIME_GAP} s of scan {unmatched} (its name read as its time)"
                    )
                log.info("%s: %d poses of %s picked by the scans' times (file names)", root, len(idx), poses)
                P, t = P[idx], stamps
            elif len(P) != len(files):
                raise ScanFormatError(
                    f"{poses}: {len(P)} poses for {len(files)} scans in {root}: a pose file holds one pose per scan "
                    "in order, or the whole sequence's poses when every scan file is named by its frame number "
                    "(000094.bin: row 94, from 0) below its row count"
                )
            self._set_poses(P, poses)
            self._timestamps = t


def rows_by_frame_number(files: list[Path], n_rows: int) -> np.ndarray | None:
    """The pose-file rows of ``files`` when a pose file of ``n_rows`` rows covers more than these scans and every
    file's stem is a distinct frame number (ASCII digits) below ``n_rows``; None otherwise (one row per scan)."""
    if n_rows <= len(files) or not files or not all(ascii_digits(f.stem) for f in files):
        return None
    rows = np.array([int(f.stem) for f in files], dtype=np.int64)
    if rows.max() >= n_rows or np.unique(rows).size != rows.size:
        return None
    return rows


#: how far (s) the nearest pose of a TUM file may be from a scan whose file name is its time
POSE_TIME_GAP = 0.05

_TIME_NAME = re.compile(r"[0-9]+(\.[0-9]+)?")


def file_times(files: list[Path]) -> np.ndarray | None:
    """The times (s) the scan files' names give when every stem is one: seconds with a fraction
    (``1318.104571.pcd``), or an integer of 16 or more digits (nanoseconds, ``1566279710893402354.bin``) or of 13 to
    15 (microseconds) — None otherwise, and for integers of fewer digits (frame numbers)."""
    out = []
    for f in files:
        stem = f.stem
        if not _TIME_NAME.fullmatch(stem) or ("." not in stem and len(stem) < 13):
            return None
        scale = 1.0 if "." in stem else 1e-9 if len(stem) >= 16 else 1e-6
        out.append(float(stem) if scale == 1.0 else float(integer_seconds([int(stem)], scale)[0]))
    return np.asarray(out, np.float64)


def _bag_root(path: Path) -> Path | None:
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return path
    if path.is_file() and path.suffix == ".bag":
        return path
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return None


def _open(loader: Callable[..., Sequence], path: Path, options: dict[str, Any]) -> Sequence:
    """``loader(path, **options)`` (a class or a function); ConfigError naming the loader and the options it takes
    for any other option."""
    is_class = isinstance(loader, type)
    params = inspect.signature(loader.__init__ if is_class else loader).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        allowed = list(params)[2 if is_class else 1 :]  # after (self and) the path
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            raise ConfigError(
                f"{path}: opened as {loader.__name__}, which does not take option(s) {unknown}; it takes {allowed}"
            )
    return loader(path, **options)


def open_sequence(path: str | Path, dataset: str | None = None, **options: Any) -> Sequence:
    """Open a sequence with the loader its path calls for; ``options`` go to that loader.

    ``dataset`` names a dataset layout of `placerec.io.datasets.DATASET_LOADERS` (kitti, mulran, newer-college,
    helipr, nclt, mcap); without it the path is matched against them in that table's order, then:

    * a folder with ``velodyne/`` (no ``calib.txt``) -> `KittiSequence`;
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
    if dataset is not None:
        return _open(dataset_loader(dataset).open, p, options)
    bag = _bag_root(p)
    if bag is not None:
        from placerec.io.rosbag import RosbagSequence

        return _open(RosbagSequence, bag, options)
    if p.is_file() and p.suffix.lower() == ".pcap":
        from placerec.io.ouster import OusterSequence

        return _open(OusterSequence, p, options)
    detected = detect_dataset(p)
    if detected is not None:
        log.info("%s: opened as a %s dataset", p, detected)
        return _open(DATASET_LOADERS[detected].open, p, options)
    if p.is_dir() and (p / "velodyne").is_dir():
        return _open(KittiSequence, p, options)
    if p.is_dir():
        return FolderSequence(p, **options)
    raise ScanFormatError(f"{p}: cannot open as a sequence (expected a folder, a rosbag or an Ouster .pcap)")
