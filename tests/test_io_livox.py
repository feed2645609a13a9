"""Livox recordings (issue #28): CustomMsg (livox_ros_driver2 and livox_ros_driver) and the Livox drivers'
PointCloud2 layout in ROS1 bags and rosbag2 folders (sqlite3 and mcap storage), written with rosbags' own
writers (mcap: the mcap package) and read back through `open_sequence`."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from placerec.errors import ScanFormatError
from placerec.io import open_sequence
from placerec.io.livox import (
    CUSTOM_MSG_DEF,
    CUSTOM_POINT_DEF,
    LIVOX_CUSTOM_MSGS,
    custom_msg_to_scan,
    decode_custom_points,
    register_livox_types,
)
from placerec.io.rosbag import RosbagSequence, pointcloud2_to_scan

pytest.importorskip("rosbags", reason="rosbags not installed (pip install placerec[ros])")
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

V2, V1 = LIVOX_CUSTOM_MSGS
PC2 = "sensor_msgs/msg/PointCloud2"
T0 = 1_700_000_000


def _typestore(ros2: bool, point_def: str = CUSTOM_POINT_DEF, msg_def: str = CUSTOM_MSG_DEF) -> Any:
    """ROS2 Humble / ROS1 Noetic types with the Livox types (ours, or a variant definition)."""
    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    if point_def == CUSTOM_POINT_DEF and msg_def == CUSTOM_MSG_DEF:
        return register_livox_types(ts)
    for msgtype in LIVOX_CUSTOM_MSGS:
        pkg = msgtype.split("/")[0]
        ts.register(get_types_from_msg(point_def, f"{pkg}/msg/CustomPoint"))
        ts.register(get_types_from_msg(msg_def, msgtype))
    return ts


def _points(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    p = {c: rng.normal(0, 15, n).astype(np.float32) for c in "xyz"}
    p["offset_time"] = np.sort(rng.integers(0, 100_000_000, n)).astype(np.uint32)
    for c in ("reflectivity", "tag", "line"):
        p[c] = rng.integers(0, 256 if c != "line" else 6, n).astype(np.uint8)
    return p


def _header(ts: Any, sec: int, nsec: int, frame: str) -> Any:
    T = ts.types
    kw: dict[str, Any] = {"stamp": T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), "frame_id": frame}
    if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__:
        kw["seq"] = 7
    return T["std_msgs/msg/Header"](**kw)


def _custom(
    ts: Any, msgtype: str, p: dict[str, np.ndarray], sec: int, nsec: int, *, frame: str = "livox_frame",
    lidar_id: int = 3, point_num: int | None = None, point_fields: tuple[str, ...] | None = None,
) -> Any:  # fmt: skip
    T = ts.types
    Point = T[msgtype.replace("CustomMsg", "CustomPoint")]
    names = point_fields or tuple(k for k in Point.__dataclass_fields__ if not k.startswith("__"))
    n = len(p["x"])
    points = [Point(**{k: p[k][i].item() for k in names}) for i in range(n)]
    return T[msgtype](
        header=_header(ts, sec, nsec, frame),
        timebase=sec * 1_000_000_000 + nsec,
        point_num=n if point_num is None else point_num,
        lidar_id=lidar_id,
        rsvd=np.array([1, 2, 3], dtype=np.uint8),
        points=points,
    )


LIVOX_PC2 = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("tag", 16, 2), ("line", 17, 2),
             ("timestamp", 18, 8)]  # fmt: skip


def _livox_pc2(ts: Any, p: dict[str, np.ndarray], sec: int, nsec: int, fields=LIVOX_PC2) -> Any:
    """A PointCloud2 as livox_ros_driver2 writes it (packed 26-byte points, float64 absolute ns timestamp)."""
    T = ts.types
    n = len(p["x"])
    arr = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
                                      "formats": ["<f4"] * 4 + ["u1", "u1", "<f8"],
                                      "offsets": [0, 4, 8, 12, 16, 17, 18], "itemsize": 26}))  # fmt: skip
    for c in "xyz":
        arr[c] = p[c]
    arr["intensity"], arr["tag"], arr["line"] = p["reflectivity"], p["tag"], p["line"]
    arr["timestamp"] = (sec * 1_000_000_000 + nsec) + p["offset_time"].astype(np.float64)
    pf = [T["sensor_msgs/msg/PointField"](name=a, offset=o, datatype=d, count=1) for a, o, d in fields]
    return T[PC2](
        header=_header(ts, sec, nsec, "livox_frame"), height=1, width=n, fields=pf, is_bigendian=False,
        point_step=26, row_step=26 * n, data=np.frombuffer(arr.tobytes(), np.uint8).copy(), is_dense=True,
    )  # fmt: skip


def _write(path: Path, ros2: bool, topics: dict[str, tuple[str, list[Any]]], ts: Any) -> Path:
    """A ROS1 bag or rosbag2 (sqlite3) folder: topic -> (msgtype, messages)."""
    if ros2:
        from rosbags.rosbag2 import Writer
    else:
        from rosbags.rosbag1 import Writer  # type: ignore[assignment]
    ser = ts.serialize_cdr if ros2 else ts.serialize_ros1
    with Writer(path) as w:
        for topic, (msgtype, msgs) in topics.items():
            conn = w.add_connection(topic, msgtype, typestore=ts)
            for k, m in enumerate(msgs):
                w.write(conn, 5_000_000_000 + k * 100_000_000, ser(m, msgtype))
    return path


def _write_mcap_bag(path: Path, topics: dict[str, tuple[str, list[Any]]], ts: Any, msgdefs: bool) -> Path:
    """A rosbag2 folder with mcap storage: the metadata.yaml of a sqlite3 bag of the same topics, pointed at an
    mcap file (schemas with the message definitions, or empty ones: a bag without definitions)."""
    import yaml
    from mcap.writer import Writer

    tmp = _write(path.parent / (path.name + "_sqlite"), True, topics, ts)
    meta = yaml.safe_load((tmp / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    info["storage_identifier"] = "mcap"
    info["relative_file_paths"] = [f"{path.name}_0.mcap"]
    info.pop("files", None)
    path.mkdir()
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with open(path / f"{path.name}_0.mcap", "wb") as fh:
        w = Writer(fh)
        w.start("ros2", "placerec-test")
        for topic, (msgtype, msgs) in topics.items():
            text = ts.generate_msgdef(msgtype, ros_version=2)[0] if msgdefs else ""
            schema = w.register_schema(msgtype, "ros2msg", text.encode())
            chan = w.register_channel(topic, "cdr", schema)
            for k, m in enumerate(msgs):
                t = 5_000_000_000 + k * 100_000_000
                w.add_message(chan, log_time=t, data=bytes(ts.serialize_cdr(m, msgtype)), publish_time=t)
        w.finish()
    return path


def _check_scan(scan: Any, p: dict[str, np.ndarray], sec: int, nsec: int, name: str = "livox-3") -> None:
    np.testing.assert_array_equal(scan.xyz, np.stack([p["x"], p["y"], p["z"]], 1))
    np.testing.assert_array_equal(scan.intensity, p["reflectivity"].astype(np.float32))
    np.testing.assert_array_equal(scan.ring, p["line"])
    np.testing.assert_allclose(scan.time, p["offset_time"] * 1e-9, rtol=1e-6, atol=1e-9)
    assert scan.timestamp == pytest.approx(sec + nsec * 1e-9, abs=1e-6)
    assert scan.sensor.pattern == "non-repetitive" and scan.sensor.intensity_max == 255
    assert scan.sensor.name == name and not scan.sensor.is_spinning


STORAGES = ["ros1", "ros2-sqlite3", "ros2-mcap", "ros2-mcap-no-msgdef"]


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("msgtype", LIVOX_CUSTOM_MSGS, ids=["driver2", "driver1"])
def test_custom_msg_round_trip(tmp_path: Path, storage: str, msgtype: str) -> None:
    ros2 = storage != "ros1"
    ts = _typestore(ros2)
    rng = np.random.default_rng(1)
    clouds = [_points(rng, n) for n in (300, 1, 0, 77)]
    stamps = [(T0 + k, 1000 * k + 5) for k in range(len(clouds))]
    msgs = [
        _custom(ts, msgtype, p, s, ns, frame="f" * k)
        for k, (p, (s, ns)) in enumerate(zip(clouds, stamps, strict=True))
    ]
    topics = {"/livox/lidar": (msgtype, msgs)}
    if storage.startswith("ros2-mcap"):
        path = _write_mcap_bag(tmp_path / "bag", topics, ts, msgdefs=storage == "ros2-mcap")
    else:
        path = _write(tmp_path / ("bag" if ros2 else "rec.bag"), ros2, topics, ts)
    seq = open_sequence(path)
    try:
        assert isinstance(seq, RosbagSequence) and len(seq) == 4 and seq.topic == "/livox/lidar"
        np.testing.assert_allclose(seq.timestamps, [s + ns * 1e-9 for s, ns in stamps], atol=1e-6, rtol=0)
        for k, p in enumerate(clouds):
            _check_scan(seq[k], p, *stamps[k])
    finally:
        seq.close()


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "cdr-le"])
def test_raw_decoding_matches_the_typestore(ros2: bool) -> None:
    """The numpy view of the points array (19 packed bytes in ROS1, 20-byte aligned records in CDR) against
    rosbags' own deserialisation, for header frame ids of every length modulo the alignments."""
    ts = _typestore(ros2)
    rng = np.random.default_rng(2)
    for endian in [True, False] if ros2 else [True]:
        for k in range(9):
            p = _points(rng, 5 + k)
            m = _custom(ts, V2, p, T0, 9, frame="x" * k, lidar_id=k)
            raw = bytes(ts.serialize_cdr(m, V2, little_endian=endian) if ros2 else ts.serialize_ros1(m, V2))
            back = ts.deserialize_cdr(raw, V2) if ros2 else ts.deserialize_ros1(raw, V2)
            head, pts = decode_custom_points(raw, ros2, "m")
            assert head["timebase"] == back.timebase and head["point_num"] == back.point_num
            assert head["lidar_id"] == k
            for name in ("offset_time", "x", "y", "z", "reflectivity", "tag", "line"):
                np.testing.assert_array_equal(
                    pts[name], [getattr(q, name) for q in back.points], err_msg=name
                )
            _check_scan(custom_msg_to_scan(raw, ros2, "m"), p, T0, 9, name=f"livox-{k}")


