"""ROS1 (``.bag``) and ROS2 (rosbag2 folder) recordings of ``sensor_msgs/PointCloud2`` and Livox
``CustomMsg`` (`placerec.io.livox`) through rosbags.

`pointcloud2_to_scan` decodes a message with one strided structured view of its data (fields by
offset/datatype/count, ``point_step``, ``row_step``, ``is_bigendian``): intensity from intensity, reflectivity
or i; ``ring``; ``t``/``time`` (integer times are nanoseconds, as the Ouster driver's ``t``). The Livox drivers'
layout (fields ``tag`` and ``line``, float64 ``timestamp``) gets ring = line and times from ``timestamp``
(`placerec.io.livox.livox_pointcloud2_scan`).
"""

from __future__ import annotations

import logging
import sqlite3
import struct
from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import DependencyError, ScanFormatError
from placerec.io._common import columns_to_scan, structured_columns
from placerec.io.livox import (
    LIVOX_CUSTOM_MSGS,
    check_custom_layout,
    custom_msg_to_scan,
    is_livox_pointcloud2,
    livox_pointcloud2_scan,
    register_livox_types,
)
from placerec.safe_yaml import load_yaml_file
from placerec.types import Scan

__all__ = [
    "RosbagSequence",
    "pointcloud2_to_scan",
    "header_stamp",
    "same_time_ranks",
    "message_index",
    "POINTCLOUD2",
    "CLOUD_MSGTYPES",
]

log = logging.getLogger(__name__)

# what rosbags lets through for a damaged bag: an empty or malformed metadata.yaml (TypeError, KeyError), a
# corrupt rosbag2 .db3 (sqlite3.Error), truncated records (struct.error, IndexError)
_BAG_ERRORS = (OSError, ValueError, KeyError, TypeError, IndexError, struct.error, sqlite3.Error)

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
#: message types a bag topic of point clouds may carry
CLOUD_MSGTYPES: tuple[str, ...] = (POINTCLOUD2, *LIVOX_CUSTOM_MSGS)
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud2_to_scan(
    msg: Any, where: str, *, organized: bool = False, timestamp: float | None = None
) -> Scan:
    """Decode a PointCloud2 message (any object with its fields) into a `Scan`, vectorised (the Livox driver
    layout: `placerec.io.livox`)."""
    order = ">" if msg.is_bigendian else "<"
    step, row_step = int(msg.point_step), int(msg.row_step)
    h, w = int(msg.height), int(msg.width)
    names, formats, offsets = [], [], []
    for f in msg.fields:
        if f.datatype not in _DATATYPES:
            raise ScanFormatError(f"{where}: PointCloud2 field {f.name!r} has unknown datatype {f.datatype}")
        dt = np.dtype(order + _DATATYPES[f.datatype])
        count = max(int(f.count), 1)
        if f.offset < 0 or f.offset + dt.itemsize * count > step:
            raise ScanFormatError(
                f"{where}: PointCloud2 field {f.name!r} (offset {f.offset}, {count} x "
                f"{dt.itemsize} bytes) does not fit in point_step {step}"
            )
        names.append(f.name)
        formats.append(dt if count == 1 else (dt, (count,)))
        offsets.append(int(f.offset))
    livox = is_livox_pointcloud2(list(msg.fields), where)
    if h * w and row_step < w * step:
        raise ScanFormatError(f"{where}: PointCloud2 row_step {row_step} < width {w} x point_step {step}")
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    need = (h - 1) * row_step + w * step if h * w else 0
    if data.size < need:
        raise ScanFormatError(
            f"{where}: PointCloud2 data has {data.size} bytes, expected {need} "
            f"({h} x {w} points, point_step {step}, row_step {row_step})"
        )
    try:
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": max(step, 1)})
    except ValueError as exc:
        raise ScanFormatError(f"{where}: PointCloud2 fields cannot be decoded ({exc})") from None
    if h * w:
        arr = np.ndarray((h, w), dtype=dtype, buffer=data, strides=(row_step, step))
    else:
        arr = np.empty((h, w), dtype=dtype)
    shape = (h, w) if organized and h > 1 else None
    if livox:
        return livox_pointcloud2_scan(structured_columns(arr), where, shape=shape, timestamp=timestamp)
    return columns_to_scan(structured_columns(arr), where, shape=shape, timestamp=timestamp)


