"""KittiSequence, FolderSequence and open_sequence on synthetic folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from placerec.errors import ConfigError, ScanFormatError
from placerec.io import (
    FolderSequence,
    KittiSequence,
    open_sequence,
    write_kitti_poses,
    write_scan,
    write_tum_poses,
)
from placerec.io.poses import quat_to_matrix
from placerec.types import Scan, Sequence


def make_scan(n: int, seed: int = 0, ring: bool = True, time: bool = True) -> Scan:
    rng = np.random.default_rng(seed)
    return Scan(
        xyz=rng.normal(0, 15, (n, 3)),
        intensity=rng.uniform(0, 1, n),
        ring=rng.integers(0, 64, n) if ring else None,
        time=rng.uniform(0, 0.1, n) if time else None,
    )


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    P = np.tile(np.eye(4), (n, 1, 1))
    q = rng.normal(size=(n, 4))
    P[:, :3, :3] = quat_to_matrix(q)
    P[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return P


def _kitti_folder(root: Path, n: int = 5, ring: bool = False) -> list[Scan]:
    scans = [make_scan(100 + 10 * k, seed=k, ring=False, time=False) for k in range(n)]
    for k, s in enumerate(scans):
        write_scan(root / "velodyne" / f"{k:06d}.bin", s)
        if ring:
            (root / "ring").mkdir(exist_ok=True)
            np.save(root / "ring" / f"{k:06d}.npy", np.arange(len(s), dtype=np.int16) % 32)
    return scans


def test_kitti_sequence_lazy_with_poses_times_and_calib(tmp_path: Path) -> None:
    root = tmp_path / "sequences" / "07"
    scans = _kitti_folder(root)
    P_cam = random_poses(5)
    (tmp_path / "poses").mkdir()
    write_kitti_poses(tmp_path / "poses" / "07.txt", P_cam)  # official layout: dataset/poses/07.txt
    (root / "times.txt").write_text("\n".join(f"{0.1 * k:.6e}" for k in range(5)) + "\n")
    seq = KittiSequence(root)
    assert isinstance(seq, Sequence) and len(seq) == 5 and seq.name == "07"
    np.testing.assert_allclose(seq.poses, P_cam)  # no calib.txt: poses as given
    np.testing.assert_allclose(seq.timestamps, np.arange(5) * 0.1)
    s3 = seq[3]
    np.testing.assert_array_equal(s3.xyz, scans[3].xyz)
    assert s3.timestamp == pytest.approx(0.3)
    Tr = random_poses(1, seed=9)[0]
    calib = "P0: " + " ".join(["0"] * 12) + "\nTr: " + " ".join(f"{v:.17g}" for v in Tr[:3].ravel()) + "\n"
    (root / "calib.txt").write_text(calib)
    seq = KittiSequence(root)
    expected = np.linalg.inv(Tr) @ P_cam @ Tr
    np.testing.assert_allclose(seq.poses, expected, atol=1e-9)
    # consistency: a LiDAR-frame point moved by the LiDAR pose equals the camera-frame route
    x = np.array([1.0, 2.0, 3.0, 1.0])
    np.testing.assert_allclose(Tr @ seq.poses[2] @ x, P_cam[2] @ Tr @ x, atol=1e-9)
    np.testing.assert_allclose(KittiSequence(root, poses_in_camera_frame=False).poses, P_cam)


def test_kitti_sequence_errors(tmp_path: Path) -> None:
    with pytest.raises(ScanFormatError, match="velodyne"):
        KittiSequence(tmp_path)
    _kitti_folder(tmp_path, n=3)
    write_kitti_poses(tmp_path / "poses.txt", random_poses(4))
    with pytest.raises(ScanFormatError, match="4 poses for 3 scans"):
        KittiSequence(tmp_path)
    (tmp_path / "poses.txt").unlink()
    (tmp_path / "times.txt").write_text("0\n1\n")
    with pytest.raises(ScanFormatError, match="2 timestamps for 3 scans"):
        KittiSequence(tmp_path)
    (tmp_path / "times.txt").unlink()
    write_kitti_poses(tmp_path / "poses.txt", random_poses(3))
    with pytest.raises(ScanFormatError, match="Tr"):
        KittiSequence(tmp_path, poses_in_camera_frame=True)


def test_simulator_layout_sensor_yaml_and_ring(tmp_path: Path) -> None:
    scans = _kitti_folder(tmp_path, n=3, ring=True)
    write_kitti_poses(tmp_path / "poses.txt", random_poses(3))
    sensor = {
        "name": "sim-vlp16",
        "beam_elevations_deg": np.linspace(15, -15, 16).tolist(),
        "columns": 1800,
        "intensity_max": 255.0,
        "min_range": 0.5,
        "max_range": 100.0,
    }
    (tmp_path / "sensor.yaml").write_text(yaml.safe_dump(sensor))
    seq = open_sequence(tmp_path)
    assert isinstance(seq, KittiSequence)
    s = seq[1]
    assert s.sensor.name == "sim-vlp16" and s.sensor.n_beams == 16 and s.sensor.max_range == 100.0
    np.testing.assert_array_equal(s.ring, np.arange(len(scans[1])) % 32)
    np.save(tmp_path / "ring" / "000002.npy", np.zeros(3, np.int16))
    with pytest.raises(ScanFormatError, match="one per point"):
        seq[2]
    (tmp_path / "sensor.yaml").write_text("name: x\nbeams: 3\n")
    with pytest.raises(ScanFormatError, match="sensor.yaml.*unknown keys"):
        KittiSequence(tmp_path)


def test_folder_sequence_natural_order_formats_and_tum(tmp_path: Path) -> None:
    scans = [make_scan(50 + k, seed=k) for k in range(12)]
    for k, s in enumerate(scans):
        write_scan(tmp_path / f"scan{k}.pcd", s, data="binary_compressed" if k % 2 else "binary")
    (tmp_path / "notes.txt").write_text("not a scan")
    ts = 100.0 + np.arange(12)
    write_tum_poses(tmp_path / "traj.tum", random_poses(12), ts)
    seq = FolderSequence(tmp_path, poses=tmp_path / "traj.tum")
    assert [f.name for f in seq.files[:3]] == ["scan0.pcd", "scan1.pcd", "scan2.pcd"]
    assert seq.files[10].name == "scan10.pcd"
    np.testing.assert_array_equal(seq[10].xyz, scans[10].xyz)
    np.testing.assert_array_equal(seq[11].ring, scans[11].ring)
    np.testing.assert_allclose(seq.timestamps, ts)
    assert seq[4].timestamp == 104.0 and seq.poses.shape == (12, 4, 4)
    assert isinstance(open_sequence(tmp_path), FolderSequence)
    with pytest.raises(ScanFormatError, match="12 poses"):
        FolderSequence(tmp_path, pattern="scan1*.pcd", poses=tmp_path / "traj.tum")
    write_scan(tmp_path / "extra.npz", scans[0])
    with pytest.raises(ScanFormatError, match="several kinds"):
        FolderSequence(tmp_path)
    assert len(FolderSequence(tmp_path, pattern="*.npz")) == 1
    with pytest.raises(ConfigError):
        FolderSequence(tmp_path, pattern="*.npz", colour=1)


def test_folder_sequence_nclt_and_layout_options(tmp_path: Path) -> None:
    rec = np.zeros(64, dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])
    rec["x"] = 20000
    rec["l"] = np.arange(64) % 32
    for k in range(2):
        rec.tofile(tmp_path / f"{k}.bin")
    seq = FolderSequence(tmp_path, format="nclt")
    assert seq[0].ring.max() == 31 and np.allclose(seq[1].xyz[:, 0], 0.0)
    org = FolderSequence(tmp_path, organized=True, layout=(4, 8, "column-major"))  # as 32 KITTI records
    assert org[0].shape == (4, 8)


def test_open_sequence_dispatch_errors(tmp_path: Path) -> None:
    with pytest.raises(ScanFormatError, match="no such"):
        open_sequence(tmp_path / "nothing")
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(ScanFormatError, match="cannot open"):
        open_sequence(tmp_path / "f.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ScanFormatError, match="no scan files"):
        open_sequence(tmp_path / "empty")


def test_folder_of_kitti_bins_with_sensor_yaml_gets_raw_intensity(tmp_path: Path) -> None:
    # as for a KITTI sequence folder: [0, 1] reflectance times the sensor.yaml's intensity_max
    rng = np.random.default_rng(5)
    write_scan(tmp_path / "0.bin", Scan(rng.normal(size=(50, 3)) * 10, np.linspace(0, 1, 50)))
    (tmp_path / "sensor.yaml").write_text("name: vlp16\nintensity_max: 255\n")
    s = FolderSequence(tmp_path)[0]
    assert s.sensor.name == "vlp16"
    np.testing.assert_allclose(s.intensity, np.linspace(0, 255, 50), rtol=1e-6)


def test_frames_named_by_number_pick_their_rows_from_a_whole_sequences_poses(tmp_path: Path) -> None:
    """#32: KITTI frames 000094/000095/000198 with the sequence's poses_00.txt (one row per frame of the drive)."""
    from placerec.errors import ScanFormatError
    from placerec.io import open_sequence

    pts = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    for frame in (94, 95, 198):
        pts.tofile(tmp_path / f"{frame:06d}.bin")
    rows = np.tile(np.eye(4)[:3].reshape(1, 12), (300, 1))
    rows[:, 3] = np.arange(300)  # x = the row number
    np.savetxt(tmp_path / "whole.txt", rows)
    seq = open_sequence(tmp_path, poses=tmp_path / "whole.txt")
    assert seq.poses[:, 0, 3].tolist() == [94.0, 95.0, 198.0]
    np.savetxt(tmp_path / "short.txt", rows[:150])  # frame 198 is past its end: no way to pick the rows
    with pytest.raises(
        ScanFormatError, match=r"short.txt: 150 poses for 3 scans .* named by its frame number"
    ):
        open_sequence(tmp_path, poses=tmp_path / "short.txt")
    (tmp_path / "scan_a.bin").write_bytes(pts.tobytes())  # a name that is no frame number
    with pytest.raises(ScanFormatError, match=r"300 poses for 4 scans"):
        open_sequence(tmp_path, poses=tmp_path / "whole.txt")


