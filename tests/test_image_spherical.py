"""Spherical intensity images for clouds that are not one 360 deg spinning sweep (issue #28)."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.image.projection import (
    ImageParams,
    fill_sparse_pixels,
    make_image,
    spherical_grid,
)
from placerec.types import Scan, SensorInfo

LIMITED = SensorInfo(
    name="solid", pattern="solid-state", horizontal_fov_deg=120.0, elevation_fov_deg=(45.0, 45.0)
)


def _points(az_deg: np.ndarray, el_deg: np.ndarray, r: float | np.ndarray = 10.0) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1) * np.reshape(
        r, (-1, 1)
    )


def test_auto_mode_picks_spherical_for_sensors_that_do_not_spin():
    xyz = _points(np.array([0.0, 30.0]), np.array([0.0, 10.0]))
    scan = Scan(xyz=xyz, intensity=np.ones(2), sensor=LIMITED)
    assert make_image(scan, ImageParams(resolution_deg=1.0)).mode == "spherical"
    spinning = Scan(
        xyz=xyz, intensity=np.ones(2), sensor=SensorInfo(name="s", beam_elevations_deg=(10.0, -10.0))
    )
    assert make_image(spinning).mode == "uniform"


def test_columns_and_rows_follow_azimuth_and_elevation_over_the_field_of_view():
    # a point straight ahead lands in the middle column; +60 deg (left edge) in column 0; the right edge in the last
    az = np.array([0.0, 59.9, -59.9, 0.0, 0.0])
    el = np.array([0.0, 0.0, 0.0, 44.9, -44.9])
    scan = Scan(xyz=_points(az, el), intensity=np.arange(1.0, 6.0), sensor=LIMITED)
    params = ImageParams(resolution_deg=1.0, fill_radius_px=0)
    grid = spherical_grid(scan, params)
    assert (grid.height, grid.width) == (90, 120)
    img = make_image(scan, params)
    v, u = np.nonzero(img.valid)
    got = {int(img.point_index[a, b]): (int(a), int(b)) for a, b in zip(v, u, strict=True)}
    assert got[0] == (45, 60)
    assert got[1][1] == 0 and got[2][1] == 119
    assert got[3][0] == 0 and got[4][0] == 89


def test_points_outside_the_horizontal_field_of_view_are_dropped():
    scan = Scan(xyz=_points(np.array([0.0, 90.0, 180.0]), np.zeros(3)), intensity=np.ones(3), sensor=LIMITED)
    img = make_image(scan, ImageParams(resolution_deg=1.0, fill_radius_px=0))
    assert int(img.valid.sum()) == 1 and int(img.point_index[img.valid][0]) == 0


def test_full_circle_spherical_matches_the_cylindrical_column_convention():
    info = SensorInfo(name="mid", pattern="non-repetitive", elevation_fov_deg=(52.0, 7.0))
    az = np.array([178.5, 0.5, -90.5])
    scan = Scan(xyz=_points(az, np.zeros(3)), intensity=np.ones(3), sensor=info)
    img = make_image(scan, ImageParams(resolution_deg=1.0, fill_radius_px=0))
    cols = {int(img.point_index[a, b]): int(b) for a, b in zip(*np.nonzero(img.valid), strict=True)}
    w = img.shape[1]
    assert w == 360
    for i, a in enumerate(az):  # eq. 2: u = 0.5 (1 - theta / pi) W
        assert cols[i] == int(np.floor(0.5 * (1 - np.radians(a) / np.pi) * w))


def test_automatic_resolution_follows_density_and_is_rounded():
    rng = np.random.default_rng(0)
    n = 40_000
    xyz = _points(rng.uniform(-60, 60, n), rng.uniform(-45, 45, n))
    scan = Scan(xyz=xyz, intensity=np.ones(n), sensor=LIMITED)
    grid = spherical_grid(scan, ImageParams(density_points_per_pixel=1.0))
    # 120 x 90 deg / 40k points -> sqrt(0.27) = 0.52 deg -> 0.5 deg after rounding
    assert (grid.width, grid.height) == (240, 180)
    sparse = spherical_grid(scan, ImageParams(density_points_per_pixel=4.0))
    assert sparse.width == int(np.ceil(120 / 1.05))  # four points a pixel -> sqrt(1.08) = 1.04 -> 1.05 deg


def test_sparse_pixel_filling_fills_gaps_between_points_and_not_beyond_the_radius():
    img = np.zeros((7, 7), np.float32)
    valid = np.zeros((7, 7), bool)
    img[3, 2], img[3, 4] = 10.0, 20.0
    valid[3, 2] = valid[3, 4] = True
    out, ok = fill_sparse_pixels(img, valid, 1)
    assert ok[3, 3] and out[3, 3] == pytest.approx(15.0)
    assert not ok[3, 0] and not ok[0, 0]  # two pixels away from any valid one
    assert out[3, 2] == 10.0  # valid pixels are left alone
    same, same_ok = fill_sparse_pixels(img, valid, 0)
    assert same is img and same_ok is valid


def test_empty_and_degenerate_clouds_give_a_blank_image():
    scan = Scan(xyz=np.zeros((0, 3)), intensity=np.zeros(0), sensor=LIMITED)
    img = make_image(scan)
    assert img.mode == "spherical" and not img.valid.any()


def test_sensor_info_checks_and_round_trips_the_fields_of_sensors_that_do_not_spin():
    from placerec.errors import ScanDataError

    info = SensorInfo(name="avia", pattern="non-repetitive", horizontal_fov_deg=70.4, elevation_fov_deg=(38.6, 38.6),
                      rate_hz=10.0)  # fmt: skip
    assert SensorInfo.from_dict(info.to_dict()) == info and not info.is_spinning
    assert info.vertical_fov_deg == (38.6, 38.6)
    # a spinning sensor's description is what it was before these fields existed
    assert set(SensorInfo(name="vlp16").to_dict()) == {
        "name", "beam_elevations_deg", "columns", "intensity_max", "min_range", "max_range"
    }  # fmt: skip
    for bad, field in (
        ({"pattern": "rotating"}, "pattern"),
        ({"horizontal_fov_deg": 400.0}, "horizontal_fov_deg"),
        ({"horizontal_fov_deg": float("nan")}, "horizontal_fov_deg"),
        ({"elevation_fov_deg": (10.0, -20.0)}, "elevation_fov_deg"),
        ({"elevation_fov_deg": (95.0, 0.0)}, "elevation_fov_deg"),
        ({"rate_hz": 0.0}, "rate_hz"),
    ):
        with pytest.raises(ScanDataError, match=field):
            SensorInfo(name="x", **bad)
    with pytest.raises(ScanDataError, match="elevation_fov_deg"):
        SensorInfo.from_dict({"name": "x", "elevation_fov_deg": [1.0]})
