"""Dataset-layout loaders (`placerec.io.datasets`) on small fake layouts built from the real sample frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from placerec.errors import ConfigError, ScanFormatError
from placerec.io import open_sequence, read_poses, read_scan
from placerec.io.datasets import DATASET_LOADERS, detect_dataset
from placerec.io.datasets.mulran import MULRAN_T_BASE_LIDAR
from placerec.io.datasets.nclt import NCLT_T_BODY_VELODYNE
from placerec.io.datasets.newer_college import NCD_T_BASE_LIDAR
from placerec.io.nclt import read_nclt_bin

# calib.txt of KITTI odometry sequences 00-02: Tr = velodyne -> camera 0
KITTI00_TR = (
    "4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
    "-7.210626507539e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
    "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01"
)
P0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"


def _kitti_layout(
    real: Path, root: Path, frames=(94, 95), calib: bool = True, extra_pose: bool = False
) -> Path:
    seq = root / "sequences" / "00"
    (seq / "velodyne").mkdir(parents=True)
    for k, f in enumerate(frames):
        shutil.copy(real / "kitti00_frames" / f"{f:06d}.bin", seq / "velodyne" / f"{k:06d}.bin")
    lines = (real / "kitti00_frames" / "poses_00.txt").read_text().splitlines()
    picked = [lines[f] for f in frames] + ([lines[0]] if extra_pose else [])
    (root / "poses").mkdir()
    (root / "poses" / "00.txt").write_text("\n".join(picked) + "\n")
    if calib:
        (seq / "calib.txt").write_text(f"P0: {P0}\nTr: {KITTI00_TR}\n")
    (seq / "times.txt").write_text("9.3\n9.4\n")
    return seq


def _misalignment(a: np.ndarray, b: np.ndarray, T_a_b: np.ndarray) -> float:
    """Median distance from points of b (mapped into a's frame by T_a_b) to their nearest point of a, within 30 m."""
    near_a = a[np.linalg.norm(a, axis=1) < 30]
    near_b = b[np.linalg.norm(b, axis=1) < 30][::20].astype(np.float64)
    moved = near_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    return float(np.median(cKDTree(near_a).query(moved)[0]))


def test_kitti_poses_are_lidar_poses_and_align_consecutive_real_frames(real_data, tmp_path):
    """The frame mix-up check: with poses converted by Tr, consecutive real scans overlap; with the camera poses
    used as LiDAR poses (the common mistake) they do not."""
    seq_dir = _kitti_layout(real_data, tmp_path)
    seq = open_sequence(tmp_path, dataset="kitti", sequence="00")
    assert len(seq) == 2 and seq.timestamps.tolist() == [9.3, 9.4]
    cam, _ = read_poses(tmp_path / "poses" / "00.txt")
    Tr = np.vstack([np.array(KITTI00_TR.split(), float).reshape(3, 4), [0, 0, 0, 1]])
    np.testing.assert_allclose(seq.poses, np.linalg.inv(Tr) @ cam @ Tr, atol=1e-12)
    a, b = seq[0].xyz, seq[1].xyz
    right = _misalignment(a, b, np.linalg.inv(seq.poses[0]) @ seq.poses[1])
    wrong = _misalignment(a, b, np.linalg.inv(cam[0]) @ cam[1])
    swapped = _misalignment(a, b, np.linalg.inv(seq.poses[1]) @ seq.poses[0])
    assert right < 0.15, right
    assert wrong > 2.5 * right and swapped > 2.5 * right, (right, wrong, swapped)
    # auto-detection: the sequence folder and the dataset root both open as KITTI odometry
    assert detect_dataset(seq_dir) == "kitti" and detect_dataset(tmp_path) == "kitti"
    np.testing.assert_allclose(open_sequence(seq_dir).poses, seq.poses)


def test_kitti_layout_errors_name_the_file(real_data, tmp_path):
    _kitti_layout(real_data, tmp_path / "a", calib=False)
    with pytest.raises(ScanFormatError, match=r"calib\.txt.*Tr"):
        open_sequence(tmp_path / "a", dataset="kitti", sequence="00")
    _kitti_layout(real_data, tmp_path / "b", extra_pose=True)
    with pytest.raises(ScanFormatError, match=r"00\.txt: 3 poses for 2 scans"):
        open_sequence(tmp_path / "b", dataset="kitti", sequence=0)
    with pytest.raises(ConfigError, match=r"pass sequence= \(one of \['00'\]\)"):
        open_sequence(tmp_path / "b", dataset="kitti")
    with pytest.raises(ConfigError, match="unknown dataset 'kity'"):
        open_sequence(tmp_path / "b", dataset="kity")


MULRAN_T0 = 1_566_535_000_000_000_000


def _mulran_layout(real: Path, root: Path) -> Path:
    ouster = root / "sensor_data" / "Ouster"
    ouster.mkdir(parents=True)
    for k, name in enumerate(["32line_1.bin", "32line_2.bin"]):
        shutil.copy(real / "ouster_os1_64_revisit_pair" / name, ouster / f"{MULRAN_T0 + k * 100_000_000}.bin")
    # a scan before the ground truth starts: left out
    shutil.copy(real / "ouster_os1_64_revisit_pair" / "32line_1.bin", ouster / f"{MULRAN_T0 - 10**9}.bin")
    rows = []
    for t in [-0.05, 0.05, 0.15]:  # the base drives along +x at 10 m/s, UTM-sized coordinates
        pose = np.eye(4)[:3]
        pose[:, 3] = [353_000.0 + 10 * t, 4_026_000.0, 19.0]
        rows.append(f"{MULRAN_T0 + int(t * 1e9)}," + ",".join(f"{v:.6f}" for v in pose.ravel()))
    (root / "global_pose.csv").write_text("\n".join(rows) + "\n")
    return root


def test_mulran_interpolates_poses_and_applies_the_extrinsic(real_data, tmp_path):
    root = _mulran_layout(real_data, tmp_path / "KAIST01")
    assert detect_dataset(root) == "mulran"
    seq = open_sequence(root, organized=True)
    assert len(seq) == 2 and seq.dropped == 1
    np.testing.assert_allclose(seq.timestamps - seq.timestamps[0], [0.0, 0.1], atol=1e-6)
    # LiDAR poses: base @ T_base_lidar (the Ouster faces backwards: yaw ~179.67 deg), first one at the origin
    np.testing.assert_allclose(
        seq.poses[:, :3, :3], np.tile(MULRAN_T_BASE_LIDAR[:3, :3], (2, 1, 1)), atol=1e-9
    )
    np.testing.assert_allclose(seq.poses[:, :3, 3], [[0, 0, 0], [1.0, 0, 0]], atol=1e-5)
    assert Rotation.from_matrix(seq.poses[0, :3, :3]).as_euler("ZYX", degrees=True)[0] == pytest.approx(
        179.6654
    )
    scan = seq[0]
    assert scan.shape == (64, 1024) and scan.sensor.name.startswith("ouster-os1-64")
    ref = read_scan(
        real_data / "ouster_os1_64_revisit_pair" / "32line_1.bin", layout=(64, 1024, "column-major")
    )
    np.testing.assert_array_equal(scan.xyz, ref.xyz)
    (root / "global_pose.csv").write_text(f"{MULRAN_T0},1,0,0,0,0,1,0,0,0,0,1\n")
    with pytest.raises(ScanFormatError, match=r"global_pose\.csv:1: 12 columns, expected 13"):
        open_sequence(root, dataset="mulran")


def _pcd_names(real: Path, folder: Path) -> list[Path]:
    """Two real PCDs named so that sorting by name would swap them (nsec 82590976 comes first in time)."""
    folder.mkdir(parents=True)
    src = sorted((real / "kitti_raw_hdl64_sequence").glob("*.pcd"))[:2]
    names = ["cloud_1583836591_82590976.pcd", "cloud_1583836591_182590976.pcd"]
    for s, n in zip(src, names, strict=True):
        shutil.copy(s, folder / n)
    return src


def test_newer_college_orders_by_time_and_matches_poses(real_data, tmp_path):
    root = tmp_path / "01_short_experiment"
    src = _pcd_names(real_data, root / "raw_format" / "ouster_scan")
    (root / "ground_truth").mkdir()
    (root / "ground_truth" / "registered_poses.csv").write_text(
        "#sec,nsec,x,y,z,qx,qy,qz,qw\n"
        "1583836591,182590976,2.0,0,0,0,0,0,1\n"
        "1583836591,82590976,1.0,0,0,0,0,0,1\n"
        "1583836599,0,9.0,0,0,0,0,0,1\n"
    )
    assert detect_dataset(root) == "newer-college"
    seq = open_sequence(root)
    assert len(seq) == 2
    assert seq.timestamps[0] < seq.timestamps[1]
    assert len(seq[0]) == len(read_scan(src[0])) and len(seq[1]) == len(read_scan(src[1]))
    expect = np.eye(4)
    expect[0, 3] = 1.0
    np.testing.assert_allclose(seq.poses[0], expect @ NCD_T_BASE_LIDAR)
    assert Rotation.from_matrix(seq.poses[0, :3, :3]).as_euler("ZYX", degrees=True)[0] == pytest.approx(
        135, abs=0.1
    )
    np.testing.assert_allclose(seq.poses[1, :3, 3] - seq.poses[0, :3, 3], [1.0, 0, 0])
    (root / "ground_truth" / "registered_poses.csv").write_text("1583836591,82590976,1.0,0,0,0,0,zero,1\n")
    with pytest.raises(ScanFormatError, match=r"registered_poses\.csv:1: 'zero' is not a number"):
        open_sequence(root)


def test_helipr_ouster_records(real_data, tmp_path):
    from placerec.io.datasets.helipr import HELIPR_RECORDS

    ref = read_scan(real_data / "kitti00_frames" / "000094.bin")
    dtype = HELIPR_RECORDS["Ouster"][0]
    assert dtype.itemsize == 26
    folder = tmp_path / "LiDAR" / "Ouster"
    folder.mkdir(parents=True)
    rec = np.zeros(len(ref), dtype=dtype)
    for j, c in enumerate("xyz"):
        rec[c] = ref.xyz[:, j]
    rec["intensity"] = ref.intensity * 1000
    rec["ring"] = np.arange(len(ref)) % 128
    t0 = 1_691_937_000_000_000_000
    for k in range(2):
        rec.tofile(folder / f"{t0 + k * 100_000_000}.bin")
    rec[:1].tofile(folder / f"{t0 + 5 * 10**9}.bin")  # no ground truth at its time: left out
    (tmp_path / "LiDAR_GT").mkdir()
    (tmp_path / "LiDAR_GT" / "Ouster_gt.txt").write_text(
        f"{t0} 100.0 200.0 3.0 0 0 0.7071067811865476 0.7071067811865476\n{t0 + 100_000_000} 101.0 200.0 3.0 0 0 0 1\n"
    )
    assert detect_dataset(tmp_path) == "helipr"
    seq = open_sequence(tmp_path)
    assert len(seq) == 2 and seq.dropped == 1 and seq.name.endswith(":Ouster")
    np.testing.assert_array_equal(seq[0].xyz, ref.xyz)
    np.testing.assert_allclose(seq[0].intensity, ref.intensity * 1000, rtol=1e-6)
    assert seq[0].ring.max() == 127
    np.testing.assert_allclose(seq.poses[:, :3, 3], [[0, 0, 0], [1.0, 0, 0]])
    assert Rotation.from_matrix(seq.poses[0, :3, :3]).as_euler("ZYX", degrees=True)[0] == pytest.approx(90)
    (folder / f"{t0}.bin").write_bytes(b"x" * 27)
    with pytest.raises(ScanFormatError, match="not a multiple of the HeLiPR Ouster record size 26"):
        seq[0]


def test_nclt_flips_to_z_up_and_interpolates(real_data, tmp_path):
    root = tmp_path / "2012-01-15"
    (root / "velodyne_sync").mkdir(parents=True)
    src = next((real_data / "nclt_hdl32_frame").glob("*.bin"))
    t0 = 1326652795280148
    for k in range(2):
        shutil.copy(src, root / "velodyne_sync" / f"{t0 + k * 100_000}.bin")
    (tmp_path / "ground_truth").mkdir()
    yaw = np.pi / 2  # heading east in NCLT's north-east-down world
    (tmp_path / "ground_truth" / "groundtruth_2012-01-15.csv").write_text(
        f"{t0 - 1000000},nan,nan,nan,nan,nan,nan\n"
        f"{t0 - 100000},0,0,0,0,0,{yaw}\n"
        f"{t0 + 300000},0,4,0,0,0,{yaw}\n"
    )
    assert detect_dataset(root) == "nclt"
    seq = open_sequence(root)
    assert len(seq) == 2
    raw = read_nclt_bin(src)
    np.testing.assert_allclose(seq[0].xyz, raw.xyz * [1, -1, -1])
    assert seq[0].sensor.beam_elevations_deg[0] == -raw.sensor.beam_elevations_deg[0]
    # body at y = 1 (east) then 2: in placerec's z-up world (x, -y, -z) that is y = -1, -2; the Velodyne sits
    # 0.957 m above the body origin; heading east in NED is yaw -90 deg about z up
    lever = NCLT_T_BODY_VELODYNE[:3, 3]
    east = np.array([[-lever[1], lever[0]], [-lever[1], lever[0]]])  # the lever arm turned by the 90 deg yaw
    np.testing.assert_allclose(seq.poses[:, 0, 3], east[:, 0], atol=1e-9)
    np.testing.assert_allclose(seq.poses[:, 1, 3], -(np.array([1.0, 2.0]) + east[:, 1]), atol=1e-5)
    np.testing.assert_allclose(seq.poses[:, 2, 3], 0.957, atol=1e-3)
    yaws = Rotation.from_matrix(seq.poses[:, :3, :3]).as_euler("ZYX", degrees=True)[:, 0]
    np.testing.assert_allclose(yaws, -90.0, atol=0.01)
    (tmp_path / "ground_truth" / "groundtruth_2012-01-15.csv").write_text(f"{t0},0,0,0,0,0\n")
    with pytest.raises(ScanFormatError, match=r"groundtruth_2012-01-15\.csv:1: 6 columns, expected 7"):
        open_sequence(root)


def test_mcap_without_metadata(real_data, tmp_path):
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.LATEST)
    T = ts.types
    ref = read_scan(real_data / "kitti00_frames" / "000094.bin")
    arr = np.zeros(len(ref), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    for j, c in enumerate("xyz"):
        arr[c] = ref.xyz[:, j]
    arr["intensity"] = ref.intensity
    fields = [
        T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=7, count=1)
        for k, n in enumerate(arr.dtype.names)
    ]
    path = tmp_path / "drive.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        schema = w.register_schema("sensor_msgs/msg/PointCloud2", "ros2msg", b"")
        chan = w.register_channel("/points", "cdr", schema)
        for k in range(2):
            n = len(arr) // (k + 1)
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=5), frame_id="l"
            )
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=header,
                height=1,
                width=n,
                fields=fields,
                is_bigendian=False,
                point_step=16,
                row_step=16 * n,
                data=np.frombuffer(arr[:n].tobytes(), np.uint8).copy(),
                is_dense=True,
            )
            data = bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            w.add_message(chan, log_time=(100 + k) * 10**9, data=data, publish_time=(100 + k) * 10**9)
        w.finish()
    assert detect_dataset(path) == "mcap"
    seq = open_sequence(path)
    assert len(seq) == 2 and seq.topic == "/points"
    np.testing.assert_allclose(seq.timestamps, [100 + 5e-9, 101 + 5e-9])
    np.testing.assert_array_equal(seq[0].xyz, ref.xyz)
    assert len(seq[1]) == len(ref) // 2
    with pytest.raises(ScanFormatError, match="no PointCloud2 topic '/lidar'"):
        open_sequence(path, topic="/lidar")
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\nnot really")
    with pytest.raises(ScanFormatError, match="junk.mcap: cannot read as .mcap"):
        open_sequence(tmp_path / "junk.mcap")


