import numpy as np
import pytest

from placerec.baselines.scan_context import (
    ScanContext,
    ScanContextParams,
    make_descriptor,
    ring_key,
    scan_context_distance,
    sector_key,
)
from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.types import PlaceRecognizer, Scan


def plain(**overrides) -> ScanContext:
    """Scan Context as the reference has it: no verification (these tests check its retrieval and yaw)."""
    return ScanContext(verify={"enabled": False}, **overrides)


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def scan_of(xyz):
    xyz = np.asarray(xyz, dtype=np.float32)
    return Scan(xyz, np.zeros(len(xyz), dtype=np.float32))


def make_place(rng, n_boxes=25):
    """A synthetic place seen from the origin: a noisy ground disc and boxes of random size and height."""
    n_ground = 3000
    r = 60 * np.sqrt(rng.random(n_ground))
    a = rng.random(n_ground) * 2 * np.pi
    ground = np.c_[r * np.cos(a), r * np.sin(a), -1.7 + 0.05 * rng.normal(size=n_ground)]
    boxes = []
    for _ in range(n_boxes):
        rc, ac = rng.uniform(5, 60), rng.uniform(0, 2 * np.pi)
        size, height = rng.uniform(2, 8, size=2), rng.uniform(0.5, 10)
        lo = np.array([rc * np.cos(ac) - size[0] / 2, rc * np.sin(ac) - size[1] / 2, -1.7])
        boxes.append(lo + rng.random((200, 3)) * np.r_[size, height])
    return np.vstack([ground, *boxes])


def observe(points, rng, yaw_deg=0.0, keep=0.7, noise=0.03):
    """The place seen by a sensor yawed by ``yaw_deg`` (T_match_query = Rz(yaw)): p_query = Rz(-yaw) p_match."""
    sel = points[rng.random(len(points)) < keep]
    sel = sel + noise * rng.normal(size=sel.shape)
    return scan_of(sel @ rot_z(-yaw_deg).T)


# ---------------------------------------------------------------- descriptor


def test_descriptor_hand_checked_cells():
    pts = [
        [1.0, 0.5, 0.3],  # r 1.12 -> ring 0; azimuth 26.6 deg -> sector 4; 0.3 + 2
        [1.0, 0.5, 1.0],  # same cell, higher: the cell keeps 3.0
        [0.0, 10.0, -1.0],  # r 10 -> ring 2; azimuth 90 -> sector 14 (ceil: (84, 90] deg)
        [0.0, -10.0, -3.0],  # azimuth 270 -> sector 44; below -2 m: negative value is kept
        [10.0, 0.0, 0.0],  # azimuth 0 -> sector 0
        [-79.0, -0.01, 0.5],  # r 79 -> ring 19; azimuth 180.007 -> sector 30
        [10.0, 10.0, 7.0],  # r 14.1 -> ring 3; azimuth 45 -> sector 7
        [81.0, 0.0, 5.0],  # beyond 80 m: ignored
        [np.nan, 0.0, 5.0],  # not finite: ignored
    ]
    d = make_descriptor(np.array(pts))
    assert d.shape == (20, 60) and d.dtype == np.float32
    expected = {(0, 4): 3.0, (2, 14): 1.0, (2, 44): -1.0, (2, 0): 2.0, (19, 30): 2.5, (3, 7): 9.0}
    for (r, s), v in expected.items():
        assert d[r, s] == pytest.approx(v), (r, s)
    assert np.count_nonzero(d) == len(expected)
    # sensor height is configurable
    d0 = make_descriptor(np.array(pts), ScanContextParams(lidar_height=0.0))
    assert d0[0, 4] == pytest.approx(1.0)


def test_descriptor_of_empty_scan_is_zero():
    d = make_descriptor(scan_of(np.zeros((0, 3))))
    assert d.shape == (20, 60) and not d.any()
    with pytest.raises(ScanDataError):
        make_descriptor(np.zeros((5, 2)))


