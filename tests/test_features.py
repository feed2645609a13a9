"""Feature registry: Table I defaults, shapes and kinds, the nfeatures cap, config errors, BRISK across OpenCV
versions, and the azimuth wrap-around at the panorama seam."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.errors import ConfigError, ScanDataError
from placerec.features import EXTRACTORS, Features, available_extractors, make_extractor
from placerec.features.compat import brisk_create
from placerec.features.synthetic import textured_image

NAMES = ["orb", "brisk", "fast-surf", "surf", "superpoint"]
PANORAMA = textured_image(64, 1024, seed=21)


def test_registry_names_and_table_one_defaults():
    assert available_extractors() == sorted(NAMES)
    orb = make_extractor("orb").params
    assert (
        orb.nfeatures,
        orb.scale_factor,
        orb.n_levels,
        orb.edge_threshold,
        orb.fast_threshold,
    ) == (
        300,
        1.2,
        8,
        15,
        40,
    )
    brisk = make_extractor("brisk").params
    assert (brisk.fast_threshold, brisk.threshold, brisk.octaves, brisk.pattern_scale) == (
        40,
        30,
        3,
        1.0,
    )
    surf = make_extractor("surf").params
    assert (surf.hessian_threshold, surf.n_octaves, surf.n_octave_layers) == (400.0, 4, 3)
    assert make_extractor("fast-surf").params.fast_threshold == 40
    sp = make_extractor("superpoint").params
    assert (sp.min_probability, sp.nfeatures) == (0.005, 300)  # not Table I's 0.05: see SuperPointParams
    assert all(make_extractor(n).params.wrap_pad for n in NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_each_extractor_returns_capped_features_of_its_kind(name):
    ex = make_extractor(name)
    f = ex.extract(PANORAMA)
    assert isinstance(f, Features)
    assert 100 <= len(f) <= 300
    kind, size = {
        "orb": ("binary", 32),
        "brisk": ("binary", 64),
        "fast-surf": ("float", 64),
        "surf": ("float", 64),
        "superpoint": ("float", 256),
    }[name]
    assert (ex.descriptor_kind, ex.descriptor_size) == (kind, size)
    assert f.descriptors.shape == (len(f), size)
    assert f.descriptors.dtype == (np.uint8 if kind == "binary" else np.float32)
    assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (len(f), 2)
    for arr in (f.size, f.angle, f.response, f.octave):
        assert arr.shape == (len(f),)
    u, v = f.keypoints.T
    assert u.min() >= -0.5 and u.max() < 1024 - 0.5 and v.min() >= -0.5 and v.max() <= 63.5
    assert np.all(np.diff(f.response) <= 0)  # strongest first
    if kind == "float":
        assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1, atol=1e-5)
    if name == "superpoint":  # no orientation (Features: angle -1)
        assert np.all(f.angle == -1)
    else:
        assert np.all((f.angle >= 0) & (f.angle < 360))
    # deterministic
    g = ex.extract(PANORAMA.copy())
    assert np.array_equal(f.keypoints, g.keypoints) and np.array_equal(f.descriptors, g.descriptors)


@pytest.mark.parametrize("name", NAMES)
def test_parameters_reach_the_backend(name):
    n50 = len(make_extractor(name, nfeatures=50).extract(PANORAMA))
    # cv2.ORB splits nfeatures over its pyramid levels; the small top levels of a 64-row image fill fewer
    assert 30 <= n50 <= 50 if name == "orb" else n50 == 50
    if name in ("fast-surf", "surf"):
        assert make_extractor(name, extended=True).extract(PANORAMA).descriptors.shape[1] == 128
        up = make_extractor(name, upright=True).extract(PANORAMA)
        assert np.all(up.angle == 0)
    if name == "superpoint":
        strict = make_extractor(name, min_probability=0.02, nfeatures=10_000).extract(PANORAMA)
        loose = make_extractor(name, nfeatures=10_000).extract(PANORAMA)
        assert 0 < len(strict) < len(loose) and strict.response.min() >= 0.02
        wide = make_extractor(name, nms_radius=8, nfeatures=10_000).extract(PANORAMA)
        assert len(wide) < len(loose)
    elif name == "surf":
        few = make_extractor(name, hessian_threshold=4000.0, nfeatures=10_000).extract(PANORAMA)
        many = make_extractor(name, nfeatures=10_000).extract(PANORAMA)
        assert 0 < len(few) < len(many) and few.response.min() > 4000
    else:
        strict = make_extractor(name, fast_threshold=80, nfeatures=10_000).extract(PANORAMA)
        loose = make_extractor(name, nfeatures=10_000).extract(PANORAMA)
        assert len(strict) < len(loose)


def test_mask_and_input_validation():
    mask = np.zeros_like(PANORAMA)
    mask[:, :512] = 1
    for name in NAMES:
        f = make_extractor(name).extract(PANORAMA, mask)
        assert len(f) > 0 and f.keypoints[:, 0].max() < 511.5
    ex = make_extractor("orb")
    with pytest.raises(ScanDataError):
        ex.extract(PANORAMA.astype(np.float32))
    with pytest.raises(ScanDataError):
        ex.extract(np.dstack([PANORAMA] * 3))
    with pytest.raises(ScanDataError):
        ex.extract(PANORAMA, mask[:, :100])
    empty = make_extractor("surf").extract(np.full((64, 256), 128, np.uint8))
    assert len(empty) == 0 and empty.descriptors.shape == (0, 64) and empty.descriptors.dtype == np.float32


def test_config_errors_name_the_allowed_values():
    with pytest.raises(ConfigError, match=r"unknown extractor 'sift'.*'brisk'.*'fast-surf'.*'orb'.*'surf'"):
        make_extractor("sift")
    with pytest.raises(
        ConfigError, match=r"features\.orb: nfeature: unknown key; allowed keys there:.* nfeatures"
    ):
        make_extractor("orb", nfeature=100)
    with pytest.raises(ConfigError, match=r"features\.surf: n_octaves: .*valid integer"):
        make_extractor("surf", n_octaves=2.5)
    with pytest.raises(ConfigError, match=r"wrap_pad: Input should be a valid boolean"):
        make_extractor("brisk", wrap_pad="yes")
    with pytest.raises(ConfigError, match=r"scale_factor: Input should be greater than 1"):
        make_extractor("orb", scale_factor=1.0)
    with pytest.raises(ConfigError, match=r"detector: Input should be 'fast' or 'brisk'"):
        make_extractor("brisk", detector="agast")
    with pytest.raises(ConfigError, match=r"nfeatures: Input should be greater than 0"):
        make_extractor("fast-surf", nfeatures=0)
    assert make_extractor("ORB").name == "orb"


def test_brisk_works_with_the_installed_opencv():
    brisk = brisk_create(30, 3, 1.0)
    assert brisk.descriptorSize() == 64
    f = make_extractor("brisk", detector="brisk").extract(PANORAMA)
    assert len(f) > 0 and f.descriptors.shape[1] == 64


def test_features_round_trip_through_npz(tmp_path):
    f = make_extractor("fast-surf").extract(PANORAMA)
    np.savez(tmp_path / "f.npz", **f.to_arrays("q."))
    with np.load(tmp_path / "f.npz") as data:
        g = Features.from_arrays(data, "q.")
    for field in ("keypoints", "size", "angle", "response", "octave", "descriptors"):
        assert np.array_equal(getattr(f, field), getattr(g, field))
    kps = g.to_cv_keypoints()
    assert len(kps) == len(g) and kps[0].pt == tuple(g.keypoints[0]) and np.array_equal(g.uv, g.keypoints)
    assert len(g.select(slice(0, 5))) == 5
    with pytest.raises(ScanDataError):
        Features(
            np.zeros((3, 2)), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(2), np.zeros((3, 32), np.uint8)
        )
    with pytest.raises(ScanDataError):
        Features.from_arrays({"keypoints": np.zeros((0, 2))})


# ------------------------------------------------------------------------------------------- azimuth wrap-around
def _seam_correspondences(name: str, seam: float = 24.0, **params):
    """Features near the seam of PANORAMA and of PANORAMA rolled by half its width (where they sit mid-image)."""
    w = PANORAMA.shape[1]
    ex = make_extractor(name, **params)
    f0 = ex.extract(PANORAMA)
    f1 = ex.extract(np.roll(PANORAMA, w // 2, axis=1))
    u0 = f0.keypoints[:, 0]
    near = np.flatnonzero((u0 < seam) | (u0 > w - 1 - seam))
    if name == "orb":  # upper pyramid levels resample a shifted image on another grid: compare level 0
        near = near[f0.octave[near] == 0]
    if name == "surf":  # descriptor windows (~13.4 s) that stay inside the 64-column wrap padding
        near = near[1.2 * f0.size[near] / 9 * 13.5 + 4 < 64]
    target = np.c_[np.mod(u0[near] + w // 2, w), f0.keypoints[near, 1]]
    d = np.linalg.norm(f1.keypoints[None, :, :] - target[:, None, :], axis=2)
    j = np.argmin(d, axis=1)
    found = d[np.arange(len(near)), j] < 1e-3
    return f0, f1, near, j, found


@pytest.mark.parametrize("name", NAMES)
def test_wrap_padding_matches_features_across_the_seam(name):
    f0, f1, near, j, found = _seam_correspondences(name)
    assert len(near) >= 5, "too few features near the seam to test"
    assert found.mean() >= 0.9
    a, b = f0.descriptors[near[found]], f1.descriptors[j[found]]
    if f0.descriptors.dtype == np.uint8:
        # BRISK samples with fixed-point offsets from float32 positions: a shift by 512 columns can flip a few
        # bits anywhere in the image, not only at the seam (ORB's level 0 is exact)
        same = np.unpackbits(a ^ b, axis=1).sum(axis=1) <= (16 if name == "brisk" else 0)
    else:
        same = np.abs(a - b).max(axis=1) < 1e-5
    assert same.mean() >= 0.9


def test_without_wrap_padding_the_seam_is_lost():
    w = PANORAMA.shape[1]
    for name, border in (("orb", 15), ("brisk", 8)):
        with_pad = make_extractor(name).extract(PANORAMA).keypoints[:, 0]
        without = make_extractor(name, wrap_pad=False).extract(PANORAMA).keypoints[:, 0]
        at_seam = (with_pad < border) | (with_pad > w - 1 - border)
        assert at_seam.sum() > 0
        assert np.sum((without < border - 3) | (without > w - 1 - border + 3)) < at_seam.sum()


def test_registry_classes_expose_their_names():
    for name, cls in EXTRACTORS.items():
        assert cls.name == name and {"nfeatures", "wrap_pad", "pad"} <= set(cls.Params.model_fields)
