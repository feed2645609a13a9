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
    cropped = scan_cloud(scans[QUERY], VerifiedParams(icp={"max_range": 10.0}))
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
        [Retrieved(WRONG, 0.9), Retrieved(TRUE, 0.5, extra={"votes": 4}, verify_ms=500.0)],
        store,
        VerifiedParams(),
        7,
    )
    assert [c.match_id for c in got] == [TRUE, WRONG]
    best, wrong = got
    assert best.query_id == 7 and best.accepted and not wrong.accepted
    assert _t_err(best.relative_pose, T_gt) < 0.3
    np.testing.assert_allclose(seq.poses[TRUE] @ best.relative_pose, seq.poses[QUERY], atol=0.3)
    assert best.score == best.verification.score > wrong.score
    assert best.retrieval_score == 0.5 and best.extra["votes"] == 4
    assert best.inliers is None  # ICP only
    assert all(c.verify_ms > 0 for c in got) and best.verify_ms > 500.0  # + its matching
    assert wrong.score < VerifiedParams().score.min_score  # kept, below the acceptance threshold


def test_verify_candidates_top_k_k_and_the_eps_icp_rule(clouds):
    store = CloudStore()
    store.add(TRUE, clouds[TRUE])
    store.add(WRONG, clouds[WRONG])
    retrieved = [Retrieved(WRONG, 0.9), Retrieved(TRUE, 0.5)]
    only_first = verify_candidates(clouds[QUERY], retrieved, store, VerifiedParams(top_k=1))
    assert [c.match_id for c in only_first] == [WRONG]  # beyond top_k: dropped, not verified
    p = VerifiedParams(score={"acceptance": "eps_icp", "eps_icp": 1e-6})
    got = verify_candidates(clouds[QUERY], retrieved, store, p, k=1)
    assert len(got) == 1 and got[0].score == 0.0 and not got[0].accepted  # rejected by the rule: 0
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
    with pytest.raises(ArtifactError, match="cloud_counts"):
        other.from_arrays([WRONG, TRUE], {"cloud_xyz": arrays["cloud_xyz"]})
    with pytest.raises(ScanDataError):
        other.cloud(99)
    with pytest.raises(ScanDataError):
        other.add(1, np.zeros((4, 2)))
    with pytest.raises(ConfigError):
        VerifiedParams(top_k=0)


def test_int16_zlib_store_is_lossless_smaller_and_verifies_identically(clouds):
    from placerec.quantise import FixedPointCloud, PackedCloud

    assert VerifiedParams().cloud_store == "int16-zlib"
    plain, packed = CloudStore(dtype="int16"), CloudStore(dtype="int16-zlib")
    for i in (TRUE, WRONG):
        plain.add(i, clouds[i])
        packed.add(i, clouds[i])
        np.testing.assert_array_equal(packed.cloud(i), plain.cloud(i))  # the very same int16 codes
    # memory accounting reports the compressed bytes: about two thirds of int16's on a voxelised scan
    expected = sum(PackedCloud.encode(clouds[i], level=2).nbytes for i in (TRUE, WRONG))
    assert packed.nbytes == expected < 0.8 * plain.nbytes
    assert plain.nbytes == sum(FixedPointCloud.encode(clouds[i]).nbytes for i in (TRUE, WRONG))
    # saved as float32 points, as before: a database saved from either store is the same file content
    for k, v in plain.arrays([WRONG, TRUE]).items():
        np.testing.assert_array_equal(packed.arrays([WRONG, TRUE])[k], v)
    retrieved = [Retrieved(WRONG, 0.9), Retrieved(TRUE, 0.5)]
    a = verify_candidates(clouds[QUERY], retrieved, plain, VerifiedParams())
    b = verify_candidates(clouds[QUERY], retrieved, packed, VerifiedParams())
    assert [(c.match_id, c.score) for c in a] == [(c.match_id, c.score) for c in b]
    for ca, cb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ca.relative_pose, cb.relative_pose)