def test_scans_named_by_their_time_pick_the_nearest_pose_of_a_tum_file(tmp_path: Path) -> None:
    """#32: a TUM trajectory of the whole drive, scan files named by their time (nanoseconds or seconds)."""
    from placerec.errors import ScanFormatError
    from placerec.io import open_sequence
    from placerec.io.sequences import file_times

    pts = np.random.default_rng(0).normal(size=(50, 4)).astype(np.float32)
    t0 = 1_566_279_710
    for row, jitter_ns in ((2, 10_000_000), (5, -20_000_000), (7, 0)):
        pts.tofile(tmp_path / f"{t0 + row // 10}{(row % 10) * 100_000_000 + jitter_ns:09d}.bin")
    times = t0 + np.arange(10) * 0.1
    lines = [f"{t:.3f} {k} 0 0 0 0 0 1" for k, t in enumerate(times)]  # x = the row number
    (tmp_path / "traj.tum").write_text("\n".join(lines) + "\n")
    seq = open_sequence(tmp_path, poses=tmp_path / "traj.tum")
    assert seq.poses[:, 0, 3].tolist() == [2.0, 5.0, 7.0]
    np.testing.assert_allclose(seq.timestamps - t0, [0.21, 0.48, 0.7], atol=1e-6)
    pts.tofile(tmp_path / f"{t0 + 5}000000000.bin")  # 5 s after the trajectory ends
    with pytest.raises(
        ScanFormatError, match=rf"traj.tum: no pose within 0.05 s of scan {t0 + 5}000000000.bin"
    ):
        open_sequence(tmp_path, poses=tmp_path / "traj.tum")
    assert file_times([Path("1318.104571.pcd"), Path("000094.bin")]) is None  # a frame number is no time
    assert file_times([Path("1318.104571.pcd")]).tolist() == [1318.104571]