@pytest.mark.parametrize("storage", ["ros1", "ros2-sqlite3"])
def test_livox_pointcloud2(tmp_path: Path, storage: str) -> None:
    ros2 = storage != "ros1"
    ts = _typestore(ros2)
    rng = np.random.default_rng(3)
    p = _points(rng, 200)
    path = _write(tmp_path / ("bag" if ros2 else "pc.bag"), ros2, {"/livox/points": (PC2, [_livox_pc2(ts, p, T0, 500)])}, ts)  # fmt: skip
    with open_sequence(path) as seq:
        scan = seq[0]
    p["offset_time"] -= p["offset_time"][0]  # time is relative to the first point
    np.testing.assert_array_equal(scan.xyz, np.stack([p["x"], p["y"], p["z"]], 1))
    np.testing.assert_array_equal(scan.intensity, p["reflectivity"].astype(np.float32))
    np.testing.assert_array_equal(scan.ring, p["line"])
    # float64 absolute nanoseconds keep ~256 ns
    np.testing.assert_allclose(scan.time, p["offset_time"] * 1e-9, rtol=0, atol=1e-6)
    assert scan.time[0] == 0 and scan.timestamp == pytest.approx(T0 + 500e-9)
    assert scan.sensor.pattern == "non-repetitive" and scan.sensor.intensity_max == 255
    # the driver-1 layout (no timestamp field): ring from line, no times
    no_time = _livox_pc2(ts, p, T0, 0, fields=LIVOX_PC2[:-1])
    scan = pointcloud2_to_scan(no_time, "m")
    assert scan.time is None and scan.sensor.pattern == "non-repetitive"
    np.testing.assert_array_equal(scan.ring, p["line"])


