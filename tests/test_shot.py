"""SHOT / ISHOT descriptors and SHOT LRFs: hand-checked histograms, a branch-by-branch reference of PCL's
interpolation, invariances (rigid motion, intensity offset), sensitivity, LRF sign disambiguation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.three_d import (
    DESCRIPTOR_DIMS,
    ISHOT_DIM,
    SHAPE_DIM,
    SHOTParams,
    compute_shot,
    describe,
    estimate_normals,
    shot_lrf,
)
from placerec.three_d.lrf import lrf_from_offsets

# ---------------------------------------------------------------------------------------------------------
# fixtures


def terrain(seed: int = 0, half: float = 9.0, step: float = 0.35) -> tuple[np.ndarray, np.ndarray]:
    """An irregular terrain patch with asymmetric bumps (no LRF ambiguity) and a smooth intensity pattern."""
    rng = np.random.default_rng(seed)
    g = np.arange(-half, half + 1e-9, step)
    x, y = np.meshgrid(g, g)
    x = x.ravel() + rng.uniform(-0.1, 0.1, x.size)
    y = y.ravel() + rng.uniform(-0.1, 0.1, y.size)
    z = (
        1.5 * np.exp(-((x - 2.0) ** 2 + (y - 1.0) ** 2) / 4.0)
        + 0.8 * np.exp(-((x + 3.0) ** 2 + (y - 2.5) ** 2) / 2.0)
        - 1.0 * np.exp(-((x - 0.5) ** 2 + (y + 3.0) ** 2) / 6.0)
        + 0.15 * x
        + 0.05 * y
    )
    pts = np.column_stack([x, y, z])
    inten = 0.5 + 0.3 * np.sin(0.7 * x) * np.cos(0.4 * y) + rng.uniform(-0.05, 0.05, x.size)
    return pts, np.clip(inten, 0.0, 1.0)


def random_rotation(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@pytest.fixture(scope="module")
def patch():
    pts, inten = terrain()
    normals = estimate_normals(pts, None).astype(np.float64)
    normals[normals[:, 2] < 0] *= -1  # viewpoint-independent orientation: up
    centre = np.linalg.norm(pts[:, :2], axis=1) < 2.0
    kp = np.flatnonzero(centre)[::7][:12]
    return pts, normals, inten, kp


# ---------------------------------------------------------------------------------------------------------
# reference: PCL's per-neighbour branches, written out literally for one keypoint (slow, test only)


def reference_histogram(
    delta_local: np.ndarray,
    cosines: np.ndarray,
    idiff: np.ndarray | None,
    R: float,
    wrap: bool = False,
) -> np.ndarray:
    sigs = [(0, 11, (1.0 + cosines) * 10 / 2)]
    if idiff is not None:
        sigs.append((SHAPE_DIM, 31, (1.0 + idiff) / 2 * 30))
    out = np.zeros(SHAPE_DIM if idiff is None else ISHOT_DIM)
    for m in range(delta_local.shape[0]):
        x, y, z = (float(v) for v in delta_local[m])
        dist = math.sqrt(x * x + y * y + z * z)
        if dist == 0.0:
            continue
        azim = math.atan2(y, x)
        sector = min(int(math.floor((azim + math.pi) / (math.pi / 4))), 7)
        if x == 0 and y == 0:
            sector = 0
        vol = sector * 4 + (2 if dist > R / 2 else 0) + (1 if z > 0 else 0)
        for offset, nb, values in sigs:
            value = float(values[m])
            step = int(math.floor(value + 0.5))
            frac = value - step
            own = 1.0 - abs(frac)
            if frac > 0:
                nb_step = (step + 1) % (nb - 1) if wrap else step + 1
                out[offset + vol * nb + nb_step] += frac
            else:
                nb_step = (step - 1 + nb - 1) % (nb - 1) if wrap else max(step - 1, 0)
                out[offset + vol * nb + nb_step] += -frac
            # radial
            if dist > R / 2:
                rd = (dist - 0.75 * R) / (R / 2)
                if dist > 0.75 * R:
                    own += 1 - rd
                else:
                    own += 1 + rd
                    out[offset + (vol - 2) * nb + step] += -rd
            else:
                rd = (dist - 0.25 * R) / (R / 2)
                if dist < 0.25 * R:
                    own += 1 + rd
                else:
                    own += 1 - rd
                    out[offset + (vol + 2) * nb + step] += rd
            # elevation
            incl = math.acos(max(-1.0, min(1.0, z / dist)))
            if z <= 0:
                ed = (incl - 3 * math.pi / 4) / (math.pi / 2)
                if incl > 3 * math.pi / 4:
                    own += 1 - ed
                else:
                    own += 1 + ed
                    out[offset + (vol + 1) * nb + step] += -ed
            else:
                ed = (incl - math.pi / 4) / (math.pi / 2)
                if incl < math.pi / 4:
                    own += 1 + ed
                else:
                    own += 1 - ed
                    out[offset + (vol - 1) * nb + step] += ed
            # azimuth
            if x != 0 or y != 0:
                ad = (azim - (-7 * math.pi / 8 + sector * math.pi / 4)) / (math.pi / 4)
                ad = max(-0.5, min(0.5, ad))
                if ad > 0:
                    own += 1 - ad
                    out[offset + ((vol + 4) % 32) * nb + step] += ad
                else:
                    own += 1 + ad
                    out[offset + ((vol - 4) % 32) * nb + step] += -ad
            out[offset + vol * nb + step] += own
    return out / np.linalg.norm(out)


def one_keypoint_cloud(local: np.ndarray, normals: np.ndarray):
    """Keypoint at the origin (index 0) followed by neighbours; identity LRF."""
    pts = np.vstack([[0.0, 0.0, 0.0], local])
    nrm = np.vstack([[0.0, 0.0, 1.0], normals])
    frames = np.eye(3)[None]
    return pts, nrm, frames


# ---------------------------------------------------------------------------------------------------------
# hand-checked histograms


def nonzero(v: np.ndarray) -> list[int]:
    """Indices of entries above float32 round-off (a neighbour on a bin centre leaks ~1e-8 to its neighbour)."""
    return np.flatnonzero(v > 1e-5).tolist()


def _sph(r: float, incl_deg: float, az: float) -> np.ndarray:
    inc = math.radians(incl_deg)
    return np.array([r * math.sin(inc) * math.cos(az), r * math.sin(inc) * math.sin(az), r * math.cos(inc)])


def _normal_with_cos(c: float) -> np.ndarray:
    return np.array([math.sqrt(1 - c * c), 0.0, c])


R8 = 8.0  # R/4 = 2, R/2 = 4, 3R/4 = 6
SECTOR_CENTRE = [-7 * math.pi / 8 + s * math.pi / 4 for s in range(8)]


def test_neighbour_at_a_volume_centre_fills_one_bin():
    # sector 5, inner shell centre (r = R/4), upper elevation centre (45 deg), cos = 0 -> bin 5
    p = _sph(2.0, 45.0, SECTOR_CENTRE[5])
    pts, nrm, frames = one_keypoint_cloud(p[None], _normal_with_cos(0.0)[None])
    d, valid = compute_shot(pts, nrm, [0], SHOTParams(support_radius=R8), frames=frames)
    assert valid[0]
    nz = nonzero(d[0])
    vol = 5 * 4 + 0 * 2 + 1
    assert nz == [vol * 11 + 5]
    assert d[0, vol * 11 + 5] == pytest.approx(1.0)


def test_interpolation_weights_split_to_adjacent_bins():
    # r = 3 (inner, 1/4 of the way to the outer centre), elevation 45 deg (no split),
    # azimuth a quarter sector past sector 2's centre, cos value 5.3 -> bins 5 (0.7) and 6 (0.3)
    p = _sph(3.0, 45.0, SECTOR_CENTRE[2] + 0.25 * math.pi / 4)
    cos = 2 * 5.3 / 10 - 1
    pts, nrm, frames = one_keypoint_cloud(p[None], _normal_with_cos(cos)[None])
    d, _ = compute_shot(pts, nrm, [0], SHOTParams(support_radius=R8), frames=frames)
    vol = 2 * 4 + 0 + 1
    raw = {
        vol * 11 + 5: 0.75 + 1.0 + 0.75 + 0.7,  # own: radial + elevation + azimuth + cosine
        vol * 11 + 6: 0.3,  # cosine neighbour
        (vol + 2) * 11 + 5: 0.25,  # outer shell
        (vol + 4) * 11 + 5: 0.25,  # next sector
    }
    norm = math.sqrt(sum(v * v for v in raw.values()))
    assert sorted(nonzero(d[0])) == sorted(raw)
    for k, v in raw.items():
        assert d[0, k] == pytest.approx(v / norm, abs=1e-5)


def test_weights_beyond_outer_centres_are_dropped_not_moved():
    # A: volume centre (own weight 4); B: r = 7.5 (> 3R/4), inclination 10 deg (< 45): own weight
    # (1 - 0.375) + (1 - 35/90) + 1 + 1, nothing to the neighbours
    a = _sph(2.0, 45.0, SECTOR_CENTRE[0])
    b = _sph(7.5, 10.0, SECTOR_CENTRE[3])
    pts, nrm, frames = one_keypoint_cloud(np.stack([a, b]), np.stack([_normal_with_cos(0.0)] * 2))
    d, _ = compute_shot(pts, nrm, [0], SHOTParams(support_radius=R8), frames=frames)
    va, vb = 0 * 4 + 0 + 1, 3 * 4 + 2 + 1
    assert sorted(nonzero(d[0])) == [va * 11 + 5, vb * 11 + 5]
    wb = (1 - 0.375) + (1 - 35 / 90) + 2.0
    assert d[0, va * 11 + 5] / d[0, vb * 11 + 5] == pytest.approx(4.0 / wb, rel=1e-5)


def test_intensity_bins_and_pcl_wrap_option():
    # keypoint intensity 0.5; neighbour A: 0.3 (f = +0.2 -> value 18, one bin); B: 0.75 (f = -0.25 -> 11.25)
    a = _sph(2.0, 45.0, SECTOR_CENTRE[1])
    b = _sph(2.0, 135.0, SECTOR_CENTRE[6])
    cos_a = 2 * 9.3 / 10 - 1  # shape value 9.3: upper neighbour bin 10 (ours) or 0 (PCL's modulo)
    pts, nrm, frames = one_keypoint_cloud(
        np.stack([a, b]), np.stack([_normal_with_cos(cos_a), _normal_with_cos(0)])
    )
    inten = np.array([0.5, 0.3, 0.75])
    d, _ = compute_shot(pts, nrm, [0], SHOTParams(support_radius=R8), intensity=inten, frames=frames)
    va, vb = 1 * 4 + 1, 6 * 4 + 0
    col = d[0, SHAPE_DIM:].reshape(32, 31)
    assert nonzero(col[va]) == [18]
    assert nonzero(col[vb]) == [11, 12]
    assert col[vb, 12] / col[vb, 11] == pytest.approx(0.25 / 3.75, rel=1e-5)
    shape = d[0, :SHAPE_DIM].reshape(32, 11)
    assert nonzero(shape[va]) == [9, 10]
    dw, _ = compute_shot(
        pts, nrm, [0], SHOTParams(support_radius=R8, pcl_bin_wrap=True), intensity=inten, frames=frames
    )
    assert nonzero(dw[0, :SHAPE_DIM].reshape(32, 11)[va]) == [0, 9]


@pytest.mark.parametrize("wrap", [False, True])
@pytest.mark.parametrize("with_intensity", [False, True])
def test_matches_branchwise_reference_on_random_neighbours(wrap, with_intensity):
    rng = np.random.default_rng(7)
    n = 60
    local = rng.normal(size=(n, 3))
    local *= (rng.uniform(0.2, 6.9, n) / np.linalg.norm(local, axis=1))[:, None]
    local[0] = [0.0, 0.0, 3.0]  # on the z axis: no azimuth vote
    local[1] = [3.5, 0.0, 0.0]  # on a sector border
    local[2] = [0.0, 0.0, 0.0]  # duplicate of the keypoint: skipped
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    inten = rng.uniform(0, 1, n + 1)
    pts, nrm_all, frames = one_keypoint_cloud(local, nrm)
    params = SHOTParams(support_radius=7.0, pcl_bin_wrap=wrap)
    d, valid = compute_shot(
        pts, nrm_all, [0], params, intensity=inten if with_intensity else None, frames=frames
    )
    ref = reference_histogram(
        local, nrm[:, 2], (inten[0] - inten[1:]) if with_intensity else None, 7.0, wrap=wrap
    )
    assert valid[0]
    np.testing.assert_allclose(d[0], ref, atol=2e-6)


# ---------------------------------------------------------------------------------------------------------
# invariances and sensitivity


def test_rigid_motion_invariance(patch):
    pts, normals, inten, kp = patch
    Rm = random_rotation(3)
    t = np.array([120.0, -45.0, 7.5])
    pts2 = pts @ Rm.T + t
    n2 = normals @ Rm.T
    for name, dim in (("shot", SHAPE_DIM), ("ishot", ISHOT_DIM)):
        d1, v1 = describe(name, pts, normals, inten, kp, 7.0)
        d2, v2 = describe(name, pts2, n2, inten, kp, 7.0)
        assert d1.shape == (kp.size, dim) and v1.all() and v2.all()
        assert np.abs(d1 - d2).max() < 2e-4, name
    f1, _ = shot_lrf(pts, kp, 7.0)
    f2, _ = shot_lrf(pts2, kp, 7.0)
    np.testing.assert_allclose(f2, f1 @ Rm.T, atol=1e-6)


def test_descriptors_are_unit_length_and_distinct(patch):
    pts, normals, inten, kp = patch
    d, valid = describe("ishot", pts, normals, inten, kp, 7.0)
    assert valid.all()
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert (d >= 0).all()
    # different keypoints -> different descriptors
    assert np.linalg.norm(d[0] - d[-1]) > 0.05


def test_ishot_invariant_to_intensity_offset(patch):
    pts, normals, inten, kp = patch
    d1, _ = describe("ishot", pts, normals, inten, kp, 7.0)
    d2, _ = describe("ishot", pts, normals, inten + 0.2, kp, 7.0)
    np.testing.assert_allclose(d1, d2, atol=1e-5)


def test_ishot_sensitive_to_intensity_pattern(patch):
    pts, normals, inten, kp = patch
    k = kp[0]
    near = np.linalg.norm(pts - (pts[k] + [2.5, 1.0, 0.0]), axis=1) < 2.0
    changed = inten.copy()
    changed[near] = 0.95  # a bright painted patch next to the keypoint
    d1, _ = describe("ishot", pts, normals, inten, [k], 7.0)
    d2, _ = describe("ishot", pts, normals, changed, [k], 7.0)
    texture_change = np.linalg.norm(d1[0, SHAPE_DIM:] - d2[0, SHAPE_DIM:])
    assert texture_change > 0.05
    # the shape part only rescales (joint normalisation): its direction is unchanged
    s1, s2 = d1[0, :SHAPE_DIM], d2[0, :SHAPE_DIM]
    np.testing.assert_allclose(s1 / np.linalg.norm(s1), s2 / np.linalg.norm(s2), atol=1e-6)
    # and plain SHOT does not see the paint at all
    e1, _ = describe("shot", pts, normals, inten, [k], 7.0)
    e2, _ = describe("shot", pts, normals, changed, [k], 7.0)
    np.testing.assert_array_equal(e1, e2)


def test_per_part_normalisation(patch):
    pts, normals, inten, kp = patch
    d, valid = compute_shot(pts, normals, kp, SHOTParams(normalization="per_part"), intensity=inten)
    assert valid.all()
    np.testing.assert_allclose(np.linalg.norm(d[:, :SHAPE_DIM], axis=1), 1 / math.sqrt(2), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d[:, SHAPE_DIM:], axis=1), 1 / math.sqrt(2), atol=1e-5)


# ---------------------------------------------------------------------------------------------------------
# LRF


def _elongated_bowl(x_range: tuple[float, float], bowl: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.uniform(*x_range, 400)
    y = rng.uniform(-1.0, 1.0, 400)
    z = bowl * (x**2 + y**2) + rng.normal(0, 0.01, 400)
    return np.vstack([[0.0, 0.0, 0.0], np.column_stack([x, y, z])])


@pytest.mark.parametrize("x_range,x_sign", [((-2.0, 6.0), 1.0), ((-6.0, 2.0), -1.0)])
@pytest.mark.parametrize("bowl,z_sign", [(0.04, 1.0), (-0.04, -1.0)])
def test_lrf_sign_disambiguation(x_range, x_sign, bowl, z_sign):
    pts = _elongated_bowl(x_range, bowl)
    frames, valid = shot_lrf(pts, [0], 7.0)
    assert valid[0]
    F = frames[0]
    assert F[0] @ [x_sign, 0, 0] > 0.95  # x: towards the side holding most points
    assert F[2] @ [0, 0, z_sign] > 0.9  # z: towards the side most points lie on in height
    np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(F) == pytest.approx(1.0)  # y = z x x


@pytest.mark.parametrize("mirror", [1.0, -1.0])
def test_lrf_tie_uses_points_around_the_median_distance(mirror):
    # 3 near points on one side, 3 far points on the other: an exact tie in the sign count. PCL looks at the
    # 5 points around the median distance (4 of them: the far side) -> x points to the far side.
    xs = mirror * np.array([-1.0, -2.0, -3.0, 4.0, 5.0, 6.0])
    d = np.column_stack([xs, [0.5, -0.5, 0.4, -0.4, 0.3, -0.3], [0.05, 0.1, -0.12, 0.15, -0.2, 0.25]])
    dist = np.linalg.norm(d, axis=1)
    frames, valid = lrf_from_offsets(np.zeros(6, dtype=np.int64), np.array([0, 6]), d.T, dist, 7.0)
    assert valid[0]
    assert frames[0, 0, 0] * mirror > 0.9


def test_too_few_neighbours_is_invalid():
    rng = np.random.default_rng(1)
    pts = np.vstack([rng.uniform(-1, 1, (50, 3)), [[100.0, 0, 0], [100.5, 0, 0], [100, 0.5, 0]]])
    normals = np.tile([0.0, 0.0, 1.0], (pts.shape[0], 1))
    d, valid = compute_shot(pts, normals, [0, 50], intensity=np.zeros(pts.shape[0]))
    assert valid.tolist() == [True, False]
    assert not d[1].any()
    frames, fvalid = shot_lrf(pts, [50], 7.0)
    assert not fvalid[0] and np.isnan(frames[0]).all()


# ---------------------------------------------------------------------------------------------------------
# registry and input errors


def test_registry_dimensions_and_fpfh(patch):
    pts, normals, inten, kp = patch
    for name, dim in DESCRIPTOR_DIMS.items():
        d, valid = describe(name, pts, normals, inten, kp[:3], 7.0)
        assert d.shape == (3, dim) and d.dtype == np.float32 and valid.all(), name
    d, _ = describe("fpfh", pts, normals, None, [], 7.0)
    assert d.shape == (0, 33)


def test_errors(patch):
    pts, normals, inten, kp = patch
    with pytest.raises(ConfigError, match="allowed"):
        describe("sift3d", pts, normals, inten, kp, 7.0)
    with pytest.raises(ScanDataError, match="intensity"):
        describe("ishot", pts, normals, None, kp, 7.0)
    with pytest.raises(ScanDataError, match="out of range"):
        compute_shot(pts, normals, [pts.shape[0]])
    with pytest.raises(ScanDataError, match="normals"):
        compute_shot(pts, normals[:-1], kp)
    with pytest.raises(ScanDataError, match=r"\(N, 3\)"):
        compute_shot(pts[:, :2], normals, kp)
    with pytest.raises(ConfigError, match="normalization"):
        compute_shot(pts, normals, kp, SHOTParams(normalization="l1"))
    d, valid = compute_shot(pts, normals, [], intensity=inten)
    assert d.shape == (0, ISHOT_DIM) and valid.shape == (0,)
