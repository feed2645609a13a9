"""16-row (VLP-16) intensity images: rows upsampled before extraction, keypoints in the original rows, a warning
once when an image gives too few features (placerec.features.low_rows)."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from placerec.features import available_extractors, make_extractor
from placerec.features.low_rows import FEW_FEATURES, row_factor, rows_back, upsample_rows
from placerec.features.synthetic import textured_image
from placerec.recognizer import make_pipeline
from placerec.types import Scan, SensorInfo


def _low(seed: int) -> np.ndarray:
    """A VLP-16-like image (16 beams, 1800 columns): a texture averaged down to 16 rows, as a beam samples it."""
    return cv2.resize(textured_image(128, 1800, seed=seed), (1800, 16), interpolation=cv2.INTER_AREA)


LOW = _low(3)


def test_row_factor_and_the_row_mapping():
    assert [row_factor(h, None) for h in (16, 32, 40, 63, 64, 128)] == [8, 4, 4, 3, 1, 1]
    assert row_factor(16, 1) == 1 and row_factor(64, 2) == 2
    img = np.zeros((16, 4), np.uint8)
    img[5] = 200
    up, mask = upsample_rows(img, np.full((16, 4), 255, np.uint8), 8)
    assert up.shape == mask.shape == (128, 4)
    peak = np.flatnonzero(up[:, 0] == up[:, 0].max()).mean()  # the bright row's centre, upsampled ...
    assert peak == 43.5 and rows_back(np.array([peak]), 8).tolist() == [5.0]  # ... maps back to row 5


@pytest.mark.parametrize("name", available_extractors())
def test_low_images_give_features_in_their_own_rows(name):
    ext = make_extractor(name)
    feats = ext.extract(LOW)
    assert len(feats) >= 50
    # FAST keypoints need only a 7 px patch and SuperPoint's network runs on any height that is a multiple of 8;
    # the others find nothing in 16 rows
    if name not in ("fast-surf", "superpoint"):
        assert len(make_extractor(name, row_upsample=1).extract(LOW)) == 0
    v = feats.keypoints[:, 1]
    assert v.min() >= -0.5 and v.max() <= 15.5  # mapped back to the 16 rows
    assert feats.keypoints[:, 0].max() < 1800


def test_table_one_orb_on_16_rows_finds_nothing_and_says_so(caplog):
    ext = make_extractor("orb", row_upsample=1)
    with caplog.at_level(logging.WARNING, logger="placerec.features"):
        assert len(ext.extract(LOW)) == 0
        assert len(ext.extract(LOW)) == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "only 0 features in a 16 x 1800 intensity image" in warnings[0]


def test_few_features_warn_once_per_extractor(caplog):
    blank = np.zeros((64, 1024), np.uint8)
    a, b = make_extractor("orb"), make_extractor("orb")
    with caplog.at_level(logging.WARNING, logger="placerec.features"):
        for _ in range(3):
            a.extract(blank)
        b.extract(blank)
        assert len(a.extract(textured_image(64, 1024, seed=1))) > FEW_FEATURES
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 2


def test_upsampled_keypoints_agree_with_the_image_content():
    # a keypoint found in the upsampled image lies where the low image has the same structure: extracting from
    # the image repeated 8 times by hand gives the same columns and, divided back, the same rows
    by_hand = make_extractor("orb", row_upsample=1).extract(np.repeat(LOW, 8, axis=0))
    auto = make_extractor("orb").extract(LOW)
    assert len(by_hand) > 100 and len(auto) > 100
    common = np.intersect1d(np.round(by_hand.keypoints[:, 0]), np.round(auto.keypoints[:, 0]))
    assert common.size > 0.3 * len(auto)


def _vlp16_scan(image: np.ndarray) -> Scan:
    """A per-beam scan whose intensity image is ``image`` (16 beams x 1800 columns, every point 10 m away)."""
    elev = np.linspace(15, -15, 16)
    sensor = SensorInfo("vlp16", beam_elevations_deg=tuple(elev), columns=1800)
    rows, cols = np.meshgrid(np.arange(16), np.arange(1800), indexing="ij")
    theta = np.pi * (1 - 2 * (cols + 0.5) / 1800)  # eq. 2 inverted at the column centres
    phi = np.radians(elev)[rows]
    xyz = 10 * np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)], -1)
    return Scan(
        xyz.reshape(-1, 3), image.reshape(-1).astype(np.float32), ring=rows.reshape(-1), sensor=sensor
    )


def test_orb_hbst_recognises_a_vlp16_place():
    scan = _vlp16_scan(LOW)
    other = _vlp16_scan(_low(4))
    pipe = make_pipeline("orb-hbst")
    pipe.add(0, other)
    pipe.add(1, scan)
    cands = pipe.query(scan, k=1)
    assert cands and cands[0].match_id == 1
    table_one = make_pipeline("orb-hbst", {"feature_params": {"row_upsample": 1}})
    table_one.add(1, scan)
    assert table_one.query(scan, k=1) == []  # the 16 rows as they are: nothing to match