# ---------------------------------------------------------------- the 3D pipelines


@pytest.fixture(scope="module")
def voting(sim):
    from placerec.pipelines.keypoint_voting import KeypointVoting

    seq, scans = sim
    rec = KeypointVoting(features={"descriptor": "ishot", "iss": {"max_keypoints": 150}})
    descs = {i: rec.describe(s) for i, s in scans.items()}
    for i in (WRONG, TRUE):
        rec.add_description(i, descs[i], seq.poses[i])
    return rec, descs


def test_keypoint_voting_verifies_with_grouping_ransac_and_icp(sim, voting):
    seq, _ = sim
    rec, descs = voting
    p = rec.params.verify
    assert rec.params.verify.enabled and p.consistency.enabled and p.score.acceptance == "eps_icp"
    assert (p.consistency.min_cluster_size, p.consistency.consensus_resolution, p.score.eps_icp) == (
        8,
        7.0,
        7.0,
    )
    got = rec.query_description(descs[QUERY], k=2, query_id=QUERY)
    assert [c.match_id for c in got] == [TRUE, WRONG]
    best, wrong = got
    T_gt = relative_pose(seq.poses[TRUE], seq.poses[QUERY])
    assert _t_err(best.relative_pose, T_gt) < 0.3
    np.testing.assert_allclose(seq.poses[TRUE] @ best.relative_pose, seq.poses[QUERY], atol=0.3)
    assert best.accepted and best.inliers >= 8 and best.inliers == best.verification.inliers
    assert best.verification.residual < 7.0 and best.extra["votes"] > 0 and best.extra["matches"] >= 8
    assert not wrong.accepted and wrong.score < best.score


def test_keypoint_voting_save_load_keeps_the_clouds(sim, voting, tmp_path):
    from placerec.pipelines.keypoint_voting import KeypointVoting

    rec, descs = voting
    rec.save(tmp_path / "db.npz")
    again = KeypointVoting(rec.params)
    again.load(tmp_path / "db.npz")
    a = rec.query_description(descs[QUERY], k=2)
    b = again.query_description(descs[QUERY], k=2)
    assert [(c.match_id, c.score) for c in a] == [(c.match_id, c.score) for c in b]
    np.testing.assert_allclose(a[0].relative_pose, b[0].relative_pose)
    off = KeypointVoting(rec.params.model_dump() | {"verify": {"enabled": False}})
    off.add_description(1, descs[TRUE])
    off.save(tmp_path / "off.npz")
    with pytest.raises(ArtifactError):  # saved without clouds: cannot verify
        KeypointVoting(rec.params).load(tmp_path / "off.npz")
    with pytest.raises(ScanDataError, match="cloud"):
        KeypointVoting(rec.params).add_description(5, {k: v for k, v in descs[TRUE].items() if k != "cloud"})


# ---------------------------------------------------------------- Scan Context


@pytest.fixture(scope="module")
def scan_context(sim):
    from placerec.baselines.scan_context import ScanContext

    seq, scans = sim
    sc = ScanContext()
    descs = {i: sc.describe(s) for i, s in scans.items()}
    for i in (WRONG, TRUE):
        sc.add_description(i, descs[i], seq.poses[i])
    return sc, descs


