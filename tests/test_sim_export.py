"""Exporting simulated sequences as KITTI-style folders, and the map/query localisation split."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from placerec.sim import (
    CONDITIONS,
    SimulatedSequence,
    make_localization_split,
    simulate,
    write_kitti_sequence,
)
from placerec.types import SensorInfo


def _read_poses(path: Path) -> np.ndarray:
    rows = np.loadtxt(path, ndmin=2)
    assert rows.shape[1] == 12
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :] = rows.reshape(-1, 3, 4)
    return out


@pytest.mark.parametrize("sensor", ["vlp16", "os1-64"])
def test_kitti_folder(tmp_path: Path, sensor: str) -> None:
    seq = SimulatedSequence("town", sensor, n_scans=3, seed=4, odometry_drift=True)
    out = write_kitti_sequence(seq, tmp_path / "seq", progress=False)
    bins = sorted((out / "velodyne").glob("*.bin"))
    assert [b.name for b in bins] == ["000000.bin", "000001.bin", "000002.bin"]
    info = SensorInfo.from_dict(yaml.safe_load((out / "sensor.yaml").read_text()))
    assert info == seq.sensor_info
    assert set(yaml.safe_load((out / "sensor.yaml").read_text())) == {
        "name",
        "beam_elevations_deg",
        "columns",
        "intensity_max",
        "min_range",
        "max_range",
    }
    for i, b in enumerate(bins):
        ring = np.load(out / "ring" / f"{i:06d}.npy")
        col = np.load(out / "column" / f"{i:06d}.npy")
        assert ring.dtype == np.int16 and b.stat().st_size == 16 * len(ring) == 16 * len(col)
        rec = np.fromfile(b, dtype=np.float32).reshape(-1, 4)
        scan = seq[i]
        valid = np.any(scan.xyz != 0, axis=1)
        assert np.array_equal(rec[:, :3], scan.xyz[valid])
        assert np.allclose(rec[:, 3] * info.intensity_max, scan.intensity[valid], atol=1e-2)
        assert rec[:, 3].min() >= 0.0 and rec[:, 3].max() <= 1.0
        assert np.array_equal(ring, scan.ring[valid])
        if scan.shape is not None:
            assert np.array_equal(col, np.tile(np.arange(scan.shape[1]), scan.shape[0])[valid])
    assert np.allclose(_read_poses(out / "poses.txt"), seq.poses, atol=1e-6)
    assert np.allclose(_read_poses(out / "odometry_poses.txt"), seq.odometry_poses, atol=1e-6)
    assert np.allclose(np.loadtxt(out / "times.txt"), seq.timestamps, atol=1e-6)
    assert "Tr:" in (out / "calib.txt").read_text()
    meta = yaml.safe_load((out / "simulation.yaml").read_text())
    assert meta["spec"]["seed"] == 4 and len(meta["beam_response"]["gain"]) == seq.sensor.n_beams


def test_simulate_one_liner_is_deterministic(tmp_path: Path) -> None:
    a = simulate("town", "vlp16", 2, 7, tmp_path / "a", progress=False)
    b = simulate("town", "vlp16", 2, 7, tmp_path / "b", progress=False)
    for name in ("velodyne/000001.bin", "ring/000001.npy", "poses.txt", "sensor.yaml"):
        assert (a / name).read_bytes() == (b / name).read_bytes()


def test_localization_split() -> None:
    split = make_localization_split("town", "vlp16", seed=0, n_queries=4, n_map=120)
    assert set(split.queries) == set(CONDITIONS) and len(split.map) == 120
    world = split.map.world
    for cond, q in split.queries.items():
        assert len(q) == 4
        _, dist = split.nearest_map(cond)
        assert np.all(dist <= 10.0 + 1e-9)
        xy = q.poses[:, :2, 3]
        height = q.poses[:, 2, 3] - world.ground_height(xy[:, 0], xy[:, 1])
        if cond == "pole":
            assert np.all((height >= 0.8) & (height <= 2.5))
        else:
            assert np.allclose(height, split.map.sensor.mount_height)
        assert np.allclose(q.poses[:, 2, :3], [0, 0, 1])  # gravity aligned
        assert q.beam_response.gain.tolist() == split.map.beam_response.gain.tolist()  # same sensor unit
    near = lambda s: np.mean(np.linalg.norm(s.xyz, axis=1) < 4.5)  # noqa: E731
    occ = np.mean([near(split.queries["occlusion"][i]) for i in range(2)])
    free = np.mean([near(split.queries["gator"][i]) for i in range(2)])
    assert occ > free
