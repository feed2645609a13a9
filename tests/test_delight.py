"""DELIGHT (placerec.pipelines.delight): the histograms per part, the chi-squared distance, the heading handling by
cyclic sector shifts, the ranking handed to the shared verification, bad input and the saved database."""

from dataclasses import replace

import numpy as np
import pytest

from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.pipelines.delight import (
    Delight,
    DelightParams,
    chi_squared,
    delight_distance,
    make_descriptor,
)
from placerec.recognizer import make_pipeline
from placerec.types import Scan, relative_pose


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def rotated(scan: Scan, deg: float) -> Scan:
    """The scan seen by a sensor yawed by ``-deg``: every point rotated by ``deg`` about z."""
    return replace(scan, xyz=(scan.xyz.astype(np.float64) @ rot_z(deg).T).astype(np.float32))


@pytest.fixture(scope="module")
def town():
    from placerec.sim import SimulatedSequence

    return SimulatedSequence(world="town", sensor="vlp16", n_scans=5, seed=5, clutter=False, spacing=2.0)


# ---------------------------------------------------------------- descriptor


def test_histogram_per_part_on_a_hand_built_cloud():
    p = DelightParams(inner_radius=10.0, outer_radius=20.0, bins=4)
    pts = [
        ([1.0, 0.0, 0.0], 0.1),  # r 1: inner ball; azimuth 0 -> sector 0; 0.1 * 4 -> bin 0
        ([2.0, 0.1, 0.0], 0.6),  # inner, sector 0, bin 2
        ([0.0, 5.0, 0.0], 0.99),  # azimuth 90 deg: the first of sector 2; bin 3
        ([0.0, 1.0, 0.0], 0.5),  # inner, sector 2, 0.5 * 4 = 2 -> bin 2
        ([-15.0, 0.0, 0.0], 1.0),  # shell, azimuth 180 -> sector 4; 1.0 -> the last bin
        ([0.0, -12.0, 5.0], 0.3),  # r 13: shell; azimuth 270 -> sector 6; bin 1
        ([10.0, -0.001, 0.0], 0.25),  # r just above 10: shell; azimuth just below 360 -> sector 7; bin 1
        ([0.0, 3.0, 0.0], 7.0),  # intensity above 1: the last bin
        ([25.0, 0.0, 0.0], 0.5),  # beyond the outer sphere: ignored
        ([0.0, 0.0, 0.0], 0.5),  # at the origin (no return): ignored
    ]
    scan = Scan(np.array([x for x, _ in pts]), np.array([i for _, i in pts]))
    h = make_descriptor(scan, p)
    expected = np.zeros((2, 8, 4))
    expected[0, 0] = [0.5, 0, 0.5, 0]
    expected[0, 2] = [0, 0, 1 / 3, 2 / 3]
    expected[1, 4] = [0, 0, 0, 1]
    expected[1, 6] = [0, 1, 0, 0]
    expected[1, 7] = [0, 1, 0, 0]
    assert h.shape == (2, 8, 4) and h.dtype == np.float32
    assert np.allclose(h, expected, atol=1e-7)


def test_chi_squared_on_hand_computed_values():
    a = np.array([0.5, 0.5, 0.0, 0.0]).reshape(1, 1, 4)
    b = np.array([0.25, 0.25, 0.5, 0.0]).reshape(1, 1, 4)
    # 0.25^2 / 0.75 twice + 0.5^2 / 0.5, the empty bin adds nothing
    assert chi_squared(a, b) == pytest.approx(2 * 0.0625 / 0.75 + 0.5)
    assert chi_squared(b, a) == pytest.approx(chi_squared(a, b))
    assert chi_squared(a, a) == 0.0
    disjoint = np.array([0.0, 0.0, 0.0, 1.0]).reshape(1, 1, 4)
    assert chi_squared(a, disjoint) == pytest.approx(2.0)  # two normalised histograms with no bin in common


def test_distance_sums_the_parts_and_takes_the_best_cyclic_shift():
    rng = np.random.default_rng(3)
    entry = rng.random((2, 8, 5))
    entry /= entry.sum(axis=2, keepdims=True)
    other = rng.random((2, 8, 5))
    other /= other.sum(axis=2, keepdims=True)
    query = np.roll(entry, 3, axis=1)  # the scene turned by 3 sectors
    dist, shift = delight_distance(query, np.stack([other, entry]))
    assert dist[1] == pytest.approx(0.0, abs=1e-12) and shift[1] == 3
    by_hand = min(
        sum(chi_squared(query[i, j][None, None], np.roll(other, s, axis=1)[i, j][None, None])
            for i in range(2) for j in range(8))
        for s in range(8)
    )  # fmt: skip
    assert dist[0] == pytest.approx(by_hand)
    fixed, zero = delight_distance(query, np.stack([other, entry]), shifts=False)
    assert fixed[1] > 0.5 and (zero == 0).all()
    assert fixed[0] == pytest.approx(float(chi_squared(query, other)))
    with pytest.raises(ScanDataError, match="shape"):
        delight_distance(query[:, :, :4], entry[None])


def test_yaw_by_whole_sectors_rolls_the_sectors_and_shifts_find_it(town):
    p = DelightParams()
    scan = town[2]
    base = make_descriptor(scan, p)
    for k in (1, 3, 6):
        # a point's azimuth moves by k sectors; points within float error of a border may cross it
        turned = make_descriptor(rotated(scan, 45.0 * k), p)
        assert np.abs(turned - np.roll(base, k, axis=1)).sum() < 0.05
        dist, shift = delight_distance(turned, base[None])
        assert dist[0] < 0.05 and shift[0] == k
        fixed, _ = delight_distance(turned, base[None], shifts=False)
        assert fixed[0] > 20 * max(dist[0], 1e-3)


