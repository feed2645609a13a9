"""Verified loop closures of the 3D pipelines and Scan Context, and the shared candidate-verification step
(`placerec.verify.candidates`): a true loop's ``relative_pose`` (T_match_query) within 0.3 m, a wrong candidate
ranked below it, the verified score and its statistics in every candidate."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.errors import ArtifactError, ConfigError, ScanDataError
from placerec.types import relative_pose
from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, scan_cloud, verify_candidates

QUERY, TRUE, WRONG = 13, 10, 36  # scans 10 and 13 are ~3 m apart; 36 is ~26 m from both


@pytest.fixture(scope="module")
def sim():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=40)
    scans = {i: seq[i] for i in (TRUE, QUERY, WRONG)}
    return seq, scans


@pytest.fixture(scope="module")
def clouds(sim):
    _, scans = sim
    return {i: scan_cloud(s) for i, s in scans.items()}


def _t_err(T, T_gt) -> float:
    return float(np.linalg.norm((np.linalg.inv(T_gt) @ T)[:3, 3]))


def test_scan_cloud_is_voxelised_and_cropped(sim):
    _, scans = sim
    c = scan_cloud(scans[QUERY])
    assert c.dtype == np.float32 and c.shape[1] == 3 and 1000 < len(c) < len(scans[QUERY]) // 2
    cropped = scan_cloud(scans[QUERY], VerifiedParams(verify={"icp": {"max_range": 10.0}}).verify)
    assert np.linalg.norm(cropped, axis=1).max() <= 10.0 + 0.4 and len(cropped) < len(c)


def test_verify_candidates_reranks_and_returns_t_match_query(sim, clouds):
    seq, _ = sim
    T_gt = relative_pose(seq.poses[TRUE], seq.poses[QUERY])
    assert np.linalg.norm(T_gt[:3, 3]) > 2.0  # a translation a swapped convention would get wrong
    store = CloudStore()
    store.add(TRUE, clouds[TRUE])
    store.add(WRONG, clouds[WRONG])
    # the wrong place is retrieved first; verification (ICP from the identity) must put the true one on top
    got = verify_candidates(
        clouds[QUERY],
        [Retrieved(WRONG, 0.9), Retrieved(TRUE, 0.5, extra={"votes": 4})],
        store,
        VerifiedParams(),
        7,
    )
    assert [c.match_id for c in got] == [TRUE, WRONG]
    best, wrong = got
    assert best.query_id == 7 and best.extra["accepted"] and not wrong.extra["accepted"]
    assert _t_err(best.relative_pose, T_gt) < 0.3
    np.testing.assert_allclose(seq.poses[TRUE] @ best.relative_pose, seq.poses[QUERY], atol=0.3)
    assert best.score == best.extra["verify"]["score"] > wrong.score
    assert best.extra["retrieval_score"] == 0.5 and best.extra["votes"] == 4
    assert best.inliers is None  # ICP only
    assert all(c.extra["verify_ms"] > 0 for c in got)
    assert wrong.score < VerifiedParams().verify.score.min_score  # kept, below the acceptance threshold


def test_verify_candidates_top_k_k_and_the_eps_icp_rule(clouds):
    store = CloudStore()
    store.add(TRUE, clouds[TRUE])
    store.add(WRONG, clouds[WRONG])
    retrieved = [Retrieved(WRONG, 0.9), Retrieved(TRUE, 0.5)]
    only_first = verify_candidates(clouds[QUERY], retrieved, store, VerifiedParams(top_k=1))
    assert [c.match_id for c in only_first] == [WRONG]  # beyond top_k: dropped, not verified
    p = VerifiedParams(verify={"score": {"acceptance": "eps_icp", "eps_icp": 1e-6}})
    got = verify_candidates(clouds[QUERY], retrieved, store, p, k=1)
    assert len(got) == 1 and got[0].score == 0.0 and not got[0].extra["accepted"]  # rejected by the rule: 0
    assert verify_candidates(clouds[QUERY], [], store, VerifiedParams()) == []


def test_cloud_store_round_trip_and_errors(clouds):
    store = CloudStore(max_prepared=1)
    store.add(TRUE, clouds[TRUE])
    store.add(WRONG, clouds[WRONG])
    a = store.target(TRUE)
    assert store.target(TRUE) is a  # prepared once
    store.target(WRONG)
    assert store.target(TRUE) is not a  # least recently used dropped beyond max_prepared
    arrays = store.arrays([WRONG, TRUE])
    other = CloudStore()
    other.from_arrays([WRONG, TRUE], arrays)
    np.testing.assert_array_equal(other.cloud(TRUE), clouds[TRUE])
    with pytest.raises(ArtifactError):
        other.from_arrays([TRUE], arrays)
    with pytest.raises(ScanDataError):
        other.cloud(99)
    with pytest.raises(ScanDataError):
        other.add(1, np.zeros((4, 2)))
    with pytest.raises(ConfigError):
        VerifiedParams(top_k=0)
