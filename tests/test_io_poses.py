"""KITTI and TUM trajectory readers and writers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placerec.errors import ScanFormatError
from placerec.io import read_poses, write_kitti_poses, write_tum_poses
from placerec.io.poses import quat_to_matrix


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    P[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return P


def test_kitti_round_trip(tmp_path: Path) -> None:
    P = random_poses(20)
    write_kitti_poses(tmp_path / "p.txt", P)
    back, t = read_poses(tmp_path / "p.txt")
    assert t is None and back.shape == (20, 4, 4)
    np.testing.assert_allclose(back, P, atol=1e-10)
    assert read_poses(tmp_path / "p.txt", format="kitti")[0].shape == (20, 4, 4)


def test_tum_round_trip(tmp_path: Path) -> None:
    P = random_poses(15, seed=1)
    ts = 1.7e9 + np.arange(15) * 0.1
    write_tum_poses(tmp_path / "p.tum", P, ts)
    back, t = read_poses(tmp_path / "p.tum")
    np.testing.assert_allclose(back, P, atol=1e-9)
    np.testing.assert_allclose(t, ts, atol=1e-6)


def test_tum_quaternions_are_normalised_and_comments_skipped(tmp_path: Path) -> None:
    path = tmp_path / "q.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n0.0 1 2 3 0 0 0 2\n0.1 1 2 3 0 0 3 3\n")
    P, t = read_poses(path)
    np.testing.assert_allclose(P[0], [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(
        P[1, :3, :3], Rotation.from_euler("z", 90, degrees=True).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(t, [0.0, 0.1])
    q = np.random.default_rng(2).normal(size=(50, 4))
    np.testing.assert_allclose(quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", r":2: 11 columns, expected 12"),
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 0\n", r":2: 7 columns, expected 8"),
        ("1 2 3\n", r":1: 3 columns; expected 12"),
        ("0 1 2 3 0 0 0 1\n0.1 1 2 x 0 0 0 1\n", r":2: 'x' is not a number"),
        ("0 1 2 3 0 0 0 0\n", r":1: quaternion has zero norm"),
        ("0 1 2 3 0 0 0 1\n0 1 nan 3 0 0 0 1\n", r":2: pose contains NaN"),
        ("# only a comment\n\n", "no poses found"),
    ],
)
def test_malformed_pose_files(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad_poses.txt"
    path.write_text(text)
    with pytest.raises(ScanFormatError, match=message) as err:
        read_poses(path)
    assert "bad_poses.txt" in str(err.value)


def test_missing_empty_and_binary_pose_files(tmp_path: Path) -> None:
    with pytest.raises(ScanFormatError, match="no such"):
        read_poses(tmp_path / "none.txt")
    (tmp_path / "e.txt").write_text("")
    with pytest.raises(ScanFormatError, match="empty"):
        read_poses(tmp_path / "e.txt")
    (tmp_path / "b.txt").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ScanFormatError, match="UTF-8"):
        read_poses(tmp_path / "b.txt")
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(ScanFormatError, match="expected 8"):
        read_poses(tmp_path / "k.txt", format="tum")
    with pytest.raises(ScanFormatError, match="unknown pose format"):
        read_poses(tmp_path / "k.txt", format="euroc")


@pytest.mark.parametrize(
    ("rows", "why"),
    [
        ("1000 0 0 1 0 1000 0 2 0 0 1000 3", "not a rotation"),  # rotation block scaled x1000
        ("1 0.5 0 1 0 1 0 2 0 0 1 3", "not a rotation"),  # sheared
        ("0 0 0 1 0 0 0 2 0 0 0 3", "not a rotation"),  # all-zero rotation
        ("-1 0 0 1 0 1 0 2 0 0 1 3", "reflection"),  # det -1
        ("1 0 0 1e12 0 1 0 2 0 0 1 3", "translation beyond"),
    ],
)
def test_poses_that_are_no_rigid_motion_are_refused_naming_the_line(tmp_path, rows, why):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" + rows + "\n")
    with pytest.raises(ScanFormatError, match=rf"poses.txt:2: pose is no rigid motion: .*{why}"):
        read_poses(path)


def test_in_memory_poses_must_be_rigid_motions():
    from placerec.errors import ScanDataError
    from placerec.types import ListSequence, Scan

    bad = np.tile(np.eye(4), (2, 1, 1))
    bad[1, 0, 0] = -1.0
    scans = [Scan(np.zeros((3, 3), np.float32), np.zeros(3, np.float32))] * 2
    with pytest.raises(ScanDataError, match="seq: pose 1 is no rigid motion: rotation block is a reflection"):
        ListSequence(scans, bad, name="seq")
    # rounding a file with 6 significant digits leaves a rotation a rotation
    ok = np.tile(np.eye(4), (2, 1, 1))
    ok[1, :3, :3] = np.round(Rotation.from_euler("z", 0.3).as_matrix(), 6)
    assert ListSequence(scans, ok, name="seq").poses.shape == (2, 4, 4)


def test_ground_truth_rows_and_times_are_checked_before_use():
    from placerec.io.datasets.trajectory import interpolate_poses, match_nearest

    poses = np.tile(np.eye(4), (3, 1, 1))
    times = np.array([0.0, 1.0, 2.0])
    got, inside = interpolate_poses(times, poses, np.array([0.5, 5.0]), "gt.csv")
    assert got.shape == (1, 4, 4) and inside.tolist() == [True, False]
    flipped = poses.copy()
    flipped[2, 1, 1] = -1.0  # a reflection, which scipy would reject with a ValueError
    with pytest.raises(ScanFormatError, match="gt.csv: ground-truth row 2 is no rigid motion: .*reflection"):
        interpolate_poses(times, flipped, np.array([0.5]), "gt.csv")
    for bad in ([0.0, np.nan, 2.0], [0.0, 2.0, 1.0]):
        with pytest.raises(ScanFormatError, match="gt.csv: ground-truth times must be finite"):
            interpolate_poses(np.array(bad), poses, np.array([0.5]), "gt.csv")
    with pytest.raises(ScanFormatError, match="times.txt: ground-truth times must be finite"):
        match_nearest(np.array([0.0, np.inf]), np.array([0.5]), 0.1, "times.txt")


def test_a_calibration_with_two_different_tr_lines_is_refused(tmp_path):
    from placerec.io.datasets.kitti import read_kitti_calib

    eye = "1 0 0 0 0 1 0 0 0 0 1 0"
    calib = tmp_path / "calib.txt"
    calib.write_text(f"P0: {eye}\nTr: {eye}\nTr: {eye}\n")  # the same line twice: one transform
    assert np.array_equal(read_kitti_calib(calib)["Tr"], np.eye(4))
    calib.write_text(f"P0: {eye}\nTr: {eye}\nTr: 0 -1 0 0 1 0 0 0 0 0 1 0\n")
    with pytest.raises(ScanFormatError, match=r"calib.txt:3: a second, different 'Tr' line"):
        read_kitti_calib(calib)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0.0\nnan\n0.2\n", r"times.txt:2: timestamp nan is not a finite"),
        ("0.0\n0.2\n0.1\n", r"times.txt:3: timestamp 0.1 s does not come after the previous one \(0.2 s\)"),
        ("0.0\n0.1\n0.1\n", r"times.txt:3: .*must increase strictly"),  # two scans at one time
    ],
)
def test_times_must_be_finite_and_increase(tmp_path, text, match):
    from placerec.io.file_sequence import read_times

    (tmp_path / "times.txt").write_text(text)
    with pytest.raises(ScanFormatError, match=match):
        read_times(tmp_path / "times.txt", 3)
    (tmp_path / "ok.txt").write_text("0.0\n0.1\n0.1000001\n")
    assert read_times(tmp_path / "ok.txt", 3).tolist() == [0.0, 0.1, 0.1000001]
