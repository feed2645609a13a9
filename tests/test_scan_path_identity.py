"""The cheaper per-scan paths (issue #30) give exactly what the straightforward code they replace gives: each
reference below is that code, kept here, compared bit for bit on simulated scans (always; with non-finite, zero
and far points added) and on the real KITTI HDL-64 frames (when ``../shared`` is there)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from placerec.image.projection import ImageParams, _valid_points, fill_vertical_holes, make_image
from placerec.preprocess import PreprocessParams, crop, preprocess_scan, remove_invalid
from placerec.types import Scan, valid_points
from placerec.verify.candidates import scan_cloud
from placerec.verify.icp import as_points
from placerec.verify.params import VerifyParams

# ---- the references ----


def ref_as_points(points):
    p = np.asarray(getattr(points, "xyz", points), dtype=np.float64)[:, :3]
    keep = np.isfinite(p).all(axis=1) & (np.abs(p).sum(axis=1) > 0)
    return np.ascontiguousarray(p[keep])


def ref_scan_cloud(scan, params):
    import small_gicp

    p = ref_as_points(scan)
    if params.icp.max_range is not None:
        p = p[np.einsum("ni,ni->n", p, p) <= params.icp.max_range**2]
    if p.shape[0] == 0:
        return np.zeros((0, 3), np.float32)
    vox = small_gicp.voxelgrid_sampling(p, params.icp.voxel_size)
    return np.asarray(vox.points(), dtype=np.float32)[:, :3]


def ref_keep(scan, keep, keep_organized):
    if keep_organized and scan.shape is not None:
        if keep.all():
            return scan
        xyz = np.where(keep[:, None], scan.xyz, np.float32(0.0))
        return replace(scan, xyz=xyz, intensity=np.where(keep, scan.intensity, np.float32(0.0)))
    if keep.all() and scan.shape is None:
        return scan
    return scan.select(keep)


def ref_remove_invalid(scan, keep_organized):
    finite = np.isfinite(scan.xyz).all(axis=1) & np.isfinite(scan.intensity)
    keep = valid_points(scan, intensity=True)
    counts = {"nonfinite": int((~finite).sum()), "no_return": int((finite & ~keep).sum())}
    return ref_keep(scan, keep, keep_organized), counts


def ref_crop(scan, min_range, max_range, min_z, max_z, keep_organized):
    keep = np.ones(len(scan), dtype=bool)
    if min_range is not None or max_range is not None:
        r = scan.ranges
        if min_range is not None:
            keep &= r >= min_range
        if max_range is not None:
            keep &= r <= max_range
    z = scan.xyz[:, 2]
    if min_z is not None:
        keep &= z >= min_z
    if max_z is not None:
        keep &= z <= max_z
    return ref_keep(scan, keep, keep_organized)


def ref_preprocess(scan, p, keep_organized):
    from placerec.intensity import normalize_intensity

    scan, _ = ref_remove_invalid(scan, keep_organized)
    scan = ref_crop(scan, p.min_range, p.max_range, p.min_z, p.max_z, keep_organized)
    return normalize_intensity(scan, p.intensity.spec())


def ref_fill_vertical_holes(image, valid, max_gap):
    h = image.shape[0]
    rows = np.arange(h)[:, None]
    above = np.maximum.accumulate(np.where(valid, rows, -1), axis=0)
    below = np.minimum.accumulate(np.where(valid, rows, h)[::-1], axis=0)[::-1]
    hole = ~valid & (above >= 0) & (below < h) & (rows - above <= max_gap) & (below - rows <= max_gap)
    if not hole.any():
        return image, valid
    cols = np.broadcast_to(np.arange(image.shape[1]), image.shape)
    a, b, c = above[hole], below[hole], cols[hole]
    t = (rows.repeat(image.shape[1], axis=1)[hole] - a) / (b - a)
    out = image.astype(np.float32, copy=True)
    out[hole] = (1 - t) * image[a, c] + t * image[b, c]
    return out, valid | hole


def ref_project_uniform(scan, params):
    """Eq. 2 step by step in numpy (what `project_uniform` compiles)."""
    from placerec.image.projection import _fov, _scatter_nearest

    h = params.height or scan.sensor.n_beams or 64
    w = params.width or scan.sensor.columns or 1024
    r = scan.ranges
    idx = np.flatnonzero(valid_points(scan, intensity=True, ranges=r))
    r = r[idx]
    xyz = scan.xyz[idx]
    if idx.size == 0:
        return _scatter_nearest(idx, idx, r, scan, idx, (h, w))
    phi = np.degrees(np.arcsin(np.clip(xyz[:, 2] / r, -1.0, 1.0)))
    up, down = _fov(scan, params, xyz, r, phi)
    v = np.floor((1.0 - (phi + down) / (up + down)) * h).astype(np.int64)
    inside = (v >= 0) & (v < h)
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    cols = np.mod(np.floor(0.5 * (1.0 - theta / np.pi) * w).astype(np.int64), w)
    return _scatter_nearest(v[inside], cols[inside], r[inside], scan, idx[inside], (h, w))


def _numpy_svml() -> bool:
    """numpy's float32 arcsin / arctan2 come from Intel's SVML on AVX512-SKX CPUs (last-bit differences from the
    C library the compiled projection calls, as from numpy on other CPUs)."""
    from numpy._core._multiarray_umath import __cpu_features__

    return bool(__cpu_features__.get("AVX512_SKX"))


def check_projection(scan: Scan) -> None:
    from placerec.image.projection import project_uniform

    for params in (
        ImageParams(mode="uniform"),
        ImageParams(mode="uniform", height=48, width=900),
        ImageParams(mode="uniform", fov_up_deg=5.0, fov_down_deg=12.5),
    ):
        got, want = project_uniform(scan, params), ref_project_uniform(scan, params)
        if _numpy_svml():  # a point whose angle is within an ulp of a pixel edge may land one pixel over
            assert np.mean(got[2] != want[2]) < 1e-3
            continue
        for a, b in zip(got, want, strict=True):
            same(a, b)


# ---- comparisons ----


def same(a, b) -> None:
    """Bit-identical arrays (dtype, shape and bytes), or the same scan."""
    if isinstance(a, Scan):
        for f in ("xyz", "intensity", "ring", "time"):
            same(getattr(a, f), getattr(b, f))
        assert (a.shape, a.sensor, a.timestamp, a.source) == (b.shape, b.sensor, b.timestamp, b.source)
        return
    if a is None or b is None:
        assert a is None and b is None
        return
    assert a.dtype == b.dtype and a.shape == b.shape
    assert np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes()


PREPROCESS = [
    PreprocessParams(),
    PreprocessParams(min_range=3.0),
    PreprocessParams(min_range=2.0, max_range=40.0, min_z=-1.5, max_z=3.0),
    PreprocessParams(max_z=0.5, intensity={"mode": "raw"}),
]
VERIFY = [VerifyParams(), VerifyParams(icp={"max_range": None}), VerifyParams(icp={"max_range": 25.0})]


def check_scan(scan: Scan) -> None:
    for keep_organized in (False, True):
        got, counts = remove_invalid(scan, keep_organized)
        want, want_counts = ref_remove_invalid(scan, keep_organized)
        same(got, want)
        assert counts == want_counts
        same(
            crop(scan, 3.0, 50.0, -1.0, 2.0, keep_organized),
            ref_crop(scan, 3.0, 50.0, -1.0, 2.0, keep_organized),
        )
        for p in PREPROCESS:
            same(preprocess_scan(scan, p, keep_organized), ref_preprocess(scan, p, keep_organized))
    same(as_points(scan), ref_as_points(scan))
    for v in VERIFY:
        same(scan_cloud(scan, v), ref_scan_cloud(scan, v))
    check_projection(scan)
    idx, r = _valid_points(scan)
    want_idx = np.flatnonzero(valid_points(scan, intensity=True))
    same(idx, want_idx)
    same(r, scan.ranges[want_idx])


def check_image(scan: Scan, params: ImageParams) -> None:
    """`make_image` fills the holes of its range and intensity images as two `fill_vertical_holes` calls would."""
    img = make_image(scan, params)
    no_holes = make_image(scan, params.model_copy(update={"fill_holes_max_gap": 0}))
    gap = params.fill_holes_max_gap
    rng, _ = ref_fill_vertical_holes(no_holes.range, no_holes.valid, gap)
    inten, valid = ref_fill_vertical_holes(no_holes.intensity, no_holes.valid, gap)
    same(img.range, rng)
    same(img.intensity, inten)
    same(img.valid, valid)
    got, got_valid = fill_vertical_holes(no_holes.intensity, no_holes.valid, gap)
    same(got, inten)
    same(got_valid, valid)


def with_bad_points(scan: Scan, seed: int = 0) -> Scan:
    """``scan`` with NaN / inf coordinates and intensities, points at the origin, beyond MAX_RANGE_M and -0.0."""
    rng = np.random.default_rng(seed)
    xyz, inten = scan.xyz.copy(), scan.intensity.copy()
    n = len(scan)
    pick = rng.choice(n, size=min(n, 70), replace=False).reshape(7, -1)
    xyz[pick[0], rng.integers(0, 3, pick.shape[1])] = np.nan
    xyz[pick[1], rng.integers(0, 3, pick.shape[1])] = np.inf
    xyz[pick[2]] = 0.0
    xyz[pick[3]] = -0.0
    xyz[pick[4]] = 2e4
    inten[pick[5]] = np.nan
    xyz[pick[6], 0] = -np.inf
    return replace(scan, xyz=xyz, intensity=inten)


@pytest.fixture(scope="module")
def simulated() -> list[Scan]:
    from placerec.sim import SimulatedSequence

    scans = []
    for sensor in ("vlp16", "hdl64", "os1-64"):
        scan = SimulatedSequence("town", sensor, seed=0, n_scans=2)[1]
        scans += [scan, with_bad_points(scan)]
    return scans


def test_simulated_scans_identical(simulated):
    assert any(s.is_organized for s in simulated)
    for scan in simulated:
        check_scan(scan)


def test_simulated_images_identical(simulated):
    for scan in simulated:
        check_image(scan, ImageParams(mode="uniform", fill_holes_max_gap=2))
        check_image(scan, ImageParams(mode="uniform", fill_holes_max_gap=4, fill_empty_rows=False))


def test_as_points_of_other_arrays_identical():
    rng = np.random.default_rng(1)
    p = rng.normal(0, 30, (500, 4))
    p[::17, 1] = np.nan
    p[::23] = 0.0
    p[::31, 2] = -np.inf
    for arr in (
        p,
        p.astype(np.float32),
        p[:, :3].copy(),
        np.asfortranarray(p),
        np.round(np.nan_to_num(p, posinf=1e6, neginf=-1e6)).astype(np.int32),
    ):
        same(as_points(arr), ref_as_points(arr))
    same(as_points(np.zeros((0, 3), np.float32)), ref_as_points(np.zeros((0, 3), np.float32)))


def test_real_kitti_frames_identical(real_data):
    from placerec.io import read_scan

    frames = sorted((real_data / "kitti_raw_hdl64_sequence").glob("*.pcd"))[::4]
    frames += sorted((real_data / "kitti00_frames").glob("*.bin"))[:2]
    if not frames:
        pytest.skip("no KITTI frames in the real sample data")
    for path in frames:
        scan = read_scan(path)
        check_scan(scan)
        check_scan(with_bad_points(scan))
        check_image(
            preprocess_scan(scan, PreprocessParams(min_range=3.0)),
            ImageParams(mode="uniform", fill_holes_max_gap=2),
        )


def test_take_rows_is_row_indexing():
    from placerec.types import take_rows

    rng = np.random.default_rng(2)
    arrays = [
        rng.normal(size=(1000, 3)).astype(np.float32),
        rng.normal(size=(1000, 3)),
        rng.normal(size=(1000, 4))[:, :3],  # not contiguous
        np.asfortranarray(rng.normal(size=(1000, 3))),
        rng.integers(-5, 5, (1000, 1)).astype(np.int16),
        np.zeros((0, 3), np.float32),
    ]
    for a in arrays:
        mask = rng.random(len(a)) > 0.3
        for index in (mask, np.flatnonzero(mask), np.flatnonzero(mask)[::-1], np.zeros(len(a), bool)):
            got = take_rows(a, index)
            same(got, a[index])
            assert got.flags.c_contiguous


@pytest.mark.parametrize("shape", [(1, 7), (5, 1), (16, 64), (64, 300)])
def test_fill_vertical_holes_of_random_masks(shape):
    rng = np.random.default_rng(3)
    image = rng.random(shape).astype(np.float32)
    for density in (0.0, 0.3, 0.8, 1.0):
        valid = rng.random(shape) < density
        for gap in (1, 2, 5):
            for v in (valid, np.asfortranarray(valid), valid[:, ::-1]):
                got, got_valid = fill_vertical_holes(image, v, gap)
                want, want_valid = ref_fill_vertical_holes(image, v, gap)
                same(got, want)
                same(got_valid, want_valid)


def test_as_points_of_any_numeric_dtype():
    """The float32 / float64 inputs are filtered as they are; any other type (half, extended precision, integers,
    extra columns) is converted first, as the reference does."""
    rng = np.random.default_rng(5)
    base = rng.normal(size=(200, 4)) * 50
    base[::7] = 0.0
    base[3::11, 1] = np.nan
    for dt in (np.float16, np.float32, np.float64, np.longdouble, np.int32):
        a = (np.nan_to_num(base) if dt is np.int32 else base).astype(dt)
        same(as_points(a), ref_as_points(a))
        same(as_points(a[:, :3]), ref_as_points(a[:, :3]))


def ref_prepare(points, voxel, neighbors):
    """small_gicp's own one-call preparation (voxel grid, tree, normals and covariances on one thread)."""
    import small_gicp

    cloud, _ = small_gicp.preprocess_points(
        np.asarray(points, np.float64), downsampling_resolution=voxel, num_neighbors=neighbors, num_threads=1
    )
    return cloud


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_prepared_clouds_identical_on_any_threads(simulated, real_data, threads):
    """`prepare_target` / `prepare_source` give small_gicp's one-thread preparation bit for bit on any number of
    threads (the search tree and normals run on ``prepare_threads``)."""
    from placerec.verify.icp import prepare_source, prepare_target
    from placerec.verify.params import IcpParams

    scans = list(simulated)
    frames = sorted((real_data / "kitti_raw_hdl64_sequence").glob("*.pcd"))[:2]
    if frames:
        from placerec.io import read_scan

        scans += [read_scan(f) for f in frames]
    params = IcpParams(prepare_threads=threads)
    for scan in scans:
        # a stored cloud and the raw points
        for cloud in (scan_cloud(scan, VerifyParams()), as_points(scan)):
            for prep, voxel in (
                (prepare_target, params.voxel_size),
                (prepare_source, params.source_voxel_size),
            ):
                got = prep(cloud, params).native
                want = ref_prepare(cloud, voxel, params.normal_neighbors)
                for field in ("points", "normals", "covs"):
                    same(np.asarray(getattr(got, field)()), np.asarray(getattr(want, field)()))


def test_prepare_threads(monkeypatch):
    from placerec.threads import available_threads
    from placerec.verify.icp import prepare_threads
    from placerec.verify.params import IcpParams

    assert prepare_threads(IcpParams(prepare_threads=3)) == 3
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert prepare_threads(IcpParams()) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert prepare_threads(IcpParams()) == available_threads()


def test_prepare_threads_is_not_recorded_by_saved_databases():
    """A database saved before `prepare_threads` existed (or with another value) loads: the count is run-time."""
    from placerec.verify.candidates import VerifiedParams

    saved = VerifiedParams().saved_dump()
    assert "prepare_threads" not in saved["icp"]
    assert VerifiedParams(icp={"prepare_threads": 3}).saved_dump() == saved
