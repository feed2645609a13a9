"""Simulator sensor presets: beam layouts, ray grids, and the elevations of simulated returns per ring."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.errors import ConfigError
from placerec.sim import SimulatedSequence, get_sensor, sensor_names
from placerec.sim.sensors import ray_grid
from placerec.types import SensorInfo


def _uniform_rows(xyz: np.ndarray, info: SensorInfo, rows: int) -> np.ndarray:
    """Row index of every point under the VPR paper's uniform projection (eq. 2)."""
    up, down = info.vertical_fov_deg
    fov = np.radians(up + down)
    rng = np.linalg.norm(xyz, axis=1)
    phi = np.arcsin(xyz[:, 2] / rng)
    v = (1.0 - (phi + np.radians(down)) / fov) * rows
    return np.clip(np.floor(v), 0, rows - 1).astype(int)


def test_presets_match_real_layouts() -> None:
    assert {"vlp16", "hdl64", "os1-64", "os1-64-gen2", "os1-128"} <= set(sensor_names())
    vlp = get_sensor("vlp16")
    assert vlp.n_beams == 16 and vlp.columns == 1800 and vlp.intensity_max == 255
    assert vlp.beam_elevations_deg[0] == pytest.approx(15.0) and vlp.beam_elevations_deg[-1] == pytest.approx(
        -15.0
    )
    assert np.allclose(np.diff(vlp.beam_elevations_deg), -2.0)
    hdl = get_sensor("hdl64")
    e = np.asarray(hdl.beam_elevations_deg)
    assert hdl.n_beams == 64 and e.max() == pytest.approx(2.0) and e.min() == pytest.approx(-24.9)
    spacing = -np.diff(e)
    assert np.median(spacing[:31]) == pytest.approx(1 / 3, abs=0.03)  # upper block
    assert np.median(spacing[32:]) == pytest.approx(0.517, abs=0.03)  # lower block
    assert np.std(spacing[:31]) > 0.01  # per-beam calibration errors
    for name, fov, beams in (("os1-64", 33.2, 64), ("os1-64-gen2", 45.0, 64), ("os1-128", 45.0, 128)):
        s = get_sensor(name)
        up, down = s.to_sensor_info().vertical_fov_deg
        assert s.n_beams == beams and s.columns == 1024 and s.organized
        assert up + down == pytest.approx(fov) and s.intensity_max == 65535
        assert np.allclose(np.diff(s.beam_elevations_deg), -fov / (beams - 1), atol=1e-3)
    assert get_sensor("OS1-64-gen1") is get_sensor("os1-64")
    with pytest.raises(ConfigError, match="allowed"):
        get_sensor("hdl32x")


def test_ring_zero_is_top_beam_and_sensor_info_roundtrips() -> None:
    for name in sensor_names():
        s = get_sensor(name)
        assert np.all(np.diff(s.beam_elevations_deg) < 0)
        info = s.to_sensor_info()
        assert SensorInfo.from_dict(info.to_dict()) == info
        # sensors without a beam layout (Livox lines, solid-state rows) record no beams; no columns for rosettes
        assert info.n_beams == (s.n_beams if s.beam_elevations_deg else None)
        assert info.columns == (s.columns or None)


def test_ray_grid_directions_follow_elevations_and_projection_columns() -> None:
    s = get_sensor("os1-64")
    g = ray_grid(s)
    el = np.degrees(np.arcsin(g.directions[:, 2]))
    assert np.allclose(el, np.asarray(s.beam_elevations_deg)[g.ring], atol=1e-4)
    theta = np.arctan2(g.directions[:, 1], g.directions[:, 0])
    u = np.floor(0.5 * (1.0 - theta / np.pi) * s.columns).astype(int)
    assert np.array_equal(u, g.column)
    assert np.array_equal(g.ring.reshape(64, 1024)[:, 0], np.arange(64))  # organised: row-major
    v = ray_grid(get_sensor("vlp16"))
    assert np.array_equal(v.ring[:16], np.arange(16))  # Velodyne: firing order, column by column


def test_hdl64_uniform_projection_leaves_empty_rows_os1_does_not() -> None:
    for name, expect_empty in (("hdl64", True), ("os1-64", False), ("os1-128", False)):
        s = get_sensor(name)
        rows = _uniform_rows(ray_grid(s).directions, s.to_sensor_info(), s.n_beams)
        empty = s.n_beams - len(np.unique(rows))
        assert (empty > 0) == expect_empty, (name, empty)
    hdl = get_sensor("hdl64")
    rows = _uniform_rows(ray_grid(hdl).directions, hdl.to_sensor_info(), 64)
    filled = np.zeros(64, bool)
    filled[rows] = True
    assert not filled[40:].all()  # the gaps are in the lower (sparser) block


@pytest.mark.parametrize("name", ["vlp16", "hdl64", "os1-64"])
def test_simulated_points_lie_on_their_beams(name: str) -> None:
    seq = SimulatedSequence("town", name, n_scans=3, seed=0)
    scan = seq[1]
    assert scan.ring is not None and scan.sensor == seq.sensor_info
    valid = np.any(scan.xyz != 0, axis=1)
    xyz, ring = scan.xyz[valid], scan.ring[valid]
    el = np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))
    expected = np.asarray(seq.sensor.beam_elevations_deg)[ring]
    assert np.max(np.abs(el - expected)) < 0.01
    assert len(np.unique(ring)) >= seq.sensor.n_beams - 2  # nearly every beam returns something
    if seq.sensor.organized:
        assert scan.shape == (seq.sensor.n_beams, seq.sensor.columns)
        assert np.all(scan.intensity[~valid] == 0)
        assert np.array_equal(scan.ring.reshape(scan.shape)[:, 0], np.arange(seq.sensor.n_beams))
    else:
        assert scan.shape is None and valid.all()
