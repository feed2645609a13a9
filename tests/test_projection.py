import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.image import (
    ImageParams,
    detect_empty_rows,
    fill_empty_rows,
    make_image,
    project_per_beam,
    project_uniform,
    to_uint8,
)
from placerec.types import Scan, SensorInfo

P = ImageParams(width=360, height=20, fov_up_deg=10.0, fov_down_deg=10.0)


def _scan(points, intensity, **kw):
    return Scan(np.asarray(points, np.float32), np.asarray(intensity, np.float32), **kw)


def test_point_straight_ahead_lands_in_centre_column_and_middle_row():
    inten, rng, idx = project_uniform(_scan([[10, 0, 0]], [7]), P)
    v, u = np.argwhere(idx >= 0)[0]
    assert u == 180 and v == 10 and inten[v, u] == 7 and rng[v, u] == pytest.approx(10)


def test_columns_follow_eq2_left_is_smaller_u():
    # theta = +90 deg (left) -> u = 0.5 * (1 - 0.5) * W = W/4; theta = -90 deg (right) -> 3W/4
    _, _, idx = project_uniform(_scan([[0, 10, 0], [0, -10, 0]], [1, 2]), P)
    cols = {int(idx[v, u]): u for v, u in np.argwhere(idx >= 0)}
    assert cols == {0: 90, 1: 270}


def test_top_of_fov_is_row_zero_and_bottom_last_row():
    up = np.tan(np.radians(9.9)) * 10
    _, _, idx = project_uniform(_scan([[10, 0, up], [10, 0, -up]], [1, 2]), P)
    rows = {int(idx[v, u]): v for v, u in np.argwhere(idx >= 0)}
    assert rows == {0: 0, 1: 19}


def test_nearest_range_wins():
    pts = [[20, 0, 0], [10, 0, 0], [30, 0, 0]]
    inten, rng, idx = project_uniform(_scan(pts, [1, 2, 3]), P)
    assert (idx >= 0).sum() == 1 and inten[idx >= 0][0] == 2 and rng[idx >= 0][0] == pytest.approx(10)


def test_wrap_around_behind_the_sensor():
    # just left of straight back -> u ~ 0, just right -> u ~ W-1: the seam is behind the sensor
    eps = 1e-3
    _, _, idx = project_uniform(_scan([[-10, eps, 0], [-10, -eps, 0], [-10, 0, 1.0]], [1, 2, 3]), P)
    cols = {int(idx[v, u]): u for v, u in np.argwhere(idx >= 0)}
    assert cols[0] == 0 and cols[1] == 359 and cols[2] in (0, 359)


def test_per_beam_uses_ring_rank_by_elevation():
    sensor = SensorInfo("x", beam_elevations_deg=(-5.0, 5.0, 0.0), columns=360)  # ring 1 is the top beam
    scan = _scan([[10, 0, 0], [10, 0, 0.8], [10, 0, -0.8]], [1, 2, 3], ring=[2, 1, 0], sensor=sensor)
    inten, _, _ = project_per_beam(scan)
    assert inten.shape == (3, 360) and inten[:, 180].tolist() == [2, 1, 3]
    with pytest.raises(ScanDataError, match="ring"):
        project_per_beam(_scan([[1, 0, 0]], [1]))


def test_empty_row_detection_and_interpolation():
    img = np.zeros((6, 8), np.float32)
    img[0], img[3], img[5] = 10, 40, 50
    valid = img > 0
    empty = detect_empty_rows(valid)
    assert empty.tolist() == [False, True, True, False, True, False]
    filled = fill_empty_rows(img, empty)
    assert np.allclose(filled[:, 0], [10, 20, 30, 40, 45, 50])


def test_uneven_beams_leave_empty_rows_that_get_filled():
    # 16 beams, two blocks with different spacing, projected into 32 uniform rows
    elev = np.r_[np.linspace(2, -8, 8), np.linspace(-9.5, -24, 8)]
    az = np.radians(np.arange(0.5, 360, 1.0))
    e, a = np.meshgrid(np.radians(elev), az, indexing="ij")
    pts = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3) * 20
    inten = np.repeat(np.arange(16.0), az.size) + 1
    scan = _scan(pts, inten)
    geometry = dict(mode="uniform", width=360, height=32, fov_up_deg=2.5, fov_down_deg=24.5)
    raw = make_image(
        scan,
        ImageParams(**geometry, fill_empty_rows=False, fill_holes_max_gap=0),
    )
    assert (~raw.valid).all(axis=1).sum() >= 10
    filled = make_image(scan, ImageParams(**geometry, fill_holes_max_gap=0))  # the paper's row filling alone
    assert filled.filled_rows.sum() == (~raw.valid).all(axis=1).sum()
    assert filled.valid.all(axis=1).sum() >= 30 and filled.image.dtype == np.uint8


