"""Livox recordings: ``livox_ros_driver2/msg/CustomMsg`` (and the older ``livox_ros_driver/msg/CustomMsg``) and
the ``sensor_msgs/PointCloud2`` layout the Livox drivers write, decoded into `Scan` s.

CustomMsg
---------
``std_msgs/Header header, uint64 timebase, uint32 point_num, uint8 lidar_id, uint8[3] rsvd, CustomPoint[] points``
with ``CustomPoint`` = ``uint32 offset_time, float32 x, y, z, uint8 reflectivity, tag, line``. The points array is
decoded straight from the serialised bytes with one numpy structured view (no per-point Python objects): 19
packed bytes a point in ROS 1, 20 in CDR (ROS 2), where each point is aligned to 4 bytes (its ``uint32``), so the
last point has no padding after it. A `Scan` gets xyz; intensity = reflectivity (``intensity_max`` 255); ring =
line; time = ``offset_time`` x 1e-9 s (since ``timebase``, the time of the frame's first point); timestamp = the
header stamp (the drivers set it to ``timebase``; the header stamp is what every bag topic's sequence timestamps
are, so both message types agree); sensor ``SensorInfo(name="livox-<lidar_id>", pattern="non-repetitive")``.

A definition of CustomMsg / CustomPoint that differs from the above in any field (name, type or order) is an
unknown layout and a `ScanFormatError` naming the field; a bag without a definition is read with ours.

PointCloud2 (driver layout)
---------------------------
Fields x, y, z, intensity (float32 reflectivity), tag, line (uint8) and, from livox_ros_driver2, ``timestamp``
(float64, absolute nanoseconds; point_step 26). A PointCloud2 with both ``tag`` and ``line`` is taken as this
layout: ring = line, time = (timestamp - the first point's timestamp) x 1e-9 s (the driver stamps the header with
that first point's time, so this is the time since the header stamp, robust to a header restamped with another
clock), pattern "non-repetitive". ``tag``/``line`` other than uint8 or ``timestamp`` other than float64 are a
`ScanFormatError` naming the field.

Tag bits
--------
The Livox ``tag`` byte: bits 0-1 point property from its spatial position (00 normal, 01/10/11 noise of high /
moderate / low confidence), bits 2-3 from its intensity (00 normal, 01 noise: dust, rain, fog), bits 4-5 the
return number, bits 6-7 reserved. No point is dropped for its tag (a filter would change what a scan holds with
the sensor's firmware); points at the origin (no return) are invalid returns that placerec's valid-point mask
already leaves out.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any

import numpy as np

from placerec.errors import ScanFormatError
from placerec.io._common import columns_to_scan
from placerec.io.limits import check_size
from placerec.types import Scan, SensorInfo

__all__ = [
    "LIVOX_CUSTOM_MSGS",
    "CUSTOM_MSG_DEF",
    "CUSTOM_POINT_DEF",
    "livox_types",
    "register_livox_types",
    "check_custom_layout",
    "decode_custom_points",
    "custom_msg_to_scan",
    "is_livox_pointcloud2",
    "livox_pointcloud2_scan",
    "LIVOX_SENSOR_PATTERN",
]

#: the CustomMsg types of livox_ros_driver2 (Mid-360, HAP) and livox_ros_driver (Avia, Mid-40/70, Horizon...)
LIVOX_CUSTOM_MSGS: tuple[str, ...] = ("livox_ros_driver2/msg/CustomMsg", "livox_ros_driver/msg/CustomMsg")
LIVOX_SENSOR_PATTERN = "non-repetitive"

CUSTOM_MSG_DEF = """\
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""

CUSTOM_POINT_DEF = """\
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""

_BASE, _NAME, _ARRAY, _SEQUENCE = 1, 2, 3, 4  # rosbags' Nodetype values
#: CustomMsg fields: (name, type in .msg spelling as `_describe` writes rosbags' FIELDDEFS)
_MSG_FIELDS: tuple[tuple[str, str], ...] = (
    ("header", "std_msgs/msg/Header"),
    ("timebase", "uint64"),
    ("point_num", "uint32"),
    ("lidar_id", "uint8"),
    ("rsvd", "uint8[3]"),
    ("points", "CustomPoint[]"),
)
_POINT_FIELDS: tuple[tuple[str, str], ...] = (
    ("offset_time", "uint32"),
    ("x", "float32"),
    ("y", "float32"),
    ("z", "float32"),
    ("reflectivity", "uint8"),
    ("tag", "uint8"),
    ("line", "uint8"),
)
_POINT_BYTES = 19  # packed size of one CustomPoint


def _point_dtype(order: str) -> np.dtype:
    """One CustomPoint's fields (19 bytes; the array view's stride adds CDR's padding)."""
    return np.dtype(
        {
            "names": ["offset_time", "x", "y", "z", "reflectivity", "tag", "line"],
            "formats": [order + "u4", order + "f4", order + "f4", order + "f4", "u1", "u1", "u1"],
            "offsets": [0, 4, 8, 12, 16, 17, 18],
            "itemsize": _POINT_BYTES,
        }
    )