def test_ring_and_sector_keys():
    rng = np.random.default_rng(0)
    d = make_descriptor(scan_of(make_place(rng)))
    assert ring_key(d).shape == (20,) and sector_key(d).shape == (60,)
    np.testing.assert_allclose(ring_key(d), d.mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(ring_key(np.roll(d, 17, axis=1)), ring_key(d), rtol=1e-6)  # rotation invariant
    np.testing.assert_allclose(sector_key(np.roll(d, 17, axis=1)), np.roll(sector_key(d), 17), rtol=1e-6)


def test_distance_is_zero_for_rolled_descriptor_and_shift_recovered():
    rng = np.random.default_rng(1)
    d = rng.random((20, 60)) * (rng.random((1, 60)) > 0.2)
    for k in (0, 1, 13, 30, 59):
        q = np.roll(d, k, axis=1)
        for radius in (3, None):
            dist, shift = scan_context_distance(q, d[None], radius)
            assert dist[0] == pytest.approx(0.0, abs=1e-9) and shift[0] == k


def test_distance_definition_on_hand_case():
    # three columns non-empty in both: cosines 1, 0, 1; column 2 is empty in c and skipped
    q = np.zeros((2, 4))
    c = np.zeros((2, 4))
    q[:, 0], c[:, 0] = [1, 0], [2, 0]  # cos 1
    q[:, 1], c[:, 1] = [1, 0], [0, 3]  # cos 0
    q[:, 2] = [0.5, 0.5]  # empty in c
    q[:, 3], c[:, 3] = [10, 0], [10, 0]  # cos 1
    # sector keys q [.5 .5 .5 5], c [1 1.5 0 5]: squared difference 1.5 at shift 0, >= 17 at the others
    dist, shift = scan_context_distance(q, c[None], search_radius=0)  # coarse alignment only
    assert shift[0] == 0 and dist[0] == pytest.approx(1 - (1 + 0 + 1) / 3)
    assert scan_context_distance(q, np.zeros((1, 2, 4)), None)[0][0] == 1.0  # nothing in common


def _reference_distance(q: np.ndarray, c: np.ndarray) -> tuple[float, int]:
    """Scan Context's distance over every shift, column by column as the paper writes it."""
    S = q.shape[1]
    best = (np.inf, 0)
    for s in range(S):
        r = np.roll(c, s, axis=1)
        sims = [
            q[:, j] @ r[:, j] / (np.linalg.norm(q[:, j]) * np.linalg.norm(r[:, j]))
            for j in range(S)
            if np.linalg.norm(q[:, j]) > 0 and np.linalg.norm(r[:, j]) > 0
        ]
        d = 1.0 - np.mean(sims) if sims else 1.0
        if d < best[0] - 1e-12:
            best = (d, s)
    return best


def test_a_limited_view_is_compared_on_its_own_columns():
    """A query that fills only some sectors (a 70 deg cone: 12 of 60) against full candidates: the distance over
    every shift is the paper's, computed on the query's columns with points only."""
    rng = np.random.default_rng(7)
    full = rng.random((5, 20, 60)) * (rng.random((5, 1, 60)) > 0.1)
    q = np.zeros((20, 60))
    q[:, 20:32] = np.roll(full[3], 9, axis=1)[:, 20:32]  # candidate 3 seen through a cone, turned 9 sectors
    dist, shift = scan_context_distance(q, full, None)
    for m in range(5):
        ref_d, ref_s = _reference_distance(q, full[m])
        assert dist[m] == pytest.approx(ref_d, abs=1e-12) and shift[m] == ref_s
    assert np.argmin(dist) == 3 and shift[3] == 9 and dist[3] == pytest.approx(0.0, abs=1e-12)


def test_rotation_by_whole_sectors():
    rng = np.random.default_rng(2)
    pts = make_place(rng)
    sc = plain()
    sc.add(0, scan_of(pts))
    for k in (1, 5, 29, 44):
        c = sc.query(scan_of(pts @ rot_z(k * 6.0).T))[0]  # the scene turns by k sectors
        assert c.extra["shift"] == k and c.extra["yaw_deg"] == pytest.approx(-((k * 6.0 + 180) % 360 - 180))
        assert c.extra["distance"] < 0.01 and c.score == pytest.approx(1 - c.extra["distance"])


@pytest.mark.parametrize("yaw", [-150.0, -37.0, 37.0, 100.0, 171.0])
def test_relative_pose_maps_query_into_match_frame(yaw):
    rng = np.random.default_rng(3)
    pts = make_place(rng)
    sc = plain(full_shift_search=True)
    sc.add(7, scan_of(pts))
    query = observe(pts, rng, yaw_deg=yaw)
    c = sc.query(query, query_id=99)[0]
    assert (c.query_id, c.match_id) == (99, 7)
    err = (c.extra["yaw_deg"] - yaw + 180) % 360 - 180
    assert abs(err) <= 6.0  # within one sector
    # T_match_query maps the query's points onto the match frame
    T = c.relative_pose
    assert T.shape == (4, 4) and np.allclose(T[:3, 3], 0) and np.allclose(T[:3, :3] @ rot_z(-yaw), rot_z(err))
    assert np.degrees(np.arctan2(T[1, 0], T[0, 0])) == pytest.approx(c.extra["yaw_deg"])


def test_default_search_recovers_yaw_too():
    rng = np.random.default_rng(4)
    pts = make_place(rng)
    sc = plain()
    sc.add(0, scan_of(pts))
    c = sc.query(observe(pts, rng, yaw_deg=-80.0))[0]
    assert abs((c.extra["yaw_deg"] + 80.0 + 180) % 360 - 180) <= 6.0


# ---------------------------------------------------------------- recognizer


def test_synthetic_place_recognition():
    rng = np.random.default_rng(5)
    places = [make_place(rng) for _ in range(20)]
    sc = plain(tree_rebuild_every=8)
    assert isinstance(sc, PlaceRecognizer) and sc.name == "scan-context"
    for i, p in enumerate(places):
        sc.add(100 + i, scan_of(p))
    assert len(sc) == 20 and sc.ids.tolist() == list(range(100, 120))
    for i in rng.choice(20, 8, replace=False):
        cands = sc.query(observe(places[i], rng, yaw_deg=rng.uniform(-180, 180)), k=3)
        assert len(cands) == 3 and cands[0].match_id == 100 + i
        assert cands[0].score > cands[1].score >= cands[2].score
        assert cands[0].score > 0.8


def test_max_id_filtering():
    rng = np.random.default_rng(6)
    places = [make_place(rng) for _ in range(10)]
    sc = plain(tree_rebuild_every=3)  # some entries in the tree, some brute-forced
    for i, p in enumerate(places):
        sc.add(i, scan_of(p))
    q = observe(places[7], rng)
    assert sc.query(q, max_id=7)[0].match_id == 7
    cands = sc.query(q, k=10, max_id=5)
    assert len(cands) == 6 and all(c.match_id <= 5 for c in cands)
    assert sc.query(q, max_id=-1) == []
    assert plain().query(q) == []  # empty database


def test_retrieval_is_exact_between_tree_rebuilds():
    """Ring-key candidates must equal a brute-force search, whatever the tree state, ids order and max_id."""
    rng = np.random.default_rng(7)
    n = 60
    descs = (rng.random((n, 20, 60)) * (rng.random((n, 1, 60)) > 0.3)).astype(np.float32)
    ids = rng.permutation(1000)[:n]  # not in insertion order
    sc = plain(num_candidates=4, tree_rebuild_every=16)
    for i in range(n):
        sc.add_description(int(ids[i]), descs[i])
    keys = descs.mean(axis=2)
    for _ in range(25):
        q = descs[rng.integers(n)] + 0.05 * rng.random((20, 60)).astype(np.float32)
        max_id = int(rng.integers(0, 1000))
        elig = np.flatnonzero(ids <= max_id)
        got = sc.query_description(q, k=4, max_id=max_id)
        near = elig[np.argsort(np.linalg.norm(keys[elig] - q.mean(axis=1), axis=1))[:4]]
        dist, _ = scan_context_distance(q, descs[near], 3)
        expected = ids[near[np.argsort(dist, kind="stable")]]
        assert [c.match_id for c in got] == expected.tolist()


def test_add_rejects_duplicates_and_bad_descriptors():
    sc = plain()
    sc.add_description(1, np.zeros((20, 60)))
    with pytest.raises(ScanDataError):
        sc.add_description(1, np.zeros((20, 60)))
    with pytest.raises(ScanDataError):
        sc.add_description(2, np.zeros((20, 61)))


def test_params_validation():
    with pytest.raises(ConfigError, match="allowed"):
        plain(num_ringz=10)
    with pytest.raises(ConfigError):
        plain(num_sectors=0)
    assert ScanContext({"num_rings": 10}).params.num_rings == 10
    assert ScanContextParams().search_radius == 3


def test_save_load_identity(tmp_path):
    rng = np.random.default_rng(8)
    places = [make_place(rng) for _ in range(6)]
    sc = plain(tree_rebuild_every=4)
    for i, p in enumerate(places):
        sc.add(10 * i, scan_of(p))
    path = tmp_path / "db" / "sc.npz"
    sc.save(path)
    other = plain(num_candidates=3)  # query-time parameters may differ
    other.load(path)
    assert other.ids.tolist() == sc.ids.tolist()
    np.testing.assert_array_equal(other._desc[: len(other)], sc._desc[: len(sc)])
    q = observe(places[4], rng, yaw_deg=20.0)
    a, b = sc.query(q, k=3), other.query(q, k=3)
    assert [(c.match_id, c.score, c.extra["shift"]) for c in a] == [
        (c.match_id, c.score, c.extra["shift"]) for c in b
    ]
    other.add(99, scan_of(places[0]))  # still usable after load
    assert other.query(scan_of(places[0]))[0].match_id in (0, 99)


def test_load_refuses_other_parameters_and_corrupt_files(tmp_path):
    sc = plain()
    sc.add_description(0, np.ones((20, 60)))
    path = tmp_path / "sc.npz"
    sc.save(path)
    with pytest.raises(ArtifactError, match="parameters"):
        plain(num_rings=10).load(path)
    with pytest.raises(ArtifactError):
        plain(lidar_height=1.73).load(path)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ArtifactError):
        plain().load(bad)
    with pytest.raises(ArtifactError):
        plain().load(tmp_path / "missing.npz")


def test_describe_split_and_frontend_key():
    rng = np.random.default_rng(9)
    scan = scan_of(make_place(rng))
    a, b = plain(), plain(num_candidates=5, full_shift_search=True)
    desc = a.describe(scan)
    assert set(desc) == {"scan_context"} and desc["scan_context"].shape == (20, 60)
    assert a.frontend_key == b.frontend_key  # query-time parameters do not change descriptions
    assert a.frontend_key != plain(lidar_height=1.73).frontend_key
    b.add_description(3, desc)
    assert b.query_description(desc)[0].match_id == 3
    assert ScanContext({"num_rings": 10}).params.num_rings == 10
    with pytest.raises(ConfigError, match="rings: unknown key"):
        ScanContext({"rings": 10})