def _check_rosbag2_metadata(folder: Path) -> None:
    """ScanFormatError naming ``metadata.yaml`` when it is not a rosbag2 metadata mapping (rosbags would fail
    with a bare TypeError on an empty file)."""
    meta = folder / "metadata.yaml"
    d = load_yaml_file(meta, ScanFormatError)
    if not isinstance(d, dict) or not isinstance(d.get("rosbag2_bagfile_information"), dict):
        if d is None:
            got = "an empty file"
        elif isinstance(d, dict):
            got = f"the keys {sorted(map(str, d))[:10]}"
        else:
            got = f"a {type(d).__name__}"
        raise ScanFormatError(
            f"{meta}: not rosbag2 metadata (expected a mapping with the key 'rosbag2_bagfile_information', got "
            f"{got})"
        )


def _rosbags() -> tuple[Any, Any, Any]:
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise DependencyError(
            f"reading rosbags needs the rosbags package ({exc}); install it with: pip install placerec[ros]"
        ) from exc
    # the default typestore (for rosbag2 bags without message definitions) knows the Livox CustomMsg types too
    return AnyReader, AnyReaderError, register_livox_types(get_typestore(Stores.LATEST))


def header_stamp(raw: bytes | memoryview, ros2: bool) -> float:
    """Header stamp (s) read straight from the serialized message (the header is its first field)."""
    if ros2:  # CDR: 4-byte encapsulation header (byte 1: 1 = little endian), then int32 sec, uint32 nanosec
        endian = "<" if raw[1] == 1 else ">"
        sec, nsec = struct.unpack_from(endian + "iI", raw, 4)
    else:  # ROS1: uint32 seq, uint32 secs, uint32 nsecs
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec + nsec * 1e-9


def same_time_ranks(log_times: np.ndarray) -> np.ndarray:
    """Rank of each message among those sharing its (sorted) log time, to pick it out of a time-window query."""
    return np.arange(log_times.size) - np.searchsorted(log_times, log_times, side="left")


def message_index(index: int, n: int, topic: str) -> int:
    """``index`` (negative counts from the end) checked against ``n`` messages; IndexError outside."""
    if index < 0:
        index += n
    if not 0 <= index < n:
        raise IndexError(f"message {index} out of range ({n} messages on {topic})")
    return index


def choose_topic(path: Path, topics: list[str], topic: str | None, kind: str = "PointCloud2") -> str:
    """``topic`` if it is one of the file's point-cloud ``topics`` (of ``kind``, for the message), or the only
    one when ``topic`` is None; `ScanFormatError` naming ``path`` otherwise."""
    if topic is None:
        if len(topics) != 1:
            raise ScanFormatError(f"{path}: {len(topics)} {kind} topics {topics}; pass topic=")
        return topics[0]
    if topic not in topics:
        raise ScanFormatError(f"{path}: no {kind} topic {topic!r} ({kind} topics: {topics})")
    return topic


class PointCloud2Topic:
    """What a sequence of one PointCloud2 topic of a recording file reports (a subclass sets ``_path``,
    ``_topic`` and ``_stamps``): header-stamp timestamps, no poses, a name of file stem and topic."""

    _path: Path
    _topic: str
    _stamps: np.ndarray

    @property
    def timestamps(self) -> np.ndarray:
        return self._stamps

    @property
    def poses(self) -> None:
        return None

    @property
    def name(self) -> str:
        return f"{self._path.stem}:{self._topic}"

    @property
    def topic(self) -> str:
        return self._topic


