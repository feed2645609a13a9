"""A ``.bin`` read without a format: KITTI, NCLT recognised by its bytes, or a clear refusal."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from placerec.cli import app
from placerec.errors import ScanFormatError
from placerec.io import FolderSequence, read_scan, write_scan
from placerec.io.nclt import NCLT_SENSOR
from placerec.types import Scan

NCLT_FRAME = "nclt_hdl32_frame/1326652795280148.bin"
_NCLT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])


def _nclt_records(n: int, seed: int = 0) -> np.ndarray:
    """``n`` NCLT records of points within 30 m (metres = value * 0.005 - 100)."""
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, _NCLT_DTYPE)
    for c in "xyz":
        rec[c] = np.round((rng.uniform(-30, 30, n) + 100) / 0.005).astype(np.uint16)
    rec["i"] = rng.integers(0, 256, n)
    rec["l"] = np.arange(n) % 32
    return rec


def test_real_nclt_frame_is_recognised_without_a_format(real_data: Path, caplog) -> None:
    path = real_data / NCLT_FRAME
    assert path.stat().st_size % 16 == 0  # as many bytes as whole KITTI records: the size alone cannot tell
    with caplog.at_level(logging.INFO, logger="placerec.io.bin_sniff"):
        s = read_scan(path)
    assert "format='nclt'" in caplog.text
    assert len(s) == 23_546 and s.sensor == NCLT_SENSOR and s.ring.max() == 31
    assert s.ranges.max() < 130
    np.testing.assert_array_equal(s.xyz, read_scan(path, format="nclt").xyz)
    forced = read_scan(path, format="kitti")  # an explicit format is obeyed
    assert len(forced) == 23_546 // 2


def test_real_nclt_frame_through_a_folder_and_the_cli(real_data: Path, tmp_path: Path) -> None:
    folder = tmp_path / "velodyne_sync"
    folder.mkdir()
    for k in range(2):
        (folder / f"{k}.bin").write_bytes((real_data / NCLT_FRAME).read_bytes())
    seq = FolderSequence(folder)
    assert len(seq[1]) == 23_546 and seq[0].sensor == NCLT_SENSOR
    result = CliRunner().invoke(app, ["info", str(real_data / NCLT_FRAME), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["points"] == 23_546 and summary["beams"] == 32 and "nclt" in summary["sensor"]


def test_synthetic_nclt_recognised_and_kitti_kept(tmp_path: Path) -> None:
    nclt = tmp_path / "nclt.bin"
    _nclt_records(2000).tofile(nclt)  # 16000 bytes: also 1000 KITTI records
    s = read_scan(nclt)
    assert len(s) == 2000 and s.ring is not None and np.abs(s.xyz).max() <= 30.01
    odd = tmp_path / "odd.bin"
    _nclt_records(2001).tofile(odd)  # not a whole number of KITTI records
    assert len(read_scan(odd)) == 2001
    kitti = tmp_path / "kitti.bin"
    rng = np.random.default_rng(1)
    write_scan(kitti, Scan(rng.normal(size=(3000, 3)) * 20, rng.random(3000)))
    assert len(read_scan(kitti)) == 3000 and read_scan(kitti).ring is None


def test_bin_that_is_neither_format_names_both(tmp_path: Path) -> None:
    path = tmp_path / "garbage.bin"
    rec = np.full((500, 4), 0.5, "<f4")
    rec[:, :3] = 3e6  # 3000 km: no LiDAR point; intensity bytes rule out NCLT laser ids
    rec.tofile(path)
    with pytest.raises(ScanFormatError, match=r"garbage\.bin.*100% .* beyond 10000 m.*format='nclt'"):
        read_scan(path)
    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 2 and "format='nclt'" in result.output and "Traceback" not in result.output
    assert len(read_scan(path, format="kitti")) == 500


def test_far_points_in_a_few_records_do_not_change_the_format(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(1000, 3)) * 20
    xyz[:50] = 1e6  # 5 % outliers stay a KITTI scan
    path = tmp_path / "outliers.bin"
    write_scan(path, Scan(xyz, rng.random(1000)))
    assert len(read_scan(path)) == 1000


def test_a_fifo_is_refused_without_blocking(tmp_path):
    import os

    from placerec.errors import ScanFormatError
    from placerec.io import read_scan

    fifo = tmp_path / "scan.bin"
    os.mkfifo(fifo)  # opening it for reading would wait for a writer forever
    with pytest.raises(ScanFormatError, match="special file"):
        read_scan(fifo)