def test_organized_scan_used_as_is_and_auto_modes():
    xyz = np.zeros((2 * 4, 3), np.float32)
    xyz[:, 0] = 5
    xyz[3] = 0  # no return
    scan = _scan(xyz, np.arange(8), shape=(2, 4))
    img = make_image(scan, ImageParams(fill_empty_rows=False))
    assert img.mode == "organized" and img.valid.sum() == 7 and img.point_index[0, 3] == -1
    assert make_image(_scan([[1, 0, 0]], [1], ring=[0])).mode == "per-beam"
    assert make_image(_scan([[1, 0, 0]], [1])).mode == "uniform"


def test_vertical_hole_filling_respects_max_gap():
    from placerec.image.projection import fill_vertical_holes

    img = np.array([[10, 10], [0, 0], [30, 0], [0, 0], [0, 0], [60, 60]], np.float32)
    valid = img > 0
    out, ok = fill_vertical_holes(img, valid, max_gap=1)
    assert out[1, 0] == 20 and ok[1, 0]  # between rows 0 and 2
    assert not ok[3, 0] and not ok[1, 1]  # gaps of 3 and 5 rows are left alone
    out, ok = fill_vertical_holes(img, valid, max_gap=3)
    assert ok[3, 0] and out[3, 0] == pytest.approx(40) and not ok[1, 1]


# ------------------------------------------------ degenerate scans give blank images, never a bare error
_VLP16 = SensorInfo("vlp16", beam_elevations_deg=tuple(np.linspace(-15, 15, 16)), columns=1800)


def _degenerate(case: str) -> Scan:
    rng = np.random.default_rng(0)
    n = 500
    rings = rng.integers(0, 16, n)
    if case == "origin":  # organised-style invalid returns, rings known
        return _scan(np.zeros((n, 3)), np.ones(n), ring=rings, sensor=_VLP16)
    if case == "far":  # 1e30 overflows float32 ranges to inf
        return _scan(np.full((n, 3), 1e30), np.ones(n), ring=rings, sensor=_VLP16)
    if case == "outside-fov":  # finite but all far above the field of view
        return _scan(np.c_[np.ones(n), np.zeros(n), np.full(n, 100.0)], np.ones(n), sensor=_VLP16)
    if case == "ten-points":
        return _scan(rng.normal(size=(10, 3)) * 10, rng.random(10), sensor=_VLP16)
    if case == "empty":
        return _scan(np.zeros((0, 3)), np.zeros(0), ring=np.zeros(0), sensor=_VLP16)
    if case == "organised-origin":  # an organised scan with no valid return
        return _scan(np.zeros((16 * 1800, 3)), np.zeros(16 * 1800), shape=(16, 1800), sensor=_VLP16)
    raise AssertionError(case)


@pytest.mark.parametrize("mode", ["auto", "uniform", "per-beam"])
@pytest.mark.parametrize("case", ["origin", "far", "outside-fov", "ten-points", "empty", "organised-origin"])
def test_degenerate_scans_give_a_blank_or_sparse_image(case, mode):
    scan = _degenerate(case)
    if mode == "per-beam" and scan.ring is None:
        with pytest.raises(ScanDataError, match="ring"):
            make_image(scan, ImageParams(mode=mode))
        return
    img = make_image(scan, ImageParams(mode=mode))
    assert img.image.dtype == np.uint8 and img.image.shape[0] == 16
    assert img.valid.sum() <= 10
    assert (img.image[~img.valid] == 0).all() and not img.filled_rows.any()


@pytest.mark.parametrize("value", [0.0, 5.0])
def test_constant_intensity_gives_a_flat_image(value):
    rng = np.random.default_rng(1)
    az = rng.uniform(-np.pi, np.pi, 4000)
    elev = np.radians(rng.uniform(-14, 14, 4000))
    xyz = 10 * np.c_[np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)]
    img = make_image(_scan(xyz, np.full(4000, value), sensor=_VLP16))
    assert img.valid.any()
    assert np.unique(img.image[img.valid]).size == 1  # one grey level (black for zero intensity)
    assert img.image.max() == (0 if value == 0 else 255)


def test_rings_outside_the_sensor_layout_are_a_scan_data_error():
    xyz = np.random.default_rng(2).normal(size=(50, 3)) * 10
    ring = np.r_[np.zeros(49), 40]
    with pytest.raises(ScanDataError, match="1 of 50 points have a ring outside 0..15"):
        make_image(_scan(xyz, np.ones(50), ring=ring, sensor=_VLP16, source="f.pcd"))


def test_per_beam_without_layout_and_negative_rings_gives_a_blank_image():
    img = make_image(_scan(np.ones((5, 3)), np.ones(5), ring=np.full(5, -3)), ImageParams(mode="per-beam"))
    assert img.shape == (1, 1024) and not img.valid.any()