class RosbagSequence(PointCloud2Topic):
    """PointCloud2 or Livox CustomMsg messages of one topic of a ROS1 ``.bag`` or rosbag2 folder (sqlite3 or
    mcap storage), as a lazy `Sequence`.

    ``topic`` may be omitted when the bag has exactly one point-cloud topic (PointCloud2 or CustomMsg).
    Timestamps are the messages' header stamps; poses are None. Messages are indexed once on opening (their
    stamps are read from the raw bytes) and decoded on access. A CustomMsg topic is checked against the Livox
    layout on opening (the bag's own definition when it carries one, else placerec's: `placerec.io.livox`) and
    its points are decoded from the raw bytes. Use as a context manager or call `close`.
    """

    def __init__(self, path: str | Path, topic: str | None = None, *, organized: bool = False) -> None:
        AnyReader, AnyReaderError, typestore = _rosbags()
        self._read_errors = (AnyReaderError, *_BAG_ERRORS)
        self._path = Path(path)
        self._organized = organized
        if self._path.is_dir():
            _check_rosbag2_metadata(self._path)
        try:
            self._reader = AnyReader([self._path], default_typestore=typestore)
            self._reader.open()
        except (AnyReaderError, *_BAG_ERRORS) as exc:
            raise ScanFormatError(
                f"{self._path}: cannot open as a rosbag ({type(exc).__name__}: {exc})"
            ) from exc
        clouds = [c for c in self._reader.connections if c.msgtype in CLOUD_MSGTYPES]
        livox = any(c.msgtype != POINTCLOUD2 for c in clouds)
        kind = "point-cloud (PointCloud2 or Livox CustomMsg)" if livox else "PointCloud2"
        try:
            topic = choose_topic(self._path, sorted({c.topic for c in clouds}), topic, kind)
            self._conns = [c for c in clouds if c.topic == topic]
            self._topic = topic
            self._msgtype = self._topic_msgtype()
        except ScanFormatError:
            self.close()
            raise
        log_times, stamps = [], []
        try:
            for _, t, raw in self._reader.messages(connections=self._conns):
                log_times.append(t)
                stamps.append(header_stamp(raw, self._reader.is2))
        except (AnyReaderError, *_BAG_ERRORS) as exc:
            self.close()
            raise ScanFormatError(f"{self._path}: cannot index topic {topic} ({exc})") from exc
        if not log_times:
            self.close()
            raise ScanFormatError(f"{self._path}: topic {topic!r} has no messages: no scans")
        self._log_times = np.asarray(log_times, dtype=np.int64)
        self._stamps = np.asarray(stamps, dtype=np.float64)
        self._rank = same_time_ranks(self._log_times)

    def _topic_msgtype(self) -> str:
        """The one message type of the chosen topic's connections; a CustomMsg one checked against the Livox
        layout."""
        types = sorted({c.msgtype for c in self._conns})
        if len(types) != 1:
            raise ScanFormatError(
                f"{self._path}: topic {self._topic!r} carries several message types {types}"
            )
        if types[0] != POINTCLOUD2:
            check_custom_layout(self._reader.typestore.FIELDDEFS, types[0], f"{self._path}:{self._topic}")
        return types[0]

    def __len__(self) -> int:
        return int(self._log_times.size)

    def __getitem__(self, index: int) -> Scan:
        index = message_index(index, len(self), self._topic)
        t = int(self._log_times[index])
        where = f"{self._path}:{self._topic}#{index}"
        try:
            if not self._reader.isopen:
                self._reader.open()
            # from t - 1: rosbags' mcap storage skips a chunk whose last message is at exactly ``start``
            same_time = (
                (conn, raw)
                for conn, lt, raw in self._reader.messages(
                    connections=self._conns, start=max(t - 1, 0), stop=t + 1
                )
                if lt == t
            )
            found = [m for k, m in enumerate(same_time) if k == self._rank[index]]
            custom = bool(found) and self._msgtype != POINTCLOUD2
            msg = self._reader.deserialize(found[0][1], found[0][0].msgtype) if found and not custom else None
        except self._read_errors as exc:
            what = "PointCloud2" if self._msgtype == POINTCLOUD2 else "CustomMsg"
            raise ScanFormatError(f"{where}: cannot read {what} ({type(exc).__name__}: {exc})") from exc
        if custom:
            return custom_msg_to_scan(found[0][1], self._reader.is2, where)
        if msg is not None:
            return pointcloud2_to_scan(
                msg, where, organized=self._organized, timestamp=float(self._stamps[index])
            )
        raise ScanFormatError(f"{where}: message not found again in the bag")  # pragma: no cover

    def close(self) -> None:
        if getattr(self, "_reader", None) is not None and self._reader.isopen:
            self._reader.close()

    def __enter__(self) -> RosbagSequence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
