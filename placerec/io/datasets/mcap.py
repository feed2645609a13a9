"""A standalone ROS 2 ``.mcap`` recording (no rosbag2 ``metadata.yaml`` beside it): the ``sensor_msgs/PointCloud2``
or Livox ``CustomMsg`` (`placerec.io.livox`) messages of one topic, read with the ``mcap`` package and decoded with
rosbags' CDR deserialiser or placerec's Livox decoder (no ROS install). A ``.mcap`` inside a rosbag2 folder is
opened as that bag (`placerec.io.rosbag.RosbagSequence`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from placerec.errors import DependencyError, ScanFormatError
from placerec.io.livox import LIVOX_CUSTOM_MSGS, check_custom_layout, custom_msg_to_scan
from placerec.io.rosbag import (
    POINTCLOUD2,
    PointCloud2Topic,
    choose_topic,
    header_stamp,
    message_index,
    pointcloud2_to_scan,
    same_time_ranks,
)
from placerec.types import Scan

__all__ = ["McapSequence", "detect_mcap"]

_SCHEMA = "sensor_msgs/msg/PointCloud2"
_CLOUD_SCHEMAS = (_SCHEMA, *LIVOX_CUSTOM_MSGS)
#: the line between the definitions of a ``ros2msg`` schema and of the types it uses
_SEPARATOR = "=" * 80


def _schema_types(name: str, text: str) -> dict[str, Any]:
    """The field definitions of a ``ros2msg`` schema (``name`` first, then each ``MSG: type`` section)."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    for k, part in enumerate(text.split(_SEPARATOR)):
        lines = part.strip().splitlines()
        if k > 0:
            if not lines or not lines[0].startswith("MSG: "):
                continue
            part_name, lines = lines[0][5:].strip(), lines[1:]
        else:
            part_name = name
        types.update(get_types_from_msg("\n".join(lines), part_name))
    return types


def detect_mcap(path: Path) -> bool:
    """A ``.mcap`` file with no rosbag2 ``metadata.yaml`` beside it."""
    return path.is_file() and path.suffix.lower() == ".mcap" and not (path.parent / "metadata.yaml").is_file()


def _modules() -> tuple[Any, Any]:
    try:
        from mcap.reader import make_reader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise DependencyError(
            f"reading .mcap files needs the mcap and rosbags packages ({exc}); install them with: "
            "pip install placerec[ros]"
        ) from exc
    return make_reader, get_typestore(Stores.LATEST)


class McapSequence(PointCloud2Topic):
    """PointCloud2 or Livox CustomMsg messages of one topic of a ``.mcap`` file, as a lazy `Sequence` (poses None,
    timestamps the header stamps). ``topic`` may be left out when the file has one point-cloud topic. A CustomMsg
    schema is checked against the Livox layout when the file is opened. Messages are indexed
    (file offsets of their chunks are not kept: the file is re-read from the message's log time on access)."""

    def __init__(self, path: str | Path, topic: str | None = None, *, organized: bool = False) -> None:
        make_reader, self._typestore = _modules()
        self._path = Path(path)
        self._organized = organized
        self._make_reader = make_reader
        try:
            with open(self._path, "rb") as fh:
                reader = make_reader(fh)
                summary = reader.get_summary()
                if summary is None:
                    raise ScanFormatError(f"{self._path}: .mcap file without a summary section (not indexed)")
                schemas = {k: s for k, s in summary.schemas.items() if s.name in _CLOUD_SCHEMAS}
                topics = sorted({c.topic for c in summary.channels.values() if c.schema_id in schemas})
                topic = choose_topic(self._path, topics, topic)
                schema = next(schemas[c.schema_id] for c in summary.channels.values() if c.topic == topic)
                self._livox = schema.name in LIVOX_CUSTOM_MSGS
                if self._livox and schema.data:
                    types = _schema_types(schema.name, bytes(schema.data).decode("utf-8", "replace"))
                    check_custom_layout(types, schema.name, f"{self._path}:{topic}")
                times, stamps = [], []
                for _, _, msg in reader.iter_messages(topics=[topic], log_time_order=True):
                    times.append(msg.log_time)
                    stamps.append(header_stamp(msg.data, True))
        except ScanFormatError:
            raise
        except Exception as exc:  # the mcap reader raises its own errors, struct.error, EOFError...
            raise ScanFormatError(
                f"{self._path}: cannot read as .mcap ({type(exc).__name__}: {exc})"
            ) from exc
        if not times:
            raise ScanFormatError(f"{self._path}: topic {topic!r} has no messages: no scans")
        self._topic = topic
        self._times = np.asarray(times, dtype=np.int64)
        self._stamps = np.asarray(stamps, dtype=np.float64)
        self._rank = same_time_ranks(self._times)

    def __len__(self) -> int:
        return int(self._times.size)

    def __getitem__(self, index: int) -> Scan:
        index = message_index(index, len(self), self._topic)
        t = int(self._times[index])
        where = f"{self._path}:{self._topic}#{index}"
        try:
            with open(self._path, "rb") as fh:
                found = [
                    m.data
                    for k, (_, _, m) in enumerate(
                        self._make_reader(fh).iter_messages(
                            topics=[self._topic], starting_at=t, ending_before=t + 1, log_time_order=True
                        )
                    )
                    if k == self._rank[index]
                ]
            if found and self._livox:
                return custom_msg_to_scan(found[0], True, where)
            msg = self._typestore.deserialize_cdr(found[0], POINTCLOUD2) if found else None
        except ScanFormatError:
            raise
        except Exception as exc:
            raise ScanFormatError(f"{where}: cannot read PointCloud2 ({type(exc).__name__}: {exc})") from exc
        if msg is None:
            raise ScanFormatError(f"{where}: message not found again in the file")  # pragma: no cover
        return pointcloud2_to_scan(
            msg, where, organized=self._organized, timestamp=float(self._stamps[index])
        )