# ------------------------------------------------ default row filling on real KITTI (no black streaks)
def _streak_rows(valid: np.ndarray) -> int:
    """Rows emptier than both neighbours by more than 5 % of the width (tools/eval_row_filling.py)."""
    ef = 1.0 - valid.mean(axis=1)
    return int((ef[1:-1] - np.maximum(ef[:-2], ef[2:]) > 0.05).sum())


def _holes(valid: np.ndarray) -> float:
    """Fraction of empty pixels with valid pixels within 3 rows above and below in their column."""
    h = valid.shape[0]
    rows = np.arange(h)[:, None]
    above = np.maximum.accumulate(np.where(valid, rows, -h), axis=0)
    below = np.minimum.accumulate(np.where(valid, rows, 2 * h)[::-1], axis=0)[::-1]
    return float((~valid & (rows - above <= 3) & (below - rows <= 3)).mean())


@pytest.mark.parametrize("name", ["kitti00_frames/000094.bin", "kitti_raw_hdl64_sequence/0000000010.pcd"])
def test_default_leaves_no_row_streaks_on_real_kitti(real_data, name):
    from placerec.io import read_scan

    scan = read_scan(real_data / name)
    default = make_image(scan)
    assert default.mode == "uniform" and _streak_rows(default.valid) == 0
    paper = make_image(scan, ImageParams(fill_holes_max_gap=0))  # whole-row filling alone keeps the streaks
    assert _streak_rows(paper.valid) >= 2
    assert _holes(default.valid) < 0.02 < 0.05 < _holes(paper.valid)


def test_default_hole_filling_is_only_for_uniform_images():
    xyz = np.zeros((3 * 4, 3), np.float32)
    xyz[:, 0] = 5
    xyz[5] = 0  # an invalid return between two valid ones in its column
    img = make_image(_scan(xyz, np.arange(12), shape=(3, 4)))
    assert img.mode == "organized" and not img.valid[1, 1]
    sensor = SensorInfo("x", beam_elevations_deg=(1.0, 0.0, -1.0), columns=8)
    pts = np.array([[10, 0, 0.17], [10, 0, -0.17]], np.float32)
    per_beam = make_image(_scan(pts, [1, 3], ring=[0, 2], sensor=sensor), ImageParams(fill_empty_rows=False))
    assert per_beam.mode == "per-beam" and per_beam.valid.sum() == 2
    uniform = make_image(
        _scan(pts, [1, 3], sensor=sensor), ImageParams(mode="uniform", height=3, fill_empty_rows=False)
    )
    assert uniform.valid.sum() == 3 and uniform.intensity[1, 4] == pytest.approx(2)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"clip": "saturation"}, "ImageParams: clip 'saturation' needs a 'saturation' value"),
        (
            {"fov_up_deg": 2.0, "fov_down_deg": -3.0},
            "fov_up_deg + fov_down_deg must be positive, got 2.0 + -3.0",
        ),
        (
            {"mode": "equirectangular"},
            "ImageParams: mode: Input should be 'auto', 'uniform', 'per-beam', 'organized' or 'spherical'",
        ),
    ],
)
def test_image_params_refuse_inconsistent_settings_when_built(values, message):
    """What `make_image` cannot use is refused by `ImageParams` itself, before any scan is projected."""
    with pytest.raises(ConfigError) as err:
        ImageParams(**values)
    assert message in str(err.value)


def test_clip_at_a_saturation_value():
    intensity = np.array([[0.0, 50.0, 200.0, 400.0]])
    img = to_uint8(intensity, np.ones_like(intensity, bool), ImageParams(clip="saturation", saturation=100.0))
    assert img.tolist() == [[0, 127, 255, 255]]


def test_each_pixel_keeps_its_nearest_point_and_the_first_of_equal_ranges():
    """The one-pass kernel of `_scatter_nearest` against the sort it replaced: per pixel the smallest range, the
    lowest point index among equal ranges (many ties: ranges rounded to metres, 40k points in 512 pixels)."""
    from placerec.image import projection as P
    from placerec.types import Scan

    rng = np.random.default_rng(4)
    n = 40_000
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    scan = Scan(xyz, rng.uniform(0, 1, n).astype(np.float32))
    rows, cols = rng.integers(0, 8, n), rng.integers(0, 64, n)
    ranges = np.round(rng.uniform(1, 9, n)).astype(np.float32)
    idx = np.arange(n)
    inten, rngs, pidx = P._scatter_nearest(rows, cols, ranges, scan, idx, (8, 64))
    pix = rows * 64 + cols
    order = np.lexsort((idx, ranges, pix))
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]]
    expect = np.full(8 * 64, -1)
    expect[pix[first]] = first
    np.testing.assert_array_equal(pidx.ravel(), expect)
    np.testing.assert_array_equal(rngs.ravel()[pix[first]], ranges[first])
    np.testing.assert_array_equal(inten.ravel()[pix[first]], scan.intensity[first])
