"""Readers on the real samples in ../shared/data/real (skipped when that folder is absent)."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from placerec.errors import DependencyError, ScanFormatError
from placerec.io import FolderSequence, KittiSequence, open_sequence, read_poses, read_scan


def _row_elevations(scan) -> np.ndarray:
    xyz = scan.organized("xyz").astype(np.float64)
    r = np.linalg.norm(xyz, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        el = np.degrees(np.arcsin(np.where(r > 0.5, xyz[..., 2] / r, np.nan)))
    return np.nanmedian(el, axis=1)


def test_kitti_frames(real_data: Path) -> None:
    for name in ("000094.bin", "000095.bin", "000198.bin", "000199.bin"):
        s = read_scan(real_data / "kitti00_frames" / name)
        assert 110_000 < len(s) < 130_000
        assert 0.0 <= s.intensity.min() and s.intensity.max() <= 1.0 and s.intensity.max() > 0.9
        assert 0.2 < np.median(s.intensity) < 0.4
        assert np.percentile(s.ranges, 99) < 90


def test_kitti_poses_and_sequence_layout(real_data: Path, tmp_path: Path) -> None:
    P, t = read_poses(real_data / "kitti00_frames" / "poses_00.txt")
    assert P.shape == (4541, 4, 4) and t is None
    np.testing.assert_allclose(P[0], np.eye(4), atol=1e-6)
    np.testing.assert_allclose(
        P[:, :3, :3] @ P[:, :3, :3].transpose(0, 2, 1), np.tile(np.eye(3), (4541, 1, 1)), atol=1e-5
    )
    # a two-frame KITTI layout made of the real frames 94 and 95 with their ground-truth poses
    (tmp_path / "velodyne").mkdir()
    for k, name in enumerate(("000094.bin", "000095.bin")):
        shutil.copy(real_data / "kitti00_frames" / name, tmp_path / "velodyne" / f"{k:06d}.bin")
    lines = (real_data / "kitti00_frames" / "poses_00.txt").read_text().splitlines()[94:96]
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    seq = KittiSequence(tmp_path)
    assert len(seq) == 2 and len(seq[1]) > 100_000
    np.testing.assert_allclose(seq.poses, P[94:96])


def test_kitti_raw_pcd_sequence(real_data: Path) -> None:
    seq = FolderSequence(real_data / "kitti_raw_hdl64_sequence")
    assert len(seq) == 22 and seq.files[0].name == "0000000000.pcd" and seq.poses is None
    for i in (0, 21):
        s = seq[i]
        assert 110_000 < len(s) < 130_000
        assert s.intensity.max() <= 1.0 and np.isfinite(s.xyz).all()
    assert isinstance(open_sequence(real_data / "kitti_raw_hdl64_sequence"), FolderSequence)


def test_nclt_frame(real_data: Path) -> None:
    s = read_scan(real_data / "nclt_hdl32_frame" / "1326652795280148.bin", format="nclt")
    assert len(s) == 23_546
    assert s.ring.min() == 0 and s.ring.max() == 31
    assert s.ranges.max() < 130 and np.median(s.ranges) > 2
    assert s.intensity.max() == 255
    # HDL-32E interleaving: even laser ids look lower than the next odd one
    el = np.degrees(np.arcsin(s.xyz[:, 2] / np.maximum(s.ranges, 1e-6)))
    med = np.array([np.median(el[s.ring == k]) for k in range(32)])
    assert np.all(med[0:16:2] < med[1:16:2])
    # without a format the bytes are recognised as NCLT (tests/test_io_bin_sniff.py)
    assert len(read_scan(real_data / "nclt_hdl32_frame" / "1326652795280148.bin")) == 23_546


def test_os1_64_organised_pair(real_data: Path) -> None:
    for name in ("32line_1.bin", "32line_2.bin"):
        s = read_scan(
            real_data / "ouster_os1_64_revisit_pair" / name, organized=True, layout=(64, 1024, "column-major")
        )
        assert s.shape == (64, 1024) and len(s) == 65_536
        np.testing.assert_array_equal(s.organized("ring")[:, 0], np.arange(64))
        el = _row_elevations(s)
        assert el[0] == pytest.approx(17.8, abs=0.3) and el[-1] < -14
        assert np.all(np.diff(el[np.isfinite(el)]) < 0)  # elevation decreases down the rows
        valid = np.any(s.xyz != 0, axis=1)
        assert 0.3 < valid.mean() < 0.6  # invalid returns stay zeros
        assert 100 < np.median(s.intensity[valid]) < 250
        with pytest.raises(ScanFormatError, match="organised 128 x 1024"):
            read_scan(real_data / "ouster_os1_64_revisit_pair" / name, organized=True, layout=(128, 1024))


ouster_required = pytest.mark.skipif(
    importlib.util.find_spec("ouster") is None,
    reason="ouster-sdk not installed (pip install placerec[ouster])",
)


@ouster_required
@pytest.mark.parametrize(
    "pcap, meta, frames, shape",
    [
        ("OS-1-128_v2.3.0_1024x10_lb_n3.pcap", "OS-1-128_v2.3.0_1024x10.json", 3, (128, 1024)),
        ("OS-1-64_1024x10_fw20.pcap", "OS-1-64_sensor_config_reduced.json", 1, (64, 1024)),
    ],
)
def test_ouster_pcaps(real_data: Path, pcap: str, meta: str, frames: int, shape: tuple[int, int]) -> None:
    from placerec.io.ouster import OusterSequence, find_ouster_metadata, read_ouster_pcap

    folder = real_data / "ouster_sdk_pcaps"
    assert find_ouster_metadata(folder / pcap).name == meta
    scans = read_ouster_pcap(folder / pcap, folder / meta)
    assert len(scans) == frames
    for s in scans:
        assert s.shape == shape and len(s) == shape[0] * shape[1]
        assert s.sensor.n_beams == shape[0] and s.sensor.columns == shape[1]
        assert s.sensor.intensity_max == 255.0
        valid = np.any(s.xyz != 0, axis=1)
        assert valid.mean() > 0.2
        refl = s.intensity[valid]
        assert refl.max() > 100 and len(np.unique(refl)) > 50  # non-trivial reflectivity
        np.testing.assert_array_equal(s.organized("ring")[:, 0], np.arange(shape[0]))
        el = _row_elevations(s)
        # down the rows elevation decreases (a sparse, near-range capture allows a few noisy rows)
        assert el[0] > 15 and el[-1] < -15 and np.mean(np.diff(el[np.isfinite(el)]) < 0) > 0.95
        assert 0 <= s.time.min() and s.time.max() < 0.11
    seq = open_sequence(folder / pcap)
    assert isinstance(seq, OusterSequence) and len(seq) == frames
    assert np.all(np.diff(seq.timestamps) > 0.09) if frames > 1 else seq.timestamps.shape == (1,)
    np.testing.assert_array_equal(seq[frames - 1].xyz, scans[-1].xyz)
    if frames == 3:  # the capture's <stem>_poses_kitti.txt is loaded as its poses
        P, _ = read_poses(folder / "OS-1-128_v2.3.0_1024x10_lb_n3_poses_kitti.txt")
        assert P.shape == (3, 4, 4)
        np.testing.assert_array_equal(seq.poses, P)
    else:
        assert seq.poses is None


@ouster_required
def test_ouster_metadata_mismatch(real_data: Path) -> None:
    from placerec.io.ouster import OusterSequence

    folder = real_data / "ouster_sdk_pcaps"
    with pytest.raises(ScanFormatError, match="does not match"):
        OusterSequence(folder / "OS-1-64_1024x10_fw20.pcap", metadata=folder / "OS-1-128_v2.3.0_1024x10.json")


def test_ouster_missing_sdk_message(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    import placerec.io.ouster as ou

    monkeypatch.setitem(sys.modules, "ouster.sdk", None)  # makes `import ouster.sdk` fail
    with pytest.raises(DependencyError, match=r"pip install placerec\[ouster\]"):
        ou.OusterSequence(tmp_path / "x.pcap")
