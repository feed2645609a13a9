"""Keypoint voting: 2-NN + ratio test + votes, max_id, persistence, places databases, a tiny localisation."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.artifacts.places import build_places
from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.io.atomic import save_artifact
from placerec.pipelines import keypoint_voting as kv
from placerec.pipelines.keypoint_voting import KeypointVoting, knn2, ratio_votes
from placerec.recognizer import make_pipeline
from placerec.three_d import FeatureParams
from placerec.three_d.places import PlacesParams

D = 1344


def unit_rows(rng: np.random.Generator, n: int, dim: int = D) -> np.ndarray:
    x = np.abs(rng.normal(size=(n, dim))).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


#: planted descriptors have no scan to verify with: retrieval alone
OFF = {"verify": {"enabled": False}}


def desc(rows: np.ndarray) -> dict[str, np.ndarray]:
    return {"keypoints": np.zeros((rows.shape[0], 3), np.float32), "descriptors": rows}


@pytest.mark.parametrize("backend", ["faiss", "numpy"])
def test_knn2_is_exact(backend):
    rng = np.random.default_rng(0)
    db, q = unit_rows(rng, 500, 64), unit_rows(rng, 40, 64)
    dist, idx = knn2(q, db, backend)
    full = np.linalg.norm(q[:, None, :] - db[None, :, :], axis=2)
    ref = np.argsort(full, axis=1)[:, :2]
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_allclose(dist, np.take_along_axis(full, ref, 1), rtol=1e-4, atol=1e-5)


def test_ratio_votes_counts_only_distinctive_matches():
    dist = np.array([[0.1, 1.0], [0.95, 1.0], [0.2, 0.25], [0.0, 0.0]])
    idx = np.array([[0, 3], [1, 2], [2, 0], [3, 1]])
    row_entry = np.array([0, 0, 1, 1])
    # tau = 0.1 (vote entry 0), 0.95 (no), 0.8 (vote entry 1 at tau_max 0.9), 0/0 -> 1 (no)
    np.testing.assert_array_equal(ratio_votes(dist, idx, row_entry, 2, 0.9), [1, 1])
    np.testing.assert_array_equal(ratio_votes(dist, idx, row_entry, 2, 0.5), [1, 0])


def planted(rng, n_entries=6, per=80):
    """Entry 3 shares 50 descriptors with the query, entry 1 shares 20; 30 query rows are unrelated."""
    rows = [unit_rows(rng, per) for _ in range(n_entries)]
    target = 3

    def noisy(r):
        return r + rng.normal(0, 0.002, r.shape).astype(np.float32)

    return rows, target, np.vstack([noisy(rows[target][:50]), noisy(rows[1][:20]), unit_rows(rng, 30)])


def test_planted_duplicates_win_and_max_id_is_respected():
    rng = np.random.default_rng(1)
    rows, target, query = planted(rng)
    rec = KeypointVoting(**OFF)
    for i, r in enumerate(rows):
        rec.add_description(10 * i, desc(r), np.eye(4))
    cands = rec.query_description(desc(query), k=3, query_id=7)
    assert cands[0].match_id == 10 * target and cands[0].query_id == 7
    assert cands[0].extra["votes"] >= 45 and cands[0].score == pytest.approx(cands[0].extra["votes"] / 100)
    assert cands[0].relative_pose is None and cands[0].extra["n_query"] == 100
    assert cands[1].match_id == 10 and cands[1].extra["votes"] >= 15
    below = rec.query_description(desc(query), k=10, max_id=10 * target - 1)
    assert below[0].match_id == 10 and all(c.match_id < 10 * target for c in below)
    assert rec.query_description(desc(query), k=3, max_id=10 * target)[0].match_id == 10 * target
    with pytest.raises(ScanDataError):
        rec.add_description(0, desc(rows[0]))


def test_max_id_with_ids_added_out_of_order():
    rng = np.random.default_rng(2)
    rows, target, query = planted(rng)
    ids = [50, 10, 40, 20, 60, 30]  # target (index 3) gets id 20, the runner-up (index 1) id 10
    rec = KeypointVoting(score="votes", **OFF)
    for i, r in zip(ids, rows, strict=True):
        rec.add_description(i, desc(r))
    best = rec.query_description(desc(query))[0]
    assert best.match_id == 20 and best.score == best.extra["votes"] >= 45
    assert rec.query_description(desc(query), max_id=15)[0].match_id == 10
    assert all(c.match_id <= 15 for c in rec.query_description(desc(query), k=6, max_id=15))
    assert rec.query_description(desc(query), max_id=5) == []


def test_save_load_round_trip_and_parameter_check(tmp_path):
    rng = np.random.default_rng(3)
    rows, _, query = planted(rng)
    rec = KeypointVoting(search={"tau_max": 0.8}, **OFF)
    for i, r in enumerate(rows):
        rec.add_description(i, desc(r), np.eye(4))
    rec.save(tmp_path / "db.npz")
    again = KeypointVoting(search={"tau_max": 0.8}, **OFF)
    again.load(tmp_path / "db.npz")
    a, b = rec.query_description(desc(query), k=4), again.query_description(desc(query), k=4)
    assert [(c.match_id, c.score) for c in a] == [(c.match_id, c.score) for c in b]
    with pytest.raises(ArtifactError, match="other parameters"):
        KeypointVoting(search={"tau_max": 0.9}, **OFF).load(tmp_path / "db.npz")
    # how the exact search is computed is no part of a database: another backend loads it, with the same answers
    other = KeypointVoting(search={"tau_max": 0.8, "backend": "faiss", "nn_threads": 2}, **OFF)
    other.load(tmp_path / "db.npz")
    assert [(c.match_id, c.score) for c in other.query_description(desc(query), k=4)] == [
        (c.match_id, c.score) for c in a
    ]
    # a database whose header records them (saved before they were run-time fields) loads too
    arrays, meta = rec._state()
    meta["params"] = rec.params.model_dump(mode="json")
    assert meta["params"]["search"]["backend"] == "numpy"
    save_artifact(tmp_path / "old.npz", kv._KIND, kv._VERSION, arrays, meta)
    again.load(tmp_path / "old.npz")
    # one saved before verification fields existed (absent from its header: their defaults, the old behaviour)
    del (
        meta["params"]["verify"]["score"]["min_constraint"],
        meta["params"]["verify"]["icp_only_coarse_voxel_size"],
    )
    save_artifact(tmp_path / "older.npz", kv._KIND, kv._VERSION, arrays, meta)
    again.load(tmp_path / "older.npz")
    with pytest.raises(ArtifactError, match="other parameters"):  # not when this run sets one
        KeypointVoting(
            search={"tau_max": 0.8}, verify={"enabled": False, "icp_only_coarse_voxel_size": 3.0}
        ).load(tmp_path / "older.npz")
    meta["params"]["search"]["tau_max"] = 0.9
    save_artifact(tmp_path / "other.npz", kv._KIND, kv._VERSION, arrays, meta)
    with pytest.raises(ArtifactError, match="other parameters"):
        again.load(tmp_path / "other.npz")
    meta["params"]["search"]["no_such_field"] = 1  # a header the parameters cannot even read
    save_artifact(tmp_path / "unknown.npz", kv._KIND, kv._VERSION, arrays, meta)
    with pytest.raises(ArtifactError, match="other parameters"):
        again.load(tmp_path / "unknown.npz")


def test_registry_presets_and_bad_parameters():
    assert make_pipeline("shot-votes").params.features.descriptor == "shot"
    assert make_pipeline("fpfh-votes").params.features.descriptor == "fpfh"
    assert make_pipeline("ishot-votes", {"search": {"tau_max": 0.8}}).params.search.tau_max == 0.8
    with pytest.raises(ConfigError):
        make_pipeline("ishot-votes", {"tau": 0.8})
    with pytest.raises(ConfigError):
        KeypointVoting(search={"tau_max": 1.5})


# -- on the simulator --------------------------------------------------------------------------------------------

FAST = dict(features={"descriptor": "ishot", "iss": {"max_keypoints": 100}})


@pytest.fixture(scope="module")
def sim_map():
    from placerec.intensity import normalize_intensity
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "vlp16", n_scans=16, seed=2, spacing=2.0)
    return seq, [normalize_intensity(seq[i]) for i in range(len(seq))]


def test_localises_queries_taken_at_map_poses(sim_map):
    """Scans re-rendered at four map poses later (other clutter and noise) find their map scan."""
    from placerec.intensity import normalize_intensity

    seq, scans = sim_map
    rec = KeypointVoting(**FAST)
    for i, s in enumerate(scans):
        rec.add(i, s, seq.poses[i])
    targets = [2, 6, 10, 14]
    hits = 0
    for t in targets:
        q = normalize_intensity(seq.scan_at(seq.poses[t], timestamp=5000.0 + t, index=1000 + t))
        c = rec.query(q, k=1)
        hits += bool(c) and np.linalg.norm(seq.poses[c[0].match_id][:3, 3] - seq.poses[t][:3, 3]) < 3.0
    # chance: 3 of the 16 scans (2 m apart) lie within 3 m of a query, i.e. 3/16
    assert hits >= 3


def test_aggregated_places_and_places_database(sim_map, tmp_path):
    from placerec.intensity import normalize_intensity

    seq, scans = sim_map
    agg = KeypointVoting(places={"spacing_m": 6.0, "window_m": 6.0}, **FAST)
    for i, s in enumerate(scans):
        agg.add(i, s, seq.poses[i])
    assert agg.entries.ids == [0, 3, 6, 9, 12, 15] and len(agg.entries.store) > 300
    with pytest.raises(ScanDataError, match="pose"):
        KeypointVoting(places={"window_m": 6.0}, **FAST).add(0, scans[0])

    # single-scan places (window 0): a sparse single-scan query meets descriptors of the same density
    feats = FeatureParams(iss={"max_keypoints": 100})
    db = build_places(seq, PlacesParams(spacing_m=6.0, window_m=0.0, features=feats))
    path = tmp_path / "places.npz"
    db.save(path)
    rec = KeypointVoting(places={"database": str(path)}, **FAST)
    assert rec.entries.ids == db.ids.tolist()
    for i in range(len(seq)):  # what the localize evaluator does: consistent with the database, no-op
        rec.add(i, scans[i], seq.poses[i])
    assert len(rec) == len(db)
    with pytest.raises(ArtifactError):
        rec.add(3, scans[3], np.eye(4))
    with pytest.raises(ArtifactError):
        rec.add(len(seq), scans[0], seq.poses[0])
    t = int(db.ids[2])
    q = normalize_intensity(seq.scan_at(seq.poses[t], timestamp=7000.0, index=777))
    c = rec.query(q, k=1)
    assert c and c[0].match_id == t
    with pytest.raises(ArtifactError, match="other feature settings"):
        KeypointVoting(places={"database": str(path)}, features={"descriptor": "shot"})
    assert KeypointVoting.from_places(db).query(q, k=1)[0].match_id == c[0].match_id


def test_voting_params_hold_the_feature_params_as_a_section():
    from placerec.recognizer import make_pipeline
    from placerec.three_d.features import FeatureParams

    rec = make_pipeline(
        "ishot-votes", {"features": {"shot": {"normalization": "per_part"}, "iss": {"salient_radius": 2.0}}}
    )
    feats = rec.params.features
    assert type(feats) is FeatureParams
    assert feats.shot.normalization == "per_part" and feats.descriptor == "ishot"
    assert feats.iss.salient_radius == 2.0 and feats.iss.max_keypoints == 300
    assert set(type(rec.params).model_fields) >= {"features", "search", "places", "verify"}
    assert not set(FeatureParams.model_fields) & set(type(rec.params).model_fields)  # no flattened copies