def livox_types() -> dict[str, Any]:
    """rosbags type definitions (``Typesdict``) of CustomMsg and CustomPoint under both Livox package names."""
    from rosbags.typesys import get_types_from_msg

    typs: dict[str, Any] = {}
    for msgtype in LIVOX_CUSTOM_MSGS:
        pkg = msgtype.split("/")[0]
        typs.update(get_types_from_msg(CUSTOM_POINT_DEF, f"{pkg}/msg/CustomPoint"))
        typs.update(get_types_from_msg(CUSTOM_MSG_DEF, msgtype))
    return typs


def register_livox_types(typestore: Any) -> Any:
    """Register the Livox types (`livox_types`) in a rosbags ``Typestore`` (no-op where they are already
    there); returns the typestore."""
    missing = {k: v for k, v in livox_types().items() if k not in typestore.FIELDDEFS}
    if missing:
        typestore.register(missing)
    return typestore


def _describe(node: Any) -> str:
    """A rosbags field type (``(nodetype, detail)``) in .msg spelling: ``uint32``, ``uint8[3]``, ``X[]``."""
    try:
        kind, detail = int(node[0]), node[1]
        if kind == _BASE:
            return str(detail[0])
        if kind == _NAME:
            return str(detail)
        if kind in (_ARRAY, _SEQUENCE):
            inner = _describe(detail[0])
            return f"{inner}[{int(detail[1])}]" if kind == _ARRAY else f"{inner}[]"
    except (TypeError, IndexError, ValueError):
        pass
    return repr(node)


def _check_fields(
    fields: list[tuple[str, Any]], expected: tuple[tuple[str, str], ...], typename: str, where: str
) -> None:
    got = [(str(name), _describe(node)) for name, node in fields]
    for k, (name, want) in enumerate(expected):
        if k >= len(got):
            raise ScanFormatError(
                f"{where}: unknown Livox layout: {typename} has no field {name!r} ({want}) after "
                f"{[g[0] for g in got]}"
            )
        have_name, have = got[k]
        if have_name != name:
            raise ScanFormatError(
                f"{where}: unknown Livox layout: {typename} field {k} is {have_name!r} ({have}), expected "
                f"{name!r} ({want})"
            )
        if (
            have != want
            and not (name == "points" and have.endswith("/CustomPoint[]"))
            and not (name == "header" and have in ("std_msgs/msg/Header", "std_msgs/Header"))
        ):
            raise ScanFormatError(
                f"{where}: unknown Livox layout: {typename} field {name!r} is {have}, expected {want}"
            )
    if len(got) > len(expected):
        extra = [g[0] for g in got[len(expected) :]]
        raise ScanFormatError(f"{where}: unknown Livox layout: {typename} has extra field(s) {extra}")


def check_custom_layout(fielddefs: Mapping[str, Any], msgtype: str, where: str) -> None:
    """`ScanFormatError` naming the first field where the definition of ``msgtype`` (and its point type) in
    ``fielddefs`` (a typestore's FIELDDEFS) differs from the Livox CustomMsg layout; a type absent from
    ``fielddefs`` (a bag without definitions) is taken to be ours."""
    if msgtype not in fielddefs:
        return
    fields = list(fielddefs[msgtype][1])
    _check_fields(fields, _MSG_FIELDS, msgtype, where)
    point_type = str(fields[-1][1][1][0][1])
    if point_type in fielddefs:
        _check_fields(list(fielddefs[point_type][1]), _POINT_FIELDS, point_type, where)


def _align(pos: int, n: int) -> int:
    return pos + (-pos) % n


