"""Ouster packet captures (``.pcap`` + sensor metadata ``.json``) through ouster-sdk (optional extra).

Every frame becomes an organised `Scan` (rows = beams, top beam first; cols = columns per frame), destaggered,
with xyz from the sdk's ``XYZLut`` (sensor frame, metres; zero range -> zero point), intensity = the calibrated
``REFLECTIVITY`` channel, ``ring`` = row and ``time`` = column time offset from the first valid column (s).
`SensorInfo` carries the beam altitude angles, the column count and ``intensity_max`` = 255 or 65535 from the
reflectivity field's width. The metadata must match the capture: a JSON of another sensor mode decodes no
frame, which is reported as ScanFormatError. A frame with columns missing from the sensor's column window (a
truncated capture, dropped packets) is logged as a warning when it is decoded; the last frame is checked on
opening, so a truncated capture warns at once. Poses (``T_world_sensor``, one per frame) come from a KITTI-format
``<capture stem>_poses_kitti.txt`` beside the capture, as ouster-sdk's tools name them, or from ``poses=``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import DependencyError, ScanDataError, ScanFormatError
from placerec.io._common import check_file
from placerec.io.poses import read_poses
from placerec.threads import import_openmp
from placerec.types import Scan, SensorInfo, check_poses

__all__ = ["OusterSequence", "read_ouster_pcap", "find_ouster_metadata", "find_ouster_poses"]

log = logging.getLogger(__name__)


def _sdk() -> tuple[Any, Any]:
    try:
        import_openmp("ouster.sdk")  # its OpenMP runtime loaded with idle threads sleeping
        from ouster.sdk import core, open_source
    except ImportError as exc:
        raise DependencyError(
            f"reading Ouster pcaps needs ouster-sdk ({exc}); install it with: pip install placerec[ouster]"
        ) from exc
    return open_source, core


def find_ouster_metadata(pcap: str | Path) -> Path:
    """The ``.json`` beside ``pcap`` with the same stem, else the one sharing the longest name prefix."""
    pcap = Path(pcap)
    jsons = sorted(pcap.parent.glob("*.json"))
    exact = pcap.with_suffix(".json")
    if exact in jsons:
        return exact
    scores = {j: len(os.path.commonprefix([j.stem, pcap.stem])) for j in jsons}
    best = max(scores.values(), default=0)
    cands = [j for j, s in scores.items() if s == best]
    if best == 0 or len(cands) != 1:
        found = [j.name for j in jsons] or "none"
        raise ScanFormatError(
            f"{pcap}: cannot tell which metadata .json belongs to it (found: {found}); pass metadata="
        )
    return cands[0]


def find_ouster_poses(pcap: str | Path) -> Path | None:
    """``<stem>_poses_kitti.txt`` beside ``pcap`` when it exists (the name ouster-sdk's tools give poses)."""
    pcap = Path(pcap)
    path = pcap.with_name(f"{pcap.stem}_poses_kitti.txt")
    return path if path.is_file() else None


class OusterSequence:
    """The frames of an Ouster ``.pcap`` as a lazy `Sequence` of organised scans.

    ``metadata`` is the sensor JSON; by default `find_ouster_metadata` picks it. ``poses``: a KITTI or TUM
    trajectory with one pose per frame; by default `find_ouster_poses`, else no poses. Frames are decoded on
    access.
    """

    def __init__(
        self, pcap: str | Path, metadata: str | Path | None = None, poses: str | Path | None = None
    ) -> None:
        open_source, core = _sdk()
        self._pcap = check_file(pcap, "Ouster .pcap")
        self._meta = check_file(
            metadata if metadata is not None else find_ouster_metadata(self._pcap), "Ouster metadata .json"
        )
        self._core = core
        try:
            self._src = open_source(str(self._pcap), meta=[str(self._meta)], sensor_idx=0, index=True)
            self._n = len(self._src)
        except Exception as exc:  # the sdk raises its own exception types for unreadable captures/metadata
            raise ScanFormatError(
                f"{self._pcap}: cannot decode with metadata {self._meta.name} ({exc})"
            ) from exc
        if self._n == 0:
            raise ScanFormatError(
                f"{self._pcap}: no frame decoded with metadata {self._meta.name}; the metadata "
                "does not match the capture (other sensor, lidar mode or data profile?)"
            )
        self._info = self._src.sensor_info[0]
        lut_cls = getattr(core, "XYZLutFloat", core.XYZLut)
        self._lut = lut_cls(self._info)
        self._sensor: SensorInfo | None = None
        self._timestamps: np.ndarray | None = None
        self._poses: np.ndarray | None = None
        self._incomplete_reported: set[int] = set()
        self._frame(self._n - 1)  # a truncated capture ends in a partial frame: report it now
        poses_path = Path(poses) if poses is not None else find_ouster_poses(self._pcap)
        if poses_path is not None:
            P, _ = read_poses(poses_path)
            try:
                self._poses = check_poses(P, self._n, str(poses_path))
            except ScanDataError as exc:
                raise ScanFormatError(f"{exc} (frames of {self._pcap.name})") from None

    def __len__(self) -> int:
        return self._n

    def _frame(self, index: int) -> Any:
        if index < 0:
            index += self._n
        if not 0 <= index < self._n:
            raise IndexError(f"frame {index} out of range ({self._n} frames)")
        frame = self._src[index][0]
        if frame is None:
            raise ScanFormatError(f"{self._pcap}: frame {index} is missing from the capture")
        window = self._info.format.column_window
        if not frame.complete(window) and index not in self._incomplete_reported:
            self._incomplete_reported.add(index)
            got = int(np.count_nonzero(np.asarray(frame.status) & 1))
            log.warning(
                "%s: frame %d of %d is incomplete (%d of %d columns decoded): the capture is truncated or lost "
                "packets; its missing columns are empty",
                self._pcap,
                index,
                self._n,
                got,
                int(frame.w),
            )
        return frame

    def _sensor_info(self, refl_dtype: np.dtype | None) -> SensorInfo:
        if self._sensor is None:
            info = self._info
            imax = None if refl_dtype is None else float(np.iinfo(refl_dtype).max)
            self._sensor = SensorInfo(
                name=info.prod_line or f"ouster ({len(info.beam_altitude_angles)} beams)",
                beam_elevations_deg=tuple(float(v) for v in info.beam_altitude_angles),
                columns=int(info.format.columns_per_frame),
                intensity_max=imax,
            )
        return self._sensor

    def __getitem__(self, index: int) -> Scan:
        frame = self._frame(index)
        destagger = self._core.destagger
        h, w = int(frame.h), int(frame.w)
        xyz = destagger(self._info, np.ascontiguousarray(self._lut(frame), dtype=np.float32))
        if frame.has_field("REFLECTIVITY"):
            refl = destagger(self._info, frame.field("REFLECTIVITY"))
            inten = refl.astype(np.float32)
            dtype = refl.dtype
        else:
            log.warning("%s: frame %d has no REFLECTIVITY channel; intensity set to 0", self._pcap, index)
            inten, dtype = np.zeros((h, w), np.float32), None
        ts = np.asarray(frame.timestamp, dtype=np.int64)
        valid = ts > 0
        t0 = int(ts[valid].min()) if valid.any() else 0
        col_t = np.where(valid, (ts - t0) * 1e-9, 0.0).astype(np.float32)
        time = destagger(self._info, np.ascontiguousarray(np.broadcast_to(col_t, (h, w))))
        return Scan(
            xyz=xyz.reshape(-1, 3),
            intensity=inten.reshape(-1),
            ring=np.repeat(np.arange(h, dtype=np.int16), w),
            time=time.reshape(-1),
            shape=(h, w),
            sensor=self._sensor_info(dtype),
            timestamp=t0 * 1e-9 if valid.any() else None,
            source=f"{self._pcap}#{index}",
        )

    @property
    def timestamps(self) -> np.ndarray:
        """Sensor time (s) of the first valid column of every frame; decodes each frame once."""
        if self._timestamps is None:
            out = np.full(self._n, np.nan)
            for i in range(self._n):
                ts = np.asarray(self._frame(i).timestamp, dtype=np.int64)
                if (ts > 0).any():
                    out[i] = ts[ts > 0].min() * 1e-9
            self._timestamps = out
        return self._timestamps

    @property
    def poses(self) -> np.ndarray | None:
        """(N, 4, 4) ``T_world_sensor`` of every frame, or None without a poses file."""
        return self._poses

    @property
    def name(self) -> str:
        return self._pcap.stem

    @property
    def metadata_path(self) -> Path:
        return self._meta

    def close(self) -> None:
        self._src.close()

    def __enter__(self) -> OusterSequence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_ouster_pcap(pcap: str | Path, metadata: str | Path | None = None) -> list[Scan]:
    """Decode every frame of an Ouster ``.pcap`` (see `OusterSequence`)."""
    with OusterSequence(pcap, metadata) as seq:
        return [seq[i] for i in range(len(seq))]
