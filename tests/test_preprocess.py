from typing import get_args

import numpy as np
import pytest

from placerec.config import load_config
from placerec.errors import ConfigError, ScanDataError
from placerec.intensity import (
    INTENSITY_NORMALIZERS,
    IntensitySpec,
    default_intensity_spec,
    normalize_intensity,
)
from placerec.preprocess import PreprocessParams, crop, preprocess_scan, remove_invalid, voxel_downsample
from placerec.types import Scan, SensorInfo


def test_remove_invalid_counts_nan_inf_and_no_return():
    xyz = np.array(
        [[1, 2, 3], [np.nan, 0, 0], [0, 0, 0], [np.inf, 1, 1], [4, 5, 6], [1e5, 0, 0], [1e-8, 0, 0]],
        np.float32,
    )
    s = Scan(xyz, [1, 2, 3, 4, np.nan, 5, 6])
    out, counts = remove_invalid(s)
    # the origin, a fill-value range and a point closer than MIN_RETURN_M are no returns (types.valid_points)
    assert counts == {"nonfinite": 3, "no_return": 3}
    assert out.xyz.tolist() == [[1, 2, 3]]


def test_remove_invalid_keeps_organised_grid_when_asked():
    xyz = np.array([[1, 0, 0], [np.nan, 0, 0], [0, 1, 0], [0, 0, 2]], dtype=np.float32)
    s = Scan(xyz, [1, 2, 3, 4], shape=(2, 2))
    out, _ = remove_invalid(s, keep_organized=True)
    assert out.shape == (2, 2) and out.xyz[1].tolist() == [0, 0, 0] and out.intensity[1] == 0
    assert remove_invalid(s)[0].shape is None


def test_crop_range_and_height():
    s = Scan([[1, 0, 0], [10, 0, 0], [50, 0, 0], [3, 0, -5]], [0, 0, 0, 0])
    assert len(crop(s, min_range=2, max_range=20)) == 2
    assert crop(s, min_z=-1).xyz[:, 2].min() >= -1


def test_crop_elevation_band_keeps_points_by_their_angle_above_the_horizon():
    # elevations: 0, +45, -45, +10, -30 deg (the last two just inside, then outside, a (-20, 10) band)
    r = 10.0
    angles = np.radians([0.0, 45.0, -45.0, 9.9, 10.1, -19.9, -20.1, -30.0])
    xyz = np.c_[r * np.cos(angles), np.zeros_like(angles), r * np.sin(angles)]
    s = Scan(xyz, np.arange(len(angles), dtype=np.float32))
    kept = crop(s, elevation_deg=(-20.0, 10.0))
    assert kept.intensity.tolist() == [0.0, 3.0, 5.0]
    # a point's elevation does not depend on its azimuth or range
    turned = Scan(np.c_[np.zeros_like(angles), -3 * xyz[:, 0], 3 * xyz[:, 2]], s.intensity)
    assert crop(turned, elevation_deg=(-20.0, 10.0)).intensity.tolist() == [0.0, 3.0, 5.0]
    # through preprocess_scan, and an organised scan keeps its grid with the dropped points zeroed
    p = PreprocessParams.model_validate({"elevation_deg": [-20, 10], "intensity": {"mode": "raw"}})
    assert preprocess_scan(s, p).intensity.tolist() == [0.0, 3.0, 5.0]
    org = Scan(xyz, s.intensity + 1, shape=(2, 4))
    out = preprocess_scan(org, p, keep_organized=True)
    assert out.shape == (2, 4) and np.count_nonzero(np.any(out.xyz != 0, axis=1)) == 3


def test_elevation_band_is_checked_and_absent_from_the_dump_when_unset():
    assert "elevation_deg" not in PreprocessParams().model_dump(mode="json")
    band = PreprocessParams.model_validate({"elevation_deg": [-15, 2]})
    assert band.model_dump()["elevation_deg"] == [-15, 2]
    for bad in ([2, -15], [-15], [-90, 2], [0, 1, 2], [-1, "2"]):
        with pytest.raises(ConfigError, match="elevation_deg"):
            PreprocessParams.model_validate({"elevation_deg": bad})


def test_voxel_downsample_hand_computed():
    # two points in voxel (0,0,0), one in voxel (1,0,0) at voxel size 1
    xyz = [[0.1, 0.1, 0.1], [0.5, 0.5, 0.3], [1.5, 0.2, 0.2]]
    s = Scan(xyz, [1.0, 3.0, 10.0], ring=[4, 7, 2])
    v = voxel_downsample(s, 1.0)
    order = np.argsort(v.xyz[:, 0])
    assert np.allclose(v.xyz[order], [[0.3, 0.3, 0.2], [1.5, 0.2, 0.2]])
    assert np.allclose(v.intensity[order], [2.0, 10.0])
    # both points are equally far from the centroid (0.3,0.3,0.2)? no: distances differ -> nearest is point 0
    d0 = np.linalg.norm(np.array(xyz[0]) - [0.3, 0.3, 0.2])
    d1 = np.linalg.norm(np.array(xyz[1]) - [0.3, 0.3, 0.2])
    assert v.ring[order].tolist() == [4 if d0 < d1 else 7, 2]