def test_the_ranking_is_unchanged_by_the_heading_under_shifts_only(town):
    plain = Delight(verify={"enabled": False})
    fixed = Delight(verify={"enabled": False}, sector_shifts=False)
    for i in range(5):
        for rec in (plain, fixed):
            rec.add(i, town[i], town.poses[i])
    query = rotated(town[3], 135.0)
    c = plain.query(query, k=5)
    assert c[0].match_id == 3 and c[0].extra["shift"] == 3 and c[0].extra["yaw_deg"] == -135.0
    assert c[0].score > 0.99 and c[0].relative_pose is None
    assert [x.score for x in c] == sorted((x.score for x in c), reverse=True)
    assert fixed.query(query, k=1)[0].score < c[0].score - 0.05


# ---------------------------------------------------------------- pipeline


def test_a_query_from_the_map_finds_itself_with_a_6dof_pose_through_the_shared_verification(town):
    rec = make_pipeline("delight")
    assert isinstance(rec, Delight) and rec.params.features.descriptor == "shot"
    assert rec.params.verify.consistency.enabled and rec.params.verify.radius_m == 15.0
    for i in (0, 2, 4):
        rec.add(i, town[i], town.poses[i])
    c = rec.query(town[2], k=1, query_id=2)[0]
    assert c.match_id == 2 and c.accepted and c.extra["rank"] == 0 and c.extra["distance"] == 0.0
    assert np.allclose(c.relative_pose, np.eye(4), atol=0.05)
    assert np.allclose(c.T_world_query[:3, 3], town.poses[2][:3, 3], atol=0.05)
    # a scan between map entries, turned by 90 degrees: ranked, verified, its 6-DoF pose recovered
    query = rotated(town[1], 90.0)
    c = rec.query(query, k=1, query_id=1)[0]
    assert c.accepted and c.match_id in (0, 2)
    truth = relative_pose(town.poses[c.match_id], town.poses[1])
    truth[:3, :3] = truth[:3, :3] @ rot_z(-90.0)  # the query sensor turned by -90 degrees
    assert np.linalg.norm(c.relative_pose[:3, 3] - truth[:3, 3]) < 0.3
    assert np.allclose(c.relative_pose[:3, :3], truth[:3, :3], atol=0.02)


def test_entries_kept_apart_carry_their_own_histograms(town):
    rec = Delight(verify={"enabled": False}, places={"spacing_m": 3.0})
    for i in range(5):
        rec.add(i, town[i], town.poses[i])  # 2 m apart: scans 0, 2, 4 become entries
    assert len(rec) == 3
    for i in (0, 2, 4):
        c = rec.query(town[i], k=3)
        assert c[0].match_id == i and c[0].score == pytest.approx(1.0)
        assert {x.match_id for x in c} == {0, 2, 4}
    assert rec.query(town[4], k=3, max_id=2)[0].match_id in (0, 2)
    assert rec.query(town[4], k=3, max_id=-1) == []


def test_bad_input_is_refused(town):
    rec = Delight(verify={"enabled": False})
    few = Scan(town[0].xyz[:50], town[0].intensity[:50])
    with pytest.raises(ScanDataError, match="valid points"):
        rec.describe(few)
    for value in (0.0, 0.4, 80.0):
        flat = replace(town[0], intensity=np.full(len(town[0]), value, np.float32))
        with pytest.raises(ScanDataError, match="intensity of the valid points is constant"):
            rec.describe(flat)
    with pytest.raises(ScanDataError, match="'delight'"):
        rec.add_description(0, {"keypoints": np.zeros((0, 3)), "descriptors": np.zeros((0, 352))})
    with pytest.raises(ScanDataError, match="shape"):
        rec.add_description(0, {**rec.describe(town[0]), "delight": np.zeros((2, 8, 7), np.float32)})
    with pytest.raises(ConfigError, match="inner_radius"):
        Delight(inner_radius=40.0, outer_radius=40.0)
    with pytest.raises(ConfigError, match="places.database"):
        Delight(places={"database": "places.npz"})
    with pytest.raises(ConfigError, match="bins"):
        Delight(bins=1)


def test_save_load_round_trip(town, tmp_path):
    rec = make_pipeline("delight")
    descriptions = [rec.describe(town[i]) for i in range(5)]
    for i in (0, 2, 4):
        rec.add_description(i, descriptions[i], town.poses[i])
    rec.save(tmp_path / "db.npz")
    fresh = make_pipeline("delight")
    fresh.load(tmp_path / "db.npz")

    def answers(r):
        return [
            [(c.match_id, round(c.score, 9), c.extra["distance"],
              None if c.relative_pose is None else c.relative_pose.round(6).tolist())
             for c in r.query_description(d, k=3)]
            for d in descriptions
        ]  # fmt: skip

    assert answers(fresh) == answers(rec)
    with pytest.raises(ArtifactError, match="other parameters"):
        make_pipeline("delight", {"inner_radius": 15.0}).load(tmp_path / "db.npz")
    with pytest.raises(ArtifactError):
        make_pipeline("delight", {"bins": 16}).load(tmp_path / "db.npz")
    with pytest.raises(ArtifactError):
        make_pipeline("shot-gestalt-votes").load(tmp_path / "db.npz")
