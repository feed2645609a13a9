"""ROS1 / ROS2 bags of PointCloud2 written with rosbags' own writer, read back through RosbagSequence."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from placerec.errors import ScanFormatError
from placerec.io import open_sequence
from placerec.io.rosbag import RosbagSequence, pointcloud2_to_scan

rosbags = pytest.importorskip("rosbags", reason="rosbags not installed (pip install placerec[ros])")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

PF_FLOAT32, PF_UINT16, PF_UINT8, PF_UINT32, PF_FLOAT64 = 7, 4, 2, 6, 8


def _cloud(rng: np.random.Generator, n: int) -> np.ndarray:
    dt = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "ring", "t"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<u4"],
            "offsets": [0, 4, 8, 16, 20, 24],
            "itemsize": 32,
        }
    )  # padding at 12..16 and 28..32
    a = np.zeros(n, dtype=dt)
    for c in "xyz":
        a[c] = rng.normal(0, 20, n)
    a["intensity"] = rng.uniform(0, 255, n)
    a["ring"] = rng.integers(0, 64, n)
    a["t"] = rng.integers(0, 100_000_000, n)
    return a


def _msg(ts, arr: np.ndarray, sec: int, nsec: int, height: int = 1):
    T = ts.types
    fields = [
        T["sensor_msgs/msg/PointField"](name=name, offset=arr.dtype.fields[name][1], datatype=dt, count=1)
        for name, dt in [
            ("x", PF_FLOAT32),
            ("y", PF_FLOAT32),
            ("z", PF_FLOAT32),
            ("intensity", PF_FLOAT32),
            ("ring", PF_UINT16),
            ("t", PF_UINT32),
        ]
    ]
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header_kw = {"stamp": stamp, "frame_id": "lidar"}
    if "seq" in T["std_msgs/msg/Header"].__dataclass_fields__:
        header_kw["seq"] = 0
    header = T["std_msgs/msg/Header"](**header_kw)
    width = arr.size // height
    return T["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=False,
        point_step=arr.dtype.itemsize,
        row_step=arr.dtype.itemsize * width,
        data=np.frombuffer(arr.tobytes(), dtype=np.uint8).copy(),
        is_dense=False,
    )


def _write_bag(
    path: Path, ros2: bool, clouds: list[np.ndarray], topic: str = "/points", extra_topic: bool = False
):
    if ros2:
        from rosbags.rosbag2 import Writer

        ts = get_typestore(Stores.ROS2_HUMBLE)
        ser = ts.serialize_cdr
    else:
        from rosbags.rosbag1 import Writer

        ts = get_typestore(Stores.ROS1_NOETIC)
        ser = ts.serialize_ros1
    stamps = []
    with Writer(path) as w:
        conn = w.add_connection(topic, "sensor_msgs/msg/PointCloud2", typestore=ts)
        conn2 = (
            w.add_connection("/other", "sensor_msgs/msg/PointCloud2", typestore=ts) if extra_topic else None
        )
        for k, arr in enumerate(clouds):
            sec, nsec = 1_700_000_000 + k, 123_000_000 * (k % 3)
            stamps.append(sec + nsec * 1e-9)
            msg = _msg(ts, arr, sec, nsec, height=4 if arr.size % 4 == 0 else 1)
            log_time = 5_000_000_000 + k * 100_000_000 if k != 2 else 5_000_000_000 + 100_000_000  # dup time
            w.write(conn, log_time, ser(msg, "sensor_msgs/msg/PointCloud2"))
            if conn2 is not None:
                w.write(conn2, log_time, ser(msg, "sensor_msgs/msg/PointCloud2"))
    return stamps


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_bag_round_trip(tmp_path: Path, ros2: bool) -> None:
    rng = np.random.default_rng(3)
    clouds = [_cloud(rng, n) for n in (400, 123, 80, 1000)]
    path = tmp_path / ("bag2" if ros2 else "test.bag")
    stamps = _write_bag(path, ros2, clouds)
    with RosbagSequence(path) as seq:
        assert len(seq) == 4 and seq.poses is None and seq.topic == "/points"
        order = [0, 1, 2, 3]  # messages 1 and 2 share a log time; bag order is kept
        np.testing.assert_allclose(seq.timestamps, [stamps[k] for k in order], rtol=0, atol=1e-6)
        for i, k in enumerate(order):
            scan, arr = seq[i], clouds[k]
            assert len(scan) == arr.size
            np.testing.assert_array_equal(scan.xyz, np.stack([arr["x"], arr["y"], arr["z"]], 1))
            np.testing.assert_array_equal(scan.intensity, arr["intensity"])
            np.testing.assert_array_equal(scan.ring, arr["ring"])
            np.testing.assert_allclose(scan.time, arr["t"] * 1e-9, rtol=1e-6)
            assert scan.timestamp == pytest.approx(stamps[k], abs=1e-6)
        assert seq[-1].xyz.shape == (1000, 3)
        with pytest.raises(IndexError):
            seq[4]
    opened = open_sequence(path)
    assert isinstance(opened, RosbagSequence) and len(opened) == 4
    organised = RosbagSequence(path, organized=True)[0]
    assert organised.shape == (4, 100)
    opened.close()


def test_bag_topic_selection(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    path = tmp_path / "two.bag"
    _write_bag(path, False, [_cloud(rng, 10), _cloud(rng, 12)], extra_topic=True)
    with pytest.raises(ScanFormatError, match="pass topic="):
        RosbagSequence(path)
    with pytest.raises(ScanFormatError, match="no PointCloud2 topic"):
        RosbagSequence(path, topic="/nope")
    with RosbagSequence(path, topic="/other") as seq:
        assert len(seq) == 2 and len(seq[1]) == 12


def test_not_a_bag(tmp_path: Path) -> None:
    bad = tmp_path / "junk.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    with pytest.raises(ScanFormatError):
        RosbagSequence(bad)
    with pytest.raises(ScanFormatError):
        RosbagSequence(tmp_path / "missing.bag")


def _fake_msg(arr: np.ndarray, fields, *, big: bool = False, height: int = 1, row_pad: int = 0):
    width = arr.size // height
    step = arr.dtype.itemsize
    rows = arr.reshape(height, width)
    data = b"".join(r.tobytes() + b"\xee" * row_pad for r in rows)
    pf = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in fields]
    return SimpleNamespace(
        height=height,
        width=width,
        fields=pf,
        is_bigendian=big,
        point_step=step,
        row_step=step * width + row_pad,
        data=np.frombuffer(data, np.uint8),
    )


def test_pointcloud2_decoding_variants() -> None:
    rng = np.random.default_rng(5)
    n = 60
    for big in (False, True):
        e = ">" if big else "<"
        dt = np.dtype(
            [
                ("reflectivity", e + "u2"),
                ("z", e + "f8"),
                ("x", e + "f4"),
                ("y", e + "f4"),
                ("time", e + "f4"),
            ]
        )
        a = np.zeros(n, dtype=dt)
        a["x"], a["y"], a["z"] = rng.normal(size=(3, n))
        a["reflectivity"] = rng.integers(0, 65535, n)
        a["time"] = rng.uniform(0, 0.1, n)
        fields = [
            ("reflectivity", 0, PF_UINT16),
            ("z", 2, PF_FLOAT64),
            ("x", 10, PF_FLOAT32),
            ("y", 14, PF_FLOAT32),
            ("time", 18, PF_FLOAT32),
        ]
        scan = pointcloud2_to_scan(_fake_msg(a, fields, big=big, height=3, row_pad=5), "m", organized=True)
        assert scan.shape == (3, 20)
        np.testing.assert_allclose(scan.xyz, np.stack([a["x"], a["y"], a["z"]], 1).astype(np.float32))
        np.testing.assert_array_equal(scan.intensity, a["reflectivity"].astype(np.float32))
        assert scan.sensor.intensity_max == 65535
        np.testing.assert_allclose(scan.time, a["time"])
    bad = _fake_msg(a[:10], [("x", 0, 99)])
    with pytest.raises(ScanFormatError, match="datatype"):
        pointcloud2_to_scan(bad, "m")
    short = _fake_msg(a[:10], fields)
    short.data = short.data[:-1]
    with pytest.raises(ScanFormatError, match="bytes"):
        pointcloud2_to_scan(short, "m")
    outside = _fake_msg(a[:10], [("x", 20, PF_FLOAT64)])
    with pytest.raises(ScanFormatError, match="point_step"):
        pointcloud2_to_scan(outside, "m")


def test_missing_rosbags_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from placerec.errors import DependencyError

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(DependencyError, match=r"pip install placerec\[ros\]"):
        RosbagSequence(tmp_path / "x.bag")
