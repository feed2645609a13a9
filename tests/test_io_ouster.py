"""Ouster captures: poses beside the capture, truncated captures (real ouster-sdk test data; skipped without)."""

from __future__ import annotations

import importlib.util
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from placerec.errors import ScanFormatError
from placerec.io import open_sequence, read_poses

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("ouster") is None,
    reason="ouster-sdk not installed (pip install placerec[ouster])",
)

STEM = "OS-1-128_v2.3.0_1024x10_lb_n3"


@pytest.fixture
def capture(real_data: Path, tmp_path: Path) -> Path:
    """A copy of the 3-frame OS1-128 capture with its metadata (no poses file)."""
    src = real_data / "ouster_sdk_pcaps"
    shutil.copy(src / f"{STEM}.pcap", tmp_path)
    shutil.copy(src / "OS-1-128_v2.3.0_1024x10.json", tmp_path)
    return tmp_path / f"{STEM}.pcap"


def test_poses_kitti_beside_the_capture_are_its_poses(real_data: Path, capture: Path) -> None:
    assert open_sequence(capture).poses is None
    poses_file = real_data / "ouster_sdk_pcaps" / f"{STEM}_poses_kitti.txt"
    shutil.copy(poses_file, capture.parent)
    seq = open_sequence(capture)
    P, _ = read_poses(poses_file)
    np.testing.assert_array_equal(seq.poses, P)
    assert seq.poses.shape == (3, 4, 4) and seq.poses[1, 0, 3] == pytest.approx(0.2454, abs=1e-4)


def test_explicit_poses_and_a_wrong_count(capture: Path, tmp_path: Path) -> None:
    shifted = np.tile(np.eye(4)[:3].reshape(1, 12), (3, 1))
    shifted[:, 3] = [0.0, 1.0, 2.0]
    other = tmp_path / "mine.txt"
    np.savetxt(other, shifted)
    np.testing.assert_allclose(open_sequence(capture, poses=other).poses[:, 0, 3], [0, 1, 2])
    np.savetxt(capture.with_name(f"{STEM}_poses_kitti.txt"), shifted[:2])
    with pytest.raises(ScanFormatError, match=r"_poses_kitti\.txt: 2 poses for 3 scans"):
        open_sequence(capture)


@pytest.mark.parametrize("keep", [0.7, 0.2])
def test_truncated_capture_warns(capture: Path, caplog, keep: float) -> None:
    data = capture.read_bytes()
    capture.write_bytes(data[: int(len(data) * keep)])
    with caplog.at_level(logging.WARNING, logger="placerec.io.ouster"):
        seq = open_sequence(capture)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert (
        len(warnings) == 1
        and "truncated" in warnings[0]
        and f"frame {len(seq) - 1} of {len(seq)}" in warnings[0]
    )
    assert "of 1024 columns" in warnings[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="placerec.io.ouster"):
        seq[len(seq) - 1]  # reported once per frame
        for i in range(len(seq) - 1):
            seq[i]  # the complete frames before it do not warn
    assert not caplog.records


def test_complete_capture_does_not_warn(capture: Path, caplog) -> None:
    with caplog.at_level(logging.WARNING, logger="placerec.io.ouster"):
        seq = open_sequence(capture)
        for i in range(len(seq)):
            seq[i]
    assert not caplog.records