def test_every_dataset_is_registered():
    assert list(DATASET_LOADERS) == ["mcap", "mulran", "newer-college", "helipr", "nclt", "kitti"]


def test_a_config_opens_a_dataset_layout(real_data, tmp_path):
    from placerec.config import DatasetConfig
    from placerec.experiment.datasets import open_dataset

    _kitti_layout(real_data, tmp_path)
    cfg = DatasetConfig(source="path", path=str(tmp_path), dataset="kitti", sequence="00")
    seq = open_dataset(cfg)
    assert len(seq) == 2 and seq.name == "00"
    with pytest.raises(ConfigError, match=r"does not take option\(s\) \['topic'\]"):
        open_dataset(
            DatasetConfig(source="path", path=str(tmp_path), dataset="kitti", sequence="00", topic="/x")
        )


def test_info_reads_a_dataset_layout(real_data, tmp_path):
    import json

    from typer.testing import CliRunner

    from placerec.cli import app

    seq_dir = _kitti_layout(real_data, tmp_path)
    result = CliRunner().invoke(app, ["info", str(seq_dir), "--dataset", "kitti", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["scans"] == 2 and summary["poses"]["count"] == 2
    bad = CliRunner().invoke(app, ["info", str(seq_dir), "--dataset", "nope"])
    assert bad.exit_code != 0 and "unknown dataset 'nope'" in bad.output


def test_roll_pitch_yaw_poses_match_scipy():
    from placerec.io.datasets.trajectory import pose_from_xyz_rpy

    rpy = np.random.default_rng(0).uniform(-3, 3, (20, 3))
    P = pose_from_xyz_rpy(np.arange(60.0).reshape(20, 3), rpy)
    np.testing.assert_allclose(P[:, :3, :3], Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(P[:, :3, 3], np.arange(60.0).reshape(20, 3))


@pytest.mark.parametrize("sensor", ["Ouster", "Velodyne", "Aeva", "Avia"])
def test_helipr_record_layouts(tmp_path, sensor):
    from placerec.io.datasets.helipr import HELIPR_RECORDS, read_helipr_bin

    dtype, field, _ = HELIPR_RECORDS[sensor]
    assert dtype.itemsize == {"Ouster": 26, "Velodyne": 22, "Aeva": 29, "Avia": 19}[sensor]
    rec = np.zeros(500, dtype=dtype)
    rng = np.random.default_rng(0)
    for c in "xyz":
        rec[c] = rng.uniform(-50, 50, 500)
    rec[field] = rng.integers(1, 200, 500)
    path = tmp_path / "1700000000000000000.bin"  # after Aeva's change of format
    rec.tofile(path)
    scan = read_helipr_bin(path, sensor)
    np.testing.assert_array_equal(scan.xyz, np.c_[rec["x"], rec["y"], rec["z"]])
    np.testing.assert_array_equal(scan.intensity, rec[field].astype(np.float32))
    if sensor == "Aeva":  # older Aeva scans have no intensity field: 25-byte records, reflectivity instead
        from placerec.io.datasets.helipr import _AEVA_OLD

        early = np.zeros(500, dtype=_AEVA_OLD)
        for c in "xyz":
            early[c] = rec[c]
        early["reflectivity"] = np.arange(500)
        early.tofile(tmp_path / "1691936557946849179.bin")
        scan = read_helipr_bin(tmp_path / "1691936557946849179.bin", sensor)
        assert _AEVA_OLD.itemsize == 25 and len(scan) == 500
        np.testing.assert_array_equal(scan.intensity, np.arange(500, dtype=np.float32))


def test_helipr_aeva_layout_decided_by_content(tmp_path):
    """A file of 725·k bytes fits both Aeva record sizes (29 and 25 bytes): the layout is the one under which the
    points are plausible, whatever the file name's date says; neither or both plausible is refused."""
    from placerec.io.datasets.helipr import _AEVA_OLD, HELIPR_RECORDS, read_helipr_bin

    new = HELIPR_RECORDS["Aeva"][0]
    rng = np.random.default_rng(1)
    late, early = "1700000000000000000.bin", "1691936557946849179.bin"
    for dtype, n in ((new, 250), (_AEVA_OLD, 290)):  # both 7250 bytes
        rec = np.zeros(n, dtype=dtype)
        for c in "xyz":
            rec[c] = rng.uniform(-80, 80, n)
        rec["reflectivity"] = rng.uniform(0, 100, n)
        rec["velocity"] = rng.uniform(-20, 20, n)
        rec["time_offset"] = rng.integers(0, 100_000_000, n)
        rec["line"] = rng.integers(0, 64, n)
        if "intensity" in dtype.names:
            rec["intensity"] = rng.uniform(0, 1, n)
        for name in (late, early):  # the date names the other layout for one of the two
            rec.tofile(tmp_path / name)
            scan = read_helipr_bin(tmp_path / name, "Aeva")
            assert len(scan) == n and scan.ranges.max() < 1000
            np.testing.assert_array_equal(scan.xyz[:, 0], rec["x"])
    zeros = tmp_path / late
    np.zeros(7250, np.uint8).tofile(zeros)  # plausible either way: ambiguous
    with pytest.raises(ScanFormatError, match=r"fits both HeLiPR Aeva record sizes.*100% of the points"):
        read_helipr_bin(zeros, "Aeva")
    rng.integers(0, 256, 7250, dtype=np.uint8).tofile(zeros)  # plausible neither way
    with pytest.raises(ScanFormatError, match=f"{zeros}: size 7250 bytes fits both"):
        read_helipr_bin(zeros, "Aeva")
    np.zeros(31, np.uint8).tofile(zeros)
    with pytest.raises(ScanFormatError, match="multiple of neither HeLiPR Aeva record size"):
        read_helipr_bin(zeros, "Aeva")


def _ncd_fake(root: Path, names: list[str], gt: str) -> Path:
    """A Newer College layout whose scans are never read (the names and the ground truth are refused first)."""
    (root / "raw_format" / "ouster_scan").mkdir(parents=True)
    for n in names:
        (root / "raw_format" / "ouster_scan" / n).write_bytes(b"x")
    (root / "ground_truth").mkdir()
    (root / "ground_truth" / "registered_poses.csv").write_text(gt)
    return root


def test_newer_college_refuses_nanoseconds_of_a_second_or_more(tmp_path):
    gt = "1583836591,82590976,1.0,0,0,0,0,0,1\n"
    root = _ncd_fake(tmp_path / "a", ["cloud_1583836591_82590976.pcd", "cloud_1583836590_1000000000.pcd"], gt)
    with pytest.raises(
        ScanFormatError, match=r"cloud_1583836590_1000000000\.pcd: nanoseconds field '1000000000'"
    ):
        open_sequence(root, dataset="newer-college")
    root = _ncd_fake(tmp_path / "b", ["cloud_1583836591_٣.pcd"], gt)  # other scripts' digits: not a stamp
    with pytest.raises(ScanFormatError, match=r"expected a scan named cloud_<sec>_<nsec>\.pcd"):
        open_sequence(root, dataset="newer-college")
    bad_gt = gt + "1583836592,2000000000,1.0,0,0,0,0,0,1\n"
    root = _ncd_fake(tmp_path / "c", ["cloud_1583836591_82590976.pcd"], bad_gt)
    with pytest.raises(
        ScanFormatError, match=r"registered_poses\.csv: ground-truth data row 2 has .*nsec 2000000000;"
    ):
        open_sequence(root, dataset="newer-college")


def _mulran_fake(root: Path, stems: list[str], rows: list[str]) -> Path:
    (root / "Ouster").mkdir(parents=True)
    for s in stems:
        (root / "Ouster" / f"{s}.bin").write_bytes(b"\0" * 16)
    (root / "global_pose.csv").write_text("\n".join(rows) + "\n")
    return root


def test_timestamp_names_and_max_gap_are_checked(tmp_path):
    """Superscript digits pass `str.isdigit` but not `int`; a string max_gap reached a NumPy ufunc."""
    eye = ",".join(f"{v:g}" for v in np.eye(4)[:3].ravel())
    rows = [f"{MULRAN_T0},{eye}", f"{MULRAN_T0 + 10**9},{eye}"]
    root = _mulran_fake(tmp_path / "m", [str(MULRAN_T0), "¹²³"], rows)
    with pytest.raises(ScanFormatError, match=r"¹²³\.bin: expected a file named by its integer timestamp"):
        open_sequence(root, dataset="mulran")
    (tmp_path / "k" / "sequences" / "¹²").mkdir(parents=True)
    with pytest.raises(ScanFormatError, match="no such KITTI sequence"):
        open_sequence(tmp_path / "k", dataset="kitti", sequence="¹²")
    from placerec.io._common import natural_key

    assert natural_key(Path("a1¹2.bin")) < natural_key(Path("a2.bin"))
    heli = tmp_path / "h"
    (heli / "LiDAR" / "Aeva").mkdir(parents=True)
    (heli / "LiDAR_GT").mkdir()
    (heli / "LiDAR" / "Aeva" / "1700000000000000000.bin").write_bytes(b"\0" * 29)
    (heli / "LiDAR_GT" / "Aeva_gt.txt").write_text("1700000000000000000 0 0 0 0 0 0 1\n")
    assert len(open_sequence(heli, dataset="helipr", max_gap=0.1)) == 1
    for gap in ("0.1", None, True, float("nan"), -1.0):
        with pytest.raises(ConfigError, match="max_gap must be a"):
            open_sequence(heli, dataset="helipr", max_gap=gap)


@pytest.mark.parametrize(
    "rotation, why",
    [
        (np.diag([1.0, 1.0, -1.0]), "reflection"),
        (np.zeros((3, 3)), "not a rotation"),
        (np.eye(3) * 2, "not a"),
    ],
)
def test_mulran_refuses_rotations_that_are_not_rotations(tmp_path, rotation, why):
    """A mirrored or zero rotation in global_pose.csv is refused naming the row, before scipy's Rotation
    (which raised a bare `ValueError: Non-positive determinant`)."""
    pose = np.eye(4)[:3]
    pose[:, :3] = rotation
    good = ",".join(f"{v:g}" for v in np.eye(4)[:3].ravel())
    rows = [f"{MULRAN_T0},{good}", f"{MULRAN_T0 + 10**9}," + ",".join(f"{v:g}" for v in pose.ravel())]
    root = _mulran_fake(tmp_path / "m", [str(MULRAN_T0 + 5 * 10**8)], rows)
    with pytest.raises(
        ScanFormatError, match=rf"global_pose\.csv: ground-truth data row 2 is no rigid motion.*{why}"
    ):
        open_sequence(root, dataset="mulran")