def test_voxel_downsample_negative_coordinates_and_count():
    rng = np.random.default_rng(1)
    xyz = rng.uniform(-10, 10, size=(20000, 3))
    s = Scan(xyz, rng.random(20000))
    v = voxel_downsample(s, 0.5)
    cells = {tuple(c) for c in np.floor(xyz.astype(np.float32) / np.float32(0.5)).astype(int)}
    assert len(v) == len(cells)
    assert np.isclose(v.intensity.mean(), s.intensity.mean(), atol=0.02)
    with pytest.raises(ScanDataError):
        voxel_downsample(s, 0.0)
    with pytest.raises(ScanDataError, match="finite"):
        voxel_downsample(Scan([[np.nan, 0, 0]], [0]), 1.0)
    assert len(voxel_downsample(Scan(np.zeros((0, 3)), np.zeros(0)), 1.0)) == 0


def test_intensity_normalisers():
    s = Scan(np.ones((4, 3)), [0, 50, 100, 200], sensor=SensorInfo("vlp16"))
    assert normalize_intensity(s).intensity.tolist() == [0, 0.5, 1, 1]  # VLP-16: raw >= 100 -> 1
    p = normalize_intensity(s, IntensitySpec(mode="percentile", percentile=50))
    assert p.intensity.max() == 1.0 and np.isclose(p.intensity[1], 50 / 75)
    assert normalize_intensity(s, IntensitySpec(mode="raw")).intensity.tolist() == [0, 50, 100, 200]
    assert set(get_args(IntensitySpec.model_fields["mode"].annotation)) == set(INTENSITY_NORMALIZERS)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"mode": "bogus"}, r"IntensitySpec: mode: Input should be 'raw', 'linear' or 'percentile'"),
        ({"mode": "linear"}, r"IntensitySpec: mode 'linear' needs a 'saturation' value"),
        (
            {"mode": "percentile", "percentile": 0},
            r"IntensitySpec: percentile: Input should be greater than 0",
        ),
        ({"saturation": -1.0}, r"IntensitySpec: saturation: Input should be greater than 0"),
        ({"mode": "raw", "gain": 2}, r"gain: unknown key; allowed keys there: mode, percentile, saturation"),
    ],
)
def test_intensity_spec_is_checked_when_built(values, message):
    with pytest.raises(ConfigError, match=message):
        IntensitySpec(**values)


def test_preprocess_params_are_checked_when_built():
    with pytest.raises(ConfigError, match=r"PreprocessParams: voxel_size: Input should be greater than 0"):
        PreprocessParams(voxel_size=0.0)
    with pytest.raises(ConfigError, match=r"intensity\.mode: Input should be"):
        PreprocessParams(intensity={"mode": "bogus"})
    with pytest.raises(
        ConfigError, match=r"min_rnage: unknown key; allowed keys there: elevation_deg, intensity, max_range"
    ):
        PreprocessParams(min_rnage=1.0)
    assert default_intensity_spec("OS1-64").mode == "percentile"


def test_preprocess_scan_applies_params():
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-30, 30, size=(5000, 3))
    xyz[:10] = np.nan
    s = Scan(xyz, rng.uniform(0, 255, 5000), sensor=SensorInfo("vlp16"))
    out = preprocess_scan(s, PreprocessParams(min_range=1.0, max_range=20.0, voxel_size=1.0))
    assert np.isfinite(out.xyz).all() and out.intensity.max() <= 1.0
    assert np.linalg.norm(out.xyz, axis=1).max() <= 20.0 + 1e-3
    assert len(out) < len(s)
    plain = preprocess_scan(
        s
    )  # no params: invalid points removed, the sensor's intensity default (raw / 100)
    assert len(plain) == len(s) - 10 and plain.intensity.max() == 1.0


def test_the_config_section_is_the_preprocess_params():
    """An experiment config's ``preprocess`` section is `PreprocessParams` (0.5 m min_range by default); ``auto``
    intensity means the sensor's default, a calibration table replaces the normalisation."""
    cfg = load_config(None, ["preprocess.max_z=3.0", "preprocess.intensity.calibration=t.npz"])
    assert type(cfg.preprocess) is PreprocessParams and cfg.preprocess == PreprocessParams(
        min_range=0.5, max_z=3.0, intensity={"calibration": "t.npz"}
    )
    assert cfg.preprocess.intensity.spec() is None  # auto: the sensor's default
    linear = PreprocessParams(min_range=0.5, intensity={"mode": "linear", "saturation": 50.0})
    assert linear.intensity.spec() == IntensitySpec(mode="linear", saturation=50.0)
    s = Scan([[1, 0, 0], [2, 0, 0]], [25.0, 100.0], sensor=SensorInfo("vlp16"))
    assert preprocess_scan(s, linear).intensity.tolist() == [0.5, 1.0]


def test_voxel_speed_is_reasonable_on_a_kitti_sized_scan():
    """Not a timing assertion, only a sanity check that the vectorised path handles 120k points."""
    rng = np.random.default_rng(3)
    s = Scan(rng.uniform(-80, 80, size=(120_000, 3)), rng.random(120_000), ring=rng.integers(0, 64, 120_000))
    v = voxel_downsample(s, 0.4)
    assert len(v) > 1000 and v.ring is not None