def test_other_pointcloud2_layouts_unchanged() -> None:
    """A PointCloud2 with ``line`` but no ``tag`` (not the Livox layout) decodes as before."""
    a = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("line", "<f4")])
    a["x"] = 1
    pf = [SimpleNamespace(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
    pf.append(SimpleNamespace(name="line", offset=12, datatype=7, count=1))
    msg = SimpleNamespace(height=1, width=4, fields=pf, is_bigendian=False, point_step=16, row_step=64,
                          data=np.frombuffer(a.tobytes(), np.uint8))  # fmt: skip
    scan = pointcloud2_to_scan(msg, "m")
    assert scan.ring is None and scan.sensor.pattern is None


def test_topic_choice(tmp_path: Path) -> None:
    ts = _typestore(False)
    rng = np.random.default_rng(4)
    p = _points(rng, 10)
    path = _write(tmp_path / "both.bag", False, {
        "/livox/lidar": (V1, [_custom(ts, V1, p, T0, 0)]),
        "/livox/points": (PC2, [_livox_pc2(ts, p, T0, 0)]),
        "/imu": ("std_msgs/msg/String", [ts.types["std_msgs/msg/String"](data="x")]),
    }, ts)  # fmt: skip
    with pytest.raises(ScanFormatError, match="pass topic=") as err:
        open_sequence(path)
    assert (
        "/livox/lidar" in str(err.value)
        and "/livox/points" in str(err.value)
        and "/imu" not in str(err.value)
    )
    with pytest.raises(ScanFormatError, match="no point-cloud .* topic '/imu'"):
        open_sequence(path, topic="/imu")
    with open_sequence(path, topic="/livox/lidar") as seq:
        _check_scan(seq[0], p, T0, 0)
    with open_sequence(path, topic="/livox/points") as seq:
        assert seq[0].sensor.name == "livox" and len(seq[0]) == 10


# ---------------------------------------------------------------------------------------------------- bad input
BAD_LAYOUTS = {
    "offset_time": CUSTOM_POINT_DEF.replace("uint32 offset_time\n", ""),
    "offset_time-float64": CUSTOM_POINT_DEF.replace("uint32 offset_time", "float64 offset_time"),
    "line-uint16": CUSTOM_POINT_DEF.replace("uint8 line", "uint16 line"),
}


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
@pytest.mark.parametrize("case", sorted(BAD_LAYOUTS))
def test_unknown_custom_layout(tmp_path: Path, ros2: bool, case: str) -> None:
    """A bag whose own CustomMsg definition differs from the Livox layout: an error naming the field, the file
    and the topic, on opening."""
    ts = _typestore(ros2, point_def=BAD_LAYOUTS[case])
    p = _points(np.random.default_rng(5), 6)
    names = tuple(
        k for k in ts.types[V2.replace("CustomMsg", "CustomPoint")].__dataclass_fields__ if k[0] != "_"
    )
    path = tmp_path / ("bag" if ros2 else "bad.bag")
    _write(path, ros2, {"/livox/lidar": (V2, [_custom(ts, V2, p, T0, 0, point_fields=names)])}, ts)
    field = case.split("-")[0]
    with pytest.raises(ScanFormatError, match=field) as err:
        open_sequence(path)
    assert (
        str(path) in str(err.value) and "/livox/lidar" in str(err.value) and "Livox layout" in str(err.value)
    )


def test_unknown_custom_msg_field(tmp_path: Path) -> None:
    ts = _typestore(False, msg_def=CUSTOM_MSG_DEF.replace("uint32 point_num", "uint16 point_num"))
    p = _points(np.random.default_rng(6), 3)
    path = _write(tmp_path / "bad.bag", False, {"/l": (V1, [_custom(ts, V1, p, T0, 0)])}, ts)
    with pytest.raises(ScanFormatError, match="'point_num' is uint16, expected uint32"):
        open_sequence(path)


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_point_num_mismatch(tmp_path: Path, ros2: bool) -> None:
    ts = _typestore(ros2)
    p = _points(np.random.default_rng(7), 8)
    path = tmp_path / ("bag" if ros2 else "pn.bag")
    _write(path, ros2, {"/l": (V2, [_custom(ts, V2, p, T0, 0, point_num=9)])}, ts)
    with open_sequence(path) as seq, pytest.raises(ScanFormatError, match="point_num 9") as err:
        seq[0]
    assert str(path) in str(err.value) and "8 points" in str(err.value)


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_hostile_raw_custom_msg(ros2: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A points count over the scan load cap, one beyond the message, and truncated bytes."""
    ts = _typestore(ros2)
    p = _points(np.random.default_rng(8), 4)
    m = _custom(ts, V2, p, T0, 0, frame="ab")
    raw = bytearray(ts.serialize_cdr(m, V2) if ros2 else ts.serialize_ros1(m, V2))
    # the uint32 points count sits just before the points: 4 x 20 - 1 (CDR) or 4 x 19 (ROS1) bytes from the end
    at = len(raw) - (4 * 20 - 1 if ros2 else 4 * 19) - 4
    assert int.from_bytes(raw[at : at + 4], "little") == 4
    raw[at : at + 4] = (0xFFFFFFF0).to_bytes(4, "little")
    with pytest.raises(ScanFormatError, match="over the scan load cap"):
        custom_msg_to_scan(bytes(raw), ros2, "m")
    raw[at : at + 4] = (5).to_bytes(4, "little")
    with pytest.raises(ScanFormatError, match="declares 5 points"):
        custom_msg_to_scan(bytes(raw), ros2, "m")
    with pytest.raises(ScanFormatError, match="truncated"):
        custom_msg_to_scan(bytes(raw[:20]), ros2, "m")


@pytest.mark.parametrize("field,datatype", [("line", 7), ("tag", 4), ("timestamp", 6)])
def test_livox_pointcloud2_bad_datatype(tmp_path: Path, field: str, datatype: int) -> None:
    ts = _typestore(True)
    p = _points(np.random.default_rng(9), 5)
    fields = [(n, o, datatype if n == field else d) for n, o, d in LIVOX_PC2]
    path = _write(tmp_path / "bag", True, {"/p": (PC2, [_livox_pc2(ts, p, T0, 0, fields=fields)])}, ts)
    with open_sequence(path) as seq, pytest.raises(ScanFormatError, match=f"field '{field}'") as err:
        seq[0]
    assert str(path) in str(err.value) and "/p" in str(err.value)


@pytest.mark.parametrize("msgdefs", [True, False], ids=["schema", "empty-schema"])
def test_standalone_mcap_with_custom_msg(tmp_path: Path, msgdefs: bool) -> None:
    """A CustomMsg topic in a ``.mcap`` file with no rosbag2 metadata beside it (as recorded by ``ros2 bag`` and
    copied out, or written by Foxglove tools) reads like the bag's."""
    from placerec.io.datasets.mcap import McapSequence

    ts = _typestore(True)
    rng = np.random.default_rng(4)
    clouds = [_points(rng, n) for n in (40, 9)]
    msgs = [_custom(ts, V2, p, T0 + k, 7, frame="lidar") for k, p in enumerate(clouds)]
    bag = _write_mcap_bag(tmp_path / "bag", {"/livox/lidar": (V2, msgs)}, ts, msgdefs=msgdefs)
    lone = tmp_path / "lone.mcap"
    lone.write_bytes((bag / "bag_0.mcap").read_bytes())
    seq = open_sequence(lone)
    assert isinstance(seq, McapSequence) and len(seq) == 2
    for k, p in enumerate(clouds):
        _check_scan(seq[k], p, T0 + k, 7)


def test_standalone_mcap_with_a_foreign_custom_msg_layout_names_the_field(tmp_path: Path) -> None:
    ts = _typestore(True)
    msgs = [_custom(ts, V2, _points(np.random.default_rng(5), 3), T0, 0)]
    bag = _write_mcap_bag(tmp_path / "bag", {"/livox/lidar": (V2, msgs)}, ts, msgdefs=True)
    data = (bag / "bag_0.mcap").read_bytes().replace(b"uint32 offset_time", b"uint16 offset_time")
    lone = tmp_path / "foreign.mcap"
    lone.write_bytes(data)
    with pytest.raises(ScanFormatError, match="offset_time"):
        open_sequence(lone)