def test_scan_context_yaw_seeds_icp_for_a_6dof_pose(sim, scan_context):
    from placerec.baselines.scan_context import ScanContext

    seq, _ = sim
    sc, descs = scan_context
    assert sc.params.verify.enabled and "cloud" in descs[QUERY]
    T_gt = relative_pose(seq.poses[TRUE], seq.poses[QUERY])
    got = sc.query_description(descs[QUERY], k=2, query_id=QUERY)
    assert [c.match_id for c in got] == [TRUE, WRONG]
    best, wrong = got
    assert _t_err(best.relative_pose, T_gt) < 0.3  # the yaw-only pose was off by the whole offset
    np.testing.assert_allclose(seq.poses[TRUE] @ best.relative_pose, seq.poses[QUERY], atol=0.3)
    assert best.accepted and not wrong.accepted and best.score > wrong.score
    assert best.score == best.verification.score and best.inliers is None
    assert -1.0 <= best.retrieval_score <= 1.0 and "yaw_deg" in best.extra
    plain = ScanContext(verify={"enabled": False})
    assert plain.frontend_key != sc.frontend_key  # its descriptions carry no cloud
    plain.add_description(TRUE, plain.describe(sim[1][TRUE]))
    yaw_only = plain.query_description(plain.describe(sim[1][QUERY]))[0]
    assert _t_err(yaw_only.relative_pose, T_gt) > 2.0


def test_scan_context_save_load_keeps_the_clouds(scan_context, tmp_path):
    from placerec.baselines.scan_context import ScanContext

    sc, descs = scan_context
    sc.save(tmp_path / "sc.npz")
    again = ScanContext()
    again.load(tmp_path / "sc.npz")
    a, b = sc.query_description(descs[QUERY], k=2), again.query_description(descs[QUERY], k=2)
    assert [(c.match_id, c.score) for c in a] == [(c.match_id, c.score) for c in b]
    plain = ScanContext(verify={"enabled": False})
    plain.load(tmp_path / "sc.npz")  # the clouds are not needed without verification
    plain.save(tmp_path / "plain.npz")
    with pytest.raises(ArtifactError, match="clouds"):
        ScanContext().load(tmp_path / "plain.npz")
    with pytest.raises(ArtifactError, match="voxel"):  # clouds made at another voxel size
        ScanContext(verify={"icp": {"voxel_size": 0.5}}).load(tmp_path / "sc.npz")
    with pytest.raises(ScanDataError, match="cloud"):
        ScanContext().add_description(3, descs[TRUE]["scan_context"])


def test_local_map_verification_matches_and_aligns_in_the_candidates_frame(sim):
    from placerec.pipelines.keypoint_voting import KeypointVoting

    seq, _ = sim
    rec = KeypointVoting(
        features={"descriptor": "ishot", "iss": {"max_keypoints": 150}}, verify={"radius_m": 10.0}
    )
    descs = {i: rec.describe(seq[i]) for i in (7, TRUE, QUERY, WRONG)}
    for i in (7, TRUE, WRONG):
        rec.add_description(i, descs[i], seq.poses[i])
    e7, e10, e36 = (rec.entries.ids.index(i) for i in (7, TRUE, WRONG))
    assert rec.local_maps.members(e10) == [e10, e7] and rec.local_maps.members(e36) == [e36]
    assert rec.local_maps.members(e10, np.array([False, True, True])) == [e10]  # only eligible neighbours
    # the local map's keypoints, taken back to the world by entry 10's pose, are each entry's world keypoints
    T10 = seq.poses[TRUE]
    kp = rec.local_maps.keypoints(e10, [e10, e7])
    world = np.concatenate(
        [descs[i]["keypoints"] @ seq.poses[i][:3, :3].T + seq.poses[i][:3, 3] for i in (TRUE, 7)]
    )
    np.testing.assert_allclose(kp @ T10[:3, :3].T + T10[:3, 3], world, atol=1e-3)
    merged = rec.local_maps.target([e10, e7])
    assert merged.points.shape[0] > rec.clouds.target(TRUE).points.shape[0]
    assert rec.local_maps.target([e10, e7]) is merged  # prepared once
    got = rec.query_description(descs[QUERY], k=3, query_id=QUERY)
    best = got[0]
    assert best.match_id in (7, TRUE) and best.accepted and best.extra["local_entries"] == 2
    T_gt = relative_pose(seq.poses[best.match_id], seq.poses[QUERY])
    assert _t_err(best.relative_pose, T_gt) < 0.3
    assert all(c.extra["local_entries"] == 1 for c in got if c.match_id == WRONG)
