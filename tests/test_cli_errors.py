"""The CLI ends every placerec error with one line on stderr and status 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.io import write_scan
from placerec.types import Scan

runner = CliRunner()


def _fails_cleanly(args: list[str], *expected: str) -> str:
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    for text in expected:
        assert text in lines[0]
    return lines[0]


def _kitti_folder(root: Path, calib: str | None = None) -> Path:
    (root / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(0)
    write_scan(root / "velodyne" / "000000.bin", Scan(rng.normal(size=(100, 3)) * 10, rng.random(100)))
    (root / "poses.txt").write_text(" ".join(f"{v:g}" for v in np.eye(4)[:3].ravel()) + "\n")
    if calib is not None:
        (root / "calib.txt").write_text(calib)
    return root


def _ros2_bag(path: Path) -> Path:
    """A one-message rosbag2 folder of a PointCloud2 (x, y, z float32), written with rosbags' own writer."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    fields = [
        T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=7, count=1)
        for k, n in enumerate("xyz")
    ]
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="lidar"
    )
    data = np.frombuffer(np.arange(30, dtype="<f4").tobytes(), np.uint8).copy()
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=header,
        height=1,
        width=10,
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=120,
        data=data,
        is_dense=True,
    )
    with Writer(path) as w:
        conn = w.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        w.write(conn, 1_000_000_000, ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    return path


def test_ros2_folder_with_an_empty_metadata_yaml(tmp_path):
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("")
    _fails_cleanly(["info", str(tmp_path / "bag")], "metadata.yaml", "rosbag2_bagfile_information", "empty")


@pytest.mark.parametrize("damage", ["garbage", "truncated"])
def test_ros2_folder_with_a_corrupt_db3(tmp_path, damage):
    pytest.importorskip("rosbags", reason="rosbags not installed (pip install placerec[ros])")
    bag = _ros2_bag(tmp_path / "bag")
    assert runner.invoke(app, ["info", str(bag)]).exit_code == 0
    (db3,) = bag.glob("*.db3")
    if damage == "garbage":
        db3.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes())
    else:
        db3.write_bytes(db3.read_bytes()[:100])
    _fails_cleanly(["info", str(bag)], "cannot open as a rosbag", "DatabaseError")


def test_kitti_folder_with_an_all_zero_tr(tmp_path):
    root = _kitti_folder(tmp_path / "seq", "Tr: " + " ".join(["0"] * 12) + "\n")
    _fails_cleanly(["info", str(root)], "calib.txt: Tr is not a rigid transform")
    ok = _kitti_folder(tmp_path / "ok", "Tr: " + " ".join(f"{v:g}" for v in np.eye(4)[:3].ravel()) + "\n")
    assert runner.invoke(app, ["info", str(ok)]).exit_code == 0


def test_format_for_a_kitti_folder(tmp_path):
    root = _kitti_folder(tmp_path / "seq")
    _fails_cleanly(["info", str(root), "--format", "nclt"], "KittiSequence", "['format']", "poses")


def test_multi_line_messages_become_one_line(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("evaluation:\n  gt_distnace: 3\n  top_n: -1\n")
    line = _fails_cleanly(["run", str(cfg)], "gt_distnace", "top_n")
    assert "; evaluation.gt_distnace: unknown key" in line


def test_an_error_no_command_catches_still_ends_in_one_line():
    code = (
        "import sys\n"
        "from placerec.cli import app, main\n"
        "from placerec.errors import ScanDataError\n"
        "@app.command('boom')\n"
        "def boom():\n"
        "    raise ScanDataError('scan.bin: first line\\n  second line')\n"
        "sys.argv = ['placerec', 'boom']\n"
        "main()\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip() == "error: scan.bin: first line; second line"


def test_a_bag_damaged_after_opening_fails_on_access(tmp_path):
    pytest.importorskip("rosbags", reason="rosbags not installed (pip install placerec[ros])")
    from placerec.errors import ScanFormatError
    from placerec.io import open_sequence

    bag = _ros2_bag(tmp_path / "bag")
    seq = open_sequence(bag)
    seq.close()  # indexed; the next access reopens the bag
    (db3,) = bag.glob("*.db3")
    db3.write_bytes(db3.read_bytes()[:2048])
    with pytest.raises(ScanFormatError, match=r"bag:/points#0: cannot read PointCloud2 \(DatabaseError"):
        seq[0]