def decode_custom_points(
    raw: bytes | memoryview, ros2: bool, where: str
) -> tuple[dict[str, Any], np.ndarray]:
    """The scalar fields (``sec``, ``nanosec``, ``timebase``, ``point_num``, ``lidar_id``) and the points (a
    structured array: offset_time, x, y, z, reflectivity, tag, line; a view of ``raw``) of a serialised
    CustomMsg. `ScanFormatError` naming ``where`` for truncated bytes, a points count over the scan load cap or
    beyond the message, or a ``point_num`` other than the number of points."""
    buf = memoryview(raw).cast("B")
    try:
        if ros2:  # CDR: 4-byte encapsulation header, then fields aligned to their size from byte 4
            order = "<" if buf[1] & 1 else ">"
            base = 4
            sec, nsec, slen = struct.unpack_from(order + "iII", buf, base)
            pos = 12 + slen
            pos = _align(pos, 8)
            (timebase,) = struct.unpack_from(order + "Q", buf, base + pos)
            pos += 8
            point_num, lidar_id = struct.unpack_from(order + "IB", buf, base + pos)
            pos += 4 + 1 + 3
            pos = _align(pos, 4)
            (n,) = struct.unpack_from(order + "I", buf, base + pos)
            start, stride = base + pos + 4, 20
        else:  # ROS1: packed little endian: uint32 seq, secs, nsecs, string frame_id, ...
            order = "<"
            _, sec, nsec, slen = struct.unpack_from("<IIII", buf, 0)
            pos = 16 + slen
            timebase, point_num, lidar_id = struct.unpack_from("<QIB", buf, pos)
            (n,) = struct.unpack_from("<I", buf, pos + 16)
            start, stride = pos + 20, _POINT_BYTES
    except struct.error:
        raise ScanFormatError(f"{where}: CustomMsg truncated ({len(buf)} bytes) before its points") from None
    check_size(n * _POINT_BYTES, where, f"CustomMsg points array ({n} points)", ScanFormatError, "scan")
    need = (n - 1) * stride + _POINT_BYTES if n else 0
    if start + need > len(buf):
        raise ScanFormatError(
            f"{where}: CustomMsg points array declares {n} points ({need} bytes), the message holds "
            f"{max(len(buf) - start, 0)} bytes after its header"
        )
    if point_num != n:
        raise ScanFormatError(
            f"{where}: CustomMsg point_num {point_num} but its points array holds {n} points"
        )
    dtype = _point_dtype(order)
    points = np.ndarray((n,), dtype=dtype, buffer=buf, offset=start, strides=(stride,))
    head = {"sec": sec, "nanosec": nsec, "timebase": timebase, "point_num": point_num, "lidar_id": lidar_id}
    return head, points


def custom_msg_to_scan(raw: bytes | memoryview, ros2: bool, where: str) -> Scan:
    """A serialised CustomMsg (ROS1 or CDR bytes) as a `Scan` (module docstring: field mapping, times)."""
    head, p = decode_custom_points(raw, ros2, where)
    xyz = np.empty((p.size, 3), dtype=np.float32)
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = p["x"], p["y"], p["z"]
    return Scan(
        xyz=xyz,
        intensity=p["reflectivity"].astype(np.float32),
        ring=p["line"].astype(np.int16),
        time=(p["offset_time"].astype(np.float64) * 1e-9).astype(np.float32),
        sensor=_sensor(int(head["lidar_id"])),
        timestamp=head["sec"] + head["nanosec"] * 1e-9,
        source=where,
    )


def _sensor(lidar_id: int | None) -> SensorInfo:
    name = "livox" if lidar_id is None else f"livox-{lidar_id}"
    return SensorInfo(name=name, intensity_max=255.0, pattern=LIVOX_SENSOR_PATTERN)


#: PointCloud2 datatype codes a Livox field must have (UINT8 = 2, FLOAT64 = 8)
_PC2_TYPES = {"tag": (2, "uint8"), "line": (2, "uint8"), "timestamp": (8, "float64")}
_PC2_NAMES = {
    1: "int8",
    2: "uint8",
    3: "int16",
    4: "uint16",
    5: "int32",
    6: "uint32",
    7: "float32",
    8: "float64",
}


def is_livox_pointcloud2(fields: list[Any], where: str) -> bool:
    """Whether a PointCloud2's ``fields`` are the Livox driver layout (both ``tag`` and ``line``);
    `ScanFormatError` naming the field when ``tag``, ``line`` or ``timestamp`` has another datatype then."""
    names = {str(f.name): f for f in fields}
    if "tag" not in names or "line" not in names:
        return False
    for name, (code, label) in _PC2_TYPES.items():
        f = names.get(name)
        if f is not None and (int(f.datatype) != code or max(int(f.count), 1) != 1):
            got = _PC2_NAMES.get(int(f.datatype), f"datatype {f.datatype}")
            raise ScanFormatError(
                f"{where}: Livox PointCloud2 field {name!r} is {got} x {f.count}, expected one {label}"
            )
    return True


def livox_pointcloud2_scan(
    columns: Mapping[str, np.ndarray],
    where: str,
    *,
    shape: tuple[int, int] | None = None,
    timestamp: float | None = None,
) -> Scan:
    """A `Scan` from the decoded columns of a Livox-layout PointCloud2 (ring = line, time from ``timestamp``
    relative to the first point; module docstring)."""
    stamps = columns.get("timestamp")
    dropped = ("tag", "line", "timestamp", "ring") + (("t", "time") if stamps is not None else ())
    cols = {k: v for k, v in columns.items() if k not in dropped}
    cols["ring"] = np.asarray(columns["line"]).astype(np.int16)
    if stamps is not None:
        s = np.asarray(stamps, dtype=np.float64)
        cols["time"] = ((s - s[0]) * 1e-9).astype(np.float32) if s.size else s.astype(np.float32)
    sensor = SensorInfo(
        name="livox",
        intensity_max=255.0,
        pattern=LIVOX_SENSOR_PATTERN,
        columns=None if shape is None else shape[1],
    )
    return columns_to_scan(cols, where, shape=shape, sensor=sensor, timestamp=timestamp)
