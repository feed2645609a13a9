"""Tests of placerec.verify: Kabsch/yaw closed forms, RANSAC, consistency grouping, ICP and the verified score."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placerec.errors import ConfigError, ScanDataError
from placerec.types import relative_pose
from placerec.verify import (
    ConsistencyParams,
    RansacParams,
    ScoreParams,
    VerifyParams,
    group_correspondences,
    kabsch_batch,
    ransac_pose,
    required_iterations,
    rigid_fit,
    verified_score,
    verify,
    verify_icp,
)


def _pose(rotvec_deg, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(rotvec_deg)).as_matrix()
    T[:3, 3] = t
    return T


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


# ---------------------------------------------------------------- Kabsch


def test_kabsch_recovers_a_hand_made_transform():
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
    # 90 deg about z, then translation (1, 2, 3): (x, y, z) -> (-y + 1, x + 2, z + 3)
    dst = np.column_stack([-src[:, 1] + 1, src[:, 0] + 2, src[:, 2] + 3])
    T = rigid_fit(src, dst)
    expected = np.array([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(T, expected, atol=1e-12)


def test_kabsch_weights_select_the_trusted_pairs():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3)) * 5
    T_true = _pose([10, -20, 30], [1, -2, 0.5])
    dst = _apply(T_true, src)
    dst[7:] += 4.0  # three corrupted pairs, weight 0
    w = np.r_[np.ones(7), np.zeros(3)]
    np.testing.assert_allclose(rigid_fit(src, dst, w), T_true, atol=1e-10)
    assert not np.allclose(rigid_fit(src, dst), T_true, atol=1e-3)


def test_kabsch_never_returns_a_reflection():
    # Planar points mirrored through z = 0 plus noise: the plain V U^T of the cross covariance is a reflection
    # (det -1); the sign-corrected solution is the best proper rotation.
    rng = np.random.default_rng(2)
    src = np.column_stack([rng.normal(size=(20, 2)) * 3, rng.normal(size=20) * 0.3])
    dst = src * np.array([1.0, 1.0, -1.0])
    a, b = src - src.mean(0), dst - dst.mean(0)
    U, _, Vt = np.linalg.svd(a.T @ b)
    assert np.linalg.det(Vt.T @ U.T) < 0  # the naive answer is a reflection
    R, _ = kabsch_batch(src[None], dst[None])
    assert np.linalg.det(R[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(R[0] @ R[0].T, np.eye(3), atol=1e-12)
    # it is the best proper rotation: SciPy's independent solver (quaternion method) agrees
    ref, _ = Rotation.align_vectors(b, a)
    np.testing.assert_allclose(R[0], ref.as_matrix(), atol=1e-8)


def test_ransac_kernel_solves_samples_as_kabsch_does():
    # RANSAC's compiled minimal solver (Horn's quaternion form) against the SVD Kabsch on noisy 3-point samples,
    # and on the mirrored planar set where a plain SVD answer would be a reflection
    from placerec.verify.ransac import _kabsch3

    rng = np.random.default_rng(4)
    R, t = np.empty((3, 3)), np.empty(3)
    for _ in range(200):
        src = rng.normal(size=(3, 3)) * 5
        T = _pose(rng.normal(size=3) * 60, rng.normal(size=3) * 5)
        dst = _apply(T, src) + rng.normal(size=(3, 3)) * 0.3
        _kabsch3(src, dst, R, t)
        R_ref, t_ref = kabsch_batch(src[None], dst[None])
        np.testing.assert_allclose(R, R_ref[0], atol=1e-9)
        np.testing.assert_allclose(t, t_ref[0], atol=1e-9)
    src = np.column_stack([rng.normal(size=(20, 2)) * 3, rng.normal(size=20) * 0.3])
    dst = src * np.array([1.0, 1.0, -1.0])
    _kabsch3(src, dst, R, t)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R, kabsch_batch(src[None], dst[None])[0][0], atol=1e-9)


def test_kabsch_batch_solves_every_hypothesis():
    rng = np.random.default_rng(3)
    Ts = [_pose(rng.normal(size=3) * 40, rng.normal(size=3) * 5) for _ in range(50)]
    src = rng.normal(size=(50, 3, 3)) * 4
    dst = np.stack([_apply(T, s) for T, s in zip(Ts, src, strict=True)])
    R, t = kabsch_batch(src, dst)
    for h, T in enumerate(Ts):
        np.testing.assert_allclose(R[h], T[:3, :3], atol=1e-9)
        np.testing.assert_allclose(t[h], T[:3, 3], atol=1e-9)


def test_yaw_closed_form_is_the_least_squares_yaw():
    rng = np.random.default_rng(4)
    src = rng.normal(size=(40, 3)) * 6
    T_true = _pose([0, 0, 73], [3, -1, 0.4])
    dst = _apply(T_true, src) + rng.normal(size=(40, 3)) * 0.05
    T = rigid_fit(src, dst, mode="4dof")
    cost = lambda M: np.sum((_apply(M, src) - dst) ** 2)  # noqa: E731
    for d in (-0.2, 0.2):  # a nearby yaw, each with its best translation, costs more
        M = _pose([0, 0, np.rad2deg(np.arctan2(T[1, 0], T[0, 0])) + d], [0, 0, 0])
        M[:3, 3] = dst.mean(0) - M[:3, :3] @ src.mean(0)
        assert cost(M) > cost(T)
    assert np.rad2deg(np.arctan2(T[1, 0], T[0, 0])) == pytest.approx(73, abs=0.2)


def test_rigid_fit_rejects_bad_input():
    with pytest.raises(ScanDataError):
        rigid_fit(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ScanDataError):
        rigid_fit(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ScanDataError):
        rigid_fit(np.full((4, 3), np.nan), np.zeros((4, 3)))
    with pytest.raises(ScanDataError):
        rigid_fit(np.zeros((4, 2)), np.zeros((4, 2)))


# ---------------------------------------------------------------- RANSAC


def _outlier_set(n=200, outlier_ratio=0.7, T=None, noise=0.05, seed=5):
    rng = np.random.default_rng(seed)
    T = _pose([5, -3, 140], [4.0, -2.5, 0.3]) if T is None else T
    src = rng.uniform(-30, 30, size=(n, 3)) * [1, 1, 0.15]
    dst = _apply(T, src) + rng.normal(size=(n, 3)) * noise
    bad = rng.permutation(n)[: int(outlier_ratio * n)]
    dst[bad] = rng.uniform(-30, 30, size=(len(bad), 3)) * [1, 1, 0.15]
    good = np.ones(n, dtype=bool)
    good[bad] = False
    return src, dst, T, good


def test_ransac_recovers_a_pose_with_70_percent_outliers():
    src, dst, T, good = _outlier_set()
    r = ransac_pose(src, dst, RansacParams(inlier_threshold=0.3))
    assert r.success
    np.testing.assert_allclose(r.T[:3, 3], T[:3, 3], atol=0.05)
    angle = np.rad2deg(Rotation.from_matrix(r.T[:3, :3] @ T[:3, :3].T).magnitude())
    assert angle < 0.3
    assert (r.inliers == good).mean() > 0.98
    # adaptive stop: far fewer hypotheses than the cap at w = 0.3 (about 253 for s = 3, confidence 0.999)
    assert r.iterations <= 1.5 * required_iterations(0.3, 3, 0.999)
    assert r.iterations < RansacParams().max_iterations


def test_required_iterations_formula():
    assert required_iterations(0.5, 3, 0.99) == pytest.approx(np.log(0.01) / np.log(1 - 0.125))
    assert required_iterations(1.0, 3, 0.99) == 1.0
    assert required_iterations(0.0, 3, 0.99) == float("inf")


def test_ransac_4dof_keeps_roll_and_pitch_exactly_zero():
    T = _pose([0, 0, -35], [2.0, 1.0, -0.2])
    src, dst, _, _ = _outlier_set(T=T, outlier_ratio=0.5, seed=6)
    tilted = _pose([2.0, -1.5, 0], [0, 0, 0])  # a small tilt the 4-DoF model must not follow
    dst = _apply(tilted, dst)
    r = ransac_pose(src, dst, RansacParams(mode="4dof", inlier_threshold=1.0))
    assert r.success
    R = r.T[:3, :3]
    assert R[2, 0] == 0.0 and R[2, 1] == 0.0 and R[0, 2] == 0.0 and R[1, 2] == 0.0 and R[2, 2] == 1.0
    assert np.rad2deg(np.arctan2(R[1, 0], R[0, 0])) == pytest.approx(-35, abs=1.0)


def test_ransac_without_a_consistent_set_fails_cleanly():
    rng = np.random.default_rng(7)
    r = ransac_pose(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)))
    assert not r.success and r.n_inliers == 0
    with pytest.raises(ScanDataError):
        ransac_pose(np.zeros((5, 3)), np.zeros((4, 3)))


def test_ransac_params_are_strict():
    with pytest.raises(ConfigError):
        RansacParams(inlier_threshold=-1.0)
    with pytest.raises(ConfigError):
        RansacParams(mode="5dof")
    with pytest.raises(ConfigError):
        VerifyParams(ransac={"inlier_treshold": 0.3})
    with pytest.raises(ConfigError):
        VerifyParams(icp={"backend": "open3d", "method": "gicp"})


# ---------------------------------------------------------------- consistency grouping


def test_consistency_grouping_on_a_hand_made_case():
    # Four correspondences move rigidly (a translation by (10, 0, 0)); two are wrong: their distances to the
    # others change by more than the resolution. Min cluster 3, resolution 1 m.
    src = np.array([[0.0, 0, 0], [4, 0, 0], [0, 4, 0], [4, 4, 0], [2, 2, 0], [0, 8, 0]])
    dst = src + [10.0, 0, 0]
    dst[4] = [30.0, 2, 0]  # far from where it should be
    dst[5] = [10.0, 30, 0]
    params = ConsistencyParams(consensus_resolution=1.0, min_cluster_size=3)
    clusters = group_correspondences(src, dst, params=params)
    assert len(clusters) == 1
    assert sorted(clusters[0].tolist()) == [0, 1, 2, 3]
    # the quality order decides the visit order (best first) and the order inside the cluster
    clusters = group_correspondences(src, dst, quality=[4.0, 3, 2, 1, 0.5, 0.1], params=params)
    assert clusters[0].tolist() == [3, 2, 1, 0]
    # minimum size: a 4-member cluster is rejected when 5 are needed
    big = ConsistencyParams(consensus_resolution=1.0, min_cluster_size=5)
    assert group_correspondences(src, dst, params=big) == []


def test_consistency_grouping_growth_needs_all_members():
    src = np.array([[0.0, 0, 0], [3, 0, 0], [0, 3, 0]])
    one = ConsistencyParams(consensus_resolution=1.0, min_cluster_size=3)
    # c moved off the plane: |a-c| 3 -> 3.23, |b-c| 4.24 -> 4.41, both within 1 m: one cluster of three
    dst = np.array([[0.0, 0, 0], [3, 0, 0], [0, 3, 1.2]])
    assert [sorted(c.tolist()) for c in group_correspondences(src, dst, params=one)] == [[0, 1, 2]]
    # c consistent with a (3 -> 3.35) but not with b (4.24 -> 5.41): the cluster grown from a, b leaves c out
    dst = np.array([[0.0, 0, 0], [3, 0, 0], [-1.5, 3, 0]])
    two = ConsistencyParams(consensus_resolution=1.0, min_cluster_size=2)
    assert [c.tolist() for c in group_correspondences(src, dst, params=two)] == [[0, 1]]
    assert group_correspondences(src, dst, params=one) == []


def test_consistency_grouping_paper_defaults():
    p = ConsistencyParams()
    assert p.min_cluster_size == 8 and p.consensus_resolution == 7.0
    assert ScoreParams().eps_icp == 7.0


# ---------------------------------------------------------------- score


def test_verified_score_formula():
    p = ScoreParams(inlier_scale=10.0, fitness_distance=0.5)
    assert verified_score(10, 0.8, 0.1, p) == pytest.approx((1 - np.exp(-1)) * 0.8 * 0.8)
    assert verified_score(None, 0.5, 0.25, p) == pytest.approx(0.25)
    assert verified_score(0, 0.9, 0.1, p) == 0.0
    assert verified_score(50, float("nan"), 0.1, p) == 0.0
    assert 0.0 <= verified_score(10**6, 1.0, 0.0, p) <= 1.0


# ---------------------------------------------------------------- ICP and verify on simulated scans


@pytest.fixture(scope="module")
def sim_scans():
    from placerec.sim import SimulatedSequence

    seq = SimulatedSequence("town", "os1-64", seed=0, n_scans=40)
    return seq, {i: seq[i].xyz for i in (10, 12, 13, 36)}


def test_icp_converges_within_5cm_and_the_pose_convention_holds(sim_scans):
    seq, scans = sim_scans
    T_gt = relative_pose(
        seq.poses[10], seq.poses[13]
    )  # query 13, match 10: maps query points into the match frame
    assert np.linalg.norm(T_gt[:3, 3]) > 2.0  # a real translation, so a swapped convention cannot pass
    init = _pose([0.5, -0.5, 3.0], [0.4, -0.3, 0.1]) @ T_gt
    v = verify_icp(scans[13], scans[10], init=init)
    err = np.linalg.inv(T_gt) @ v.T_match_query
    assert np.linalg.norm(err[:3, 3]) < 0.05
    assert np.rad2deg(Rotation.from_matrix(err[:3, :3]).magnitude()) < 0.5
    # T_world_query ~= T_world_match @ T_match_query
    np.testing.assert_allclose(seq.poses[10] @ v.T_match_query, seq.poses[13], atol=0.05)
    assert v.accepted and 0.0 < v.score <= 1.0 and v.inliers is None
    # the inverse direction would be wrong by twice the translation
    assert np.linalg.norm(np.linalg.inv(T_gt)[:3, 3] - v.T_match_query[:3, 3]) > 4.0


def test_verify_with_correspondences_recovers_the_pose(sim_scans):
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    rng = np.random.default_rng(8)
    q = scans[13][rng.choice(len(scans[13]), 300, replace=False)].astype(np.float64)
    q = q[np.abs(q).sum(1) > 0]
    m = _apply(T_gt, q) + rng.normal(size=q.shape) * 0.1
    bad = rng.random(len(q)) < 0.6
    m[bad] = rng.permutation(m[bad])  # 60 % wrong matches
    v = verify(scans[13], scans[10], q, m)
    err = np.linalg.inv(T_gt) @ v.T_match_query
    assert np.linalg.norm(err[:3, 3]) < 0.05
    assert v.accepted and v.inliers >= 0.3 * len(q)
    assert set(v.timings_ms) >= {"prepare", "ransac", "icp", "total"}


def test_verify_rejects_a_wrong_candidate(sim_scans):
    seq, scans = sim_scans
    # scans 10 and 36 are ~26 m apart on the route: different places; give RANSAC random correspondences
    assert np.linalg.norm(seq.poses[10][:3, 3] - seq.poses[36][:3, 3]) > 20
    rng = np.random.default_rng(9)
    q = scans[36][rng.choice(len(scans[36]), 200)].astype(np.float64)
    m = scans[10][rng.choice(len(scans[10]), 200)].astype(np.float64)
    v = verify(scans[36], scans[10], q, m)
    assert not v.accepted
    # ICP alone from the identity does not accept it either
    assert not verify_icp(scans[36], scans[10]).accepted


def test_verify_rejects_early_without_a_consistent_cluster(sim_scans):
    _, scans = sim_scans
    rng = np.random.default_rng(10)
    q, m = rng.uniform(-40, 40, (30, 3)), rng.uniform(-40, 40, (30, 3))
    params = VerifyParams(consistency={"enabled": True, "consensus_resolution": 0.5})
    v = verify(scans[13], scans[10], q, m, params=params)
    assert not v.accepted and v.rejected_at == "grouping" and v.score == 0.0


def test_verify_rejects_bad_input(sim_scans):
    _, scans = sim_scans
    with pytest.raises(ScanDataError):
        verify(scans[13], scans[10], np.zeros((5, 3)), None)
    with pytest.raises(ScanDataError):
        verify_icp(scans[13], scans[10], init=np.eye(3))
    with pytest.raises(ScanDataError):
        verify_icp(scans[13], scans[10], init=np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ScanDataError):
        verify_icp(np.zeros((5, 3)), scans[10])


@pytest.mark.parametrize(
    "icp", [{"backend": "open3d"}, {"backend": "open3d_t"}, {"backend": "small_gicp", "method": "gicp"}]
)
def test_every_icp_backend_converges(sim_scans, icp):
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    params = VerifyParams(icp=icp)
    v = verify_icp(scans[13], scans[10], init=_pose([0, 0, 2.0], [0.3, 0.2, 0.0]) @ T_gt, params=params)
    assert np.linalg.norm((np.linalg.inv(T_gt) @ v.T_match_query)[:3, 3]) < 0.05
    assert v.accepted


def test_prepared_clouds_are_reused_and_checked(sim_scans):
    from placerec.verify import as_source, as_target

    seq, scans = sim_scans
    params = VerifyParams()
    src, tgt = as_source(scans[13], params), as_target(scans[10], params)
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    v = verify_icp(src, tgt, init=T_gt, params=params)
    assert v.timings_ms["prepare"] < 5.0  # nothing prepared again
    with pytest.raises(ScanDataError):
        verify_icp(tgt, src, init=T_gt, params=params)  # roles swapped
    with pytest.raises(ScanDataError):
        verify_icp(src, tgt, params=VerifyParams(icp={"backend": "open3d"}))


def test_the_coarse_stages_run_on_the_coarser_query_grid_made_once(sim_scans, monkeypatch):
    import importlib

    from placerec.verify import as_source, as_target
    from placerec.verify.icp import coarser_source

    verify_module = importlib.import_module("placerec.verify.verify")
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    init = _pose([0.5, -0.5, 3.0], [0.4, -0.3, 0.1]) @ T_gt  # 3 m and 3 deg off: the coarse gate is needed
    params = VerifyParams(icp_only_coarse_voxel_size=3.0)
    src, tgt = as_source(scans[13], params), as_target(scans[10], params)
    seen: list[tuple[float, float]] = []  # (source voxel, gate) of every ICP run
    real_refine = verify_module.refine

    def refine(source, target, init, icp, *args, **kwargs):
        seen.append((source.voxel_size, icp.max_correspondence_distance))
        return real_refine(source, target, init, icp, *args, **kwargs)

    monkeypatch.setattr(verify_module, "refine", refine)
    v = verify_icp(src, tgt, init=init, params=params)
    assert seen == [
        (3.0, 4.0),
        (1.5, 1.0),
    ]  # the coarse gate on the 3 m grid, the pose judged on the 1.5 m one
    err = np.linalg.inv(T_gt) @ v.T_match_query
    assert v.accepted and np.linalg.norm(err[:3, 3]) < 0.05
    coarse = src.derived[3.0]
    assert 10 <= len(coarse) < len(src) / 2 and coarse.role == "source"
    verify_icp(src, tgt, init=init, params=params)  # a second candidate of the same query
    assert src.derived[3.0] is coarse  # made once
    # correspondences give a RANSAC pose: no coarse stage, the coarser grid is not used
    seen.clear()
    rng = np.random.default_rng(8)
    q = scans[13][rng.choice(len(scans[13]), 200, replace=False)].astype(np.float64)
    verify(src, tgt, q, _apply(T_gt, q), params=params)
    assert seen == [(1.5, 1.0)]
    # unset, not coarser, or too few voxels: the query's own grid
    assert coarser_source(src, None, params.icp) is src
    assert coarser_source(src, 1.0, params.icp) is src
    few = as_source(np.random.default_rng(0).uniform(0, 20, (40, 3)), params)
    assert coarser_source(few, 50.0, params.icp) is few  # 1 voxel: too few for normals
    with pytest.raises(ScanDataError, match="source"):
        coarser_source(tgt, 3.0, params.icp)
    with pytest.raises(ConfigError, match="icp_only_coarse_voxel_size"):
        VerifyParams(icp_only_coarse_voxel_size=0.0)


def test_a_coarse_stage_that_overlaps_too_little_ends_the_icp_from_a_rough_guess(sim_scans, monkeypatch):
    import importlib

    from placerec.verify import as_source, as_target

    verify_module = importlib.import_module("placerec.verify.verify")
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    near = _pose([0.5, -0.5, 3.0], [0.4, -0.3, 0.1]) @ T_gt  # a guess the coarse gate brings home
    far = _pose([0.0, 0.0, 180.0], [60.0, 40.0, 0.0]) @ T_gt  # turned round, 70 m away: nothing overlaps
    plain = VerifyParams(icp_only_coarse_voxel_size=3.0)
    floored = VerifyParams(icp_only_coarse_voxel_size=3.0, icp_only_min_coarse_fitness=0.05)
    src, tgt = as_source(scans[13], plain), as_target(scans[10], plain)
    gates: list[float] = []
    real_refine = verify_module.refine

    def refine(source, target, init, icp, *args, **kwargs):
        gates.append(icp.max_correspondence_distance)
        return real_refine(source, target, init, icp, *args, **kwargs)

    monkeypatch.setattr(verify_module, "refine", refine)
    # overlapping from the coarse stage on: the floor changes nothing
    a, b = verify_icp(src, tgt, init=near, params=plain), verify_icp(src, tgt, init=near, params=floored)
    assert b.accepted and b.score == a.score and np.array_equal(b.T_match_query, a.T_match_query)
    # nothing within score.fitness_distance after the coarse stage: rejected there, the fine stage never runs
    gates.clear()
    v = verify_icp(src, tgt, init=far, params=floored)
    assert gates == [4.0] and not v.accepted and v.score == 0.0 and v.rejection == "coarse_fitness"
    assert v.fitness < 0.05 and v.icp_iterations >= 0 and "icp" in v.timings_ms
    gates.clear()
    assert verify_icp(src, tgt, init=far, params=plain).rejection != "coarse_fitness" and gates == [4.0, 1.0]
    # matches posing the candidate: no coarse stage, no floor
    rng = np.random.default_rng(8)
    q = scans[13][rng.choice(len(scans[13]), 200, replace=False)].astype(np.float64)
    assert verify(src, tgt, q, _apply(T_gt, q), params=floored).accepted
    with pytest.raises(ConfigError, match="icp_only_min_coarse_fitness"):
        VerifyParams(icp_only_min_coarse_fitness=1.5)


def test_the_fine_stages_follow_the_icp_from_a_rough_guess(sim_scans, monkeypatch):
    import importlib

    from placerec.verify import as_source, as_target

    verify_module = importlib.import_module("placerec.verify.verify")
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    init = _pose([0.5, -0.5, 3.0], [0.4, -0.3, 0.1]) @ T_gt
    plain = VerifyParams(icp_only_coarse_voxel_size=3.0, icp={"max_iterations": 3})
    fine = plain.model_copy(update={"icp_only_fine_distances": [0.5, 0.3]})
    src, tgt = as_source(scans[13], plain), as_target(scans[10], plain)
    runs: list[tuple[float, np.ndarray, np.ndarray]] = []  # (gate, start, result) of every ICP run
    real_refine = verify_module.refine

    def refine(source, target, init, icp, *args, **kwargs):
        out = real_refine(source, target, init, icp, *args, **kwargs)
        runs.append((icp.max_correspondence_distance, init, out.T))
        return out

    monkeypatch.setattr(verify_module, "refine", refine)
    a = verify_icp(src, tgt, init=init, params=plain)
    assert [g for g, _, _ in runs] == [4.0, 1.0]
    runs.clear()
    b = verify_icp(src, tgt, init=init, params=fine)
    # the same stages, then the tighter gates, each from the last pose; the last one's pose is judged
    assert [g for g, _, _ in runs] == [4.0, 1.0, 0.5, 0.3]
    assert np.array_equal(runs[1][2], a.T_match_query)
    assert np.array_equal(runs[2][1], runs[1][2]) and np.array_equal(runs[3][1], runs[2][2])
    assert np.array_equal(b.T_match_query, runs[3][2])

    def error(T: np.ndarray) -> float:
        return float(np.linalg.norm((np.linalg.inv(T_gt) @ T)[:3, 3]))

    # three iterations a stage leave the pose short of home; the stages after it bring it closer
    assert error(b.T_match_query) < error(a.T_match_query)
    assert b.timings_ms["icp"] > 0 and b.timings_ms["total"] >= b.timings_ms["icp"]
    # a pose from matches has no fine stages
    runs.clear()
    rng = np.random.default_rng(8)
    q = scans[13][rng.choice(len(scans[13]), 200, replace=False)].astype(np.float64)
    verify(src, tgt, q, _apply(T_gt, q), params=fine)
    assert [g for g, _, _ in runs] == [1.0]
    for bad in ([0.0], [0.5, -1.0], [float("nan")]):
        with pytest.raises(ConfigError, match="icp_only_fine_distances"):
            VerifyParams(icp_only_fine_distances=bad)


def test_eps_icp_acceptance_rule(sim_scans):
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    paper = VerifyParams(score={"acceptance": "eps_icp"})
    good = verify_icp(scans[13], scans[10], init=T_gt, params=paper)
    assert good.accepted and good.residual < 7.0
    bad = verify_icp(scans[36], scans[10], params=paper)
    assert not bad.accepted and bad.residual >= 7.0
    strict = VerifyParams(score={"acceptance": "eps_icp", "eps_icp": good.residual * 0.5})
    assert not verify_icp(scans[13], scans[10], init=T_gt, params=strict).accepted


def test_min_fitness_gates_every_acceptance_rule(sim_scans):
    from placerec.verify.score import is_accepted

    p = ScoreParams(acceptance="eps_icp", min_fitness=0.7)
    assert is_accepted(0.0, 1.0, p, fitness=0.7) and not is_accepted(0.0, 1.0, p, fitness=0.69)
    assert not is_accepted(0.0, 1.0, p) and not is_accepted(0.0, 1.0, p, fitness=float("nan"))
    assert not is_accepted(0.0, 8.0, p, fitness=0.9)  # eps_ICP still applies
    by_score = ScoreParams(acceptance="score", min_score=0.25, min_fitness=0.5)
    assert is_accepted(0.3, 99.0, by_score, fitness=0.5) and not is_accepted(0.3, 99.0, by_score, fitness=0.4)
    assert is_accepted(0.0, 1.0, ScoreParams(acceptance="eps_icp"))  # off by default
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    good = verify_icp(scans[13], scans[10], init=T_gt, params=VerifyParams(score={"acceptance": "eps_icp"}))
    gated = VerifyParams(score={"acceptance": "eps_icp", "min_fitness": min(1.0, good.fitness + 0.01)})
    again = verify_icp(scans[13], scans[10], init=T_gt, params=gated)
    assert good.accepted and not again.accepted and again.fitness == pytest.approx(good.fitness)
    with pytest.raises(ValueError):
        ScoreParams(min_fitness=1.5)


def test_rejection_names_the_rule_that_rejected():
    from placerec.types import REJECTIONS
    from placerec.verify.score import is_accepted, rejection

    score = ScoreParams(acceptance="score", min_score=0.25)
    assert rejection(0.3, 99.0, score) is None and rejection(0.2, 1.0, score) == "score"
    eps = ScoreParams(acceptance="eps_icp", eps_icp=7.0)
    assert rejection(0.0, 1.0, eps) is None and rejection(0.9, 8.0, eps) == "residual"
    both = ScoreParams(acceptance="both", min_score=0.25, eps_icp=7.0)
    assert rejection(0.2, 1.0, both) == "score" and rejection(0.3, 8.0, both) == "residual"
    gated = ScoreParams(min_fitness=0.5)
    assert rejection(0.9, 1.0, gated, fitness=0.4) == "fitness"
    for args in [(0.3, 99.0, score), (0.2, 1.0, score), (0.9, 8.0, eps), (0.9, 1.0, gated, 0.4)]:
        assert is_accepted(*args) == (rejection(*args) is None)
    pinned = ScoreParams(min_constraint=0.05)
    assert rejection(0.9, 1.0, pinned, constraint=0.04) == "constraint"
    assert rejection(0.9, 1.0, pinned, constraint=float("nan")) == "constraint"
    assert rejection(0.9, 1.0, pinned, constraint=0.05) is None
    assert rejection(0.9, 1.0, score, constraint=0.0) is None  # off by default
    ratio = ScoreParams(min_fitness_ratio=0.7, expected_fitness=0.8, expected_fitness_length_m=10.0)
    assert rejection(0.9, 1.0, ratio, fitness=0.55, displacement=0.0) == "fitness_ratio"  # 0.55 < 0.7 * 0.8
    assert rejection(0.9, 1.0, ratio, fitness=0.55, displacement=1.0) is None  # 0.7 * 0.8 * e^-0.1 = 0.507
    assert (
        rejection(0.9, 1.0, ratio, fitness=0.55) == "fitness_ratio"
    )  # no displacement: not judged, rejected
    assert rejection(0.9, 1.0, ratio, fitness=float("nan"), displacement=1.0) == "fitness_ratio"
    assert rejection(0.9, 1.0, score, fitness=0.0, displacement=0.0) is None  # off by default
    assert {
        "grouping",
        "ransac",
        "rank",
        "coarse_fitness",
        "fitness",
        "fitness_ratio",
        "constraint",
        "score",
        "residual",
        "guided_score",  # candidates verified from guided matches (tests/test_guided_matching.py)
    } == set(REJECTIONS)


def test_expected_fitness_falls_exponentially_with_the_displacement():
    from placerec.verify.score import expected_fitness

    p = ScoreParams(expected_fitness=0.75, expected_fitness_length_m=17.5)
    assert expected_fitness(0.0, p) == pytest.approx(0.75)
    assert expected_fitness(17.5, p) == pytest.approx(0.75 / np.e)
    assert expected_fitness(35.0, p) == pytest.approx(0.75 * np.exp(-2.0))
    assert expected_fitness(-1.0, p) == pytest.approx(0.75)  # a length, never negative
    with pytest.raises(ValueError):
        ScoreParams(min_fitness_ratio=0.0)
    with pytest.raises(ValueError):
        ScoreParams(expected_fitness_length_m=float("inf"))


def test_min_fitness_ratio_judges_the_verified_poses_displacement(sim_scans):
    """The gate of `complete` uses the translation of the pose ICP verified: scans 3 m apart pass a curve that
    falls over centimetres and fail one that stays at its d = 0 value, whatever the score."""
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    d = float(np.linalg.norm(T_gt[:3, 3]))
    assert d > 2.0
    good = verify_icp(scans[13], scans[10], init=T_gt)
    assert good.accepted and 0.3 < good.fitness < 1.0
    f0 = min(1.0, good.fitness / 0.9 + 0.01)  # 0.9 * f0 just above the fitness reached
    short = VerifyParams(
        score={"min_fitness_ratio": 0.9, "expected_fitness": f0, "expected_fitness_length_m": 0.05}
    )
    long = VerifyParams(
        score={"min_fitness_ratio": 0.9, "expected_fitness": f0, "expected_fitness_length_m": 1e6}
    )
    a = verify_icp(scans[13], scans[10], init=T_gt, params=short)
    b = verify_icp(scans[13], scans[10], init=T_gt, params=long)
    assert a.accepted and a.rejection is None
    assert not b.accepted and b.rejection == "fitness_ratio" and b.score == pytest.approx(good.score)


def test_normal_spread_is_the_least_constrained_direction():
    from placerec.verify.icp import normal_spread

    axes = np.eye(3)
    assert normal_spread(np.repeat(axes, 5, axis=0)) == pytest.approx(1 / 3)
    # road and one facade: nothing along the street (y), scaled and zero normals do not count
    corridor = np.array([[0, 0, 2.0], [0, 0, 1.0], [1.0, 0, 0], [0, 0, 0]])
    assert normal_spread(corridor) == pytest.approx(0.0, abs=1e-12)
    # 10 road, 10 facade and 1 cross-wall normal: the street direction holds 1/21 of them
    assert normal_spread(np.repeat(axes[[2, 0, 1]], [10, 10, 1], axis=0)) == pytest.approx(1 / 21)
    # a normal in the y-z plane adds nothing along the direction of that plane orthogonal to it
    tilted = np.array([[0, np.sin(0.1), np.cos(0.1)], [1.0, 0, 0]])
    assert normal_spread(tilted) == pytest.approx(0.0, abs=1e-12)
    assert normal_spread(np.zeros((0, 3))) == 0.0


def _rect(fixed_axis: int, value: float, lo, hi, step: float = 0.2) -> np.ndarray:
    """Points on a grid over the rectangle [lo, hi] of the two other axes, at ``value`` on ``fixed_axis``."""
    u, v = (np.arange(lo[i], hi[i] + 1e-9, step) for i in range(2))
    g = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    return np.insert(g, fixed_axis, value, axis=1)


def test_a_corridor_leaves_icp_free_and_min_constraint_rejects_it():
    """Road and one wall along y: ICP aligns it anywhere along the street with a perfect fit; with a cross wall
    the overlap pins every direction down."""
    road = _rect(2, 0.0, (-5, -10), (5, 10))
    wall = _rect(0, 5.0, (-10, 0), (10, 5))
    cross = _rect(1, 8.0, (-5, 0), (5, 5))
    shifted = _pose([0, 0, 0], [0, 3.0, 0])  # the query taken 3 m further along the street
    params = VerifyParams(score={"min_constraint": 0.05}, icp_only_coarse_distances=[])
    corridor = np.concatenate([road, wall])
    v = verify_icp(corridor, corridor, init=shifted, params=params)
    assert (
        v.fitness > 0.8 and v.constraint < 0.01 and abs(v.T_match_query[1, 3] - 3.0) < 0.3
    )  # left where it was
    assert not v.accepted and v.rejection == "constraint"
    assert verify_icp(
        corridor, corridor, init=shifted, params=VerifyParams(icp_only_coarse_distances=[])
    ).accepted
    box = np.concatenate([road, wall, cross])
    w = verify_icp(box, box, init=_pose([0, 0, 0], [0, 0.3, 0]), params=params)
    assert w.constraint > 0.05 and w.accepted and abs(w.T_match_query[1, 3]) < 0.05
    assert "constraint" in w.as_dict() and "constraint" not in verify_icp(box, box).as_dict()
    for backend in ("open3d", "open3d_t"):  # every backend's target normals
        other = VerifyParams(
            score={"min_constraint": 0.05}, icp={"backend": backend}, icp_only_coarse_distances=[]
        )
        assert verify_icp(corridor, corridor, init=shifted, params=other).rejection == "constraint"
        assert verify_icp(box, box, params=other).constraint > 0.05


def test_a_rejected_verification_says_at_which_stage(sim_scans):
    from placerec.verify.verify import hypothesise

    seq, scans = sim_scans
    few = hypothesise(np.zeros((2, 3)), np.zeros((2, 3)))
    assert few.rejected().rejection == "grouping" and few.rejected("rank").rejection == "rank"
    bad = verify_icp(scans[36], scans[10], params=VerifyParams())
    assert not bad.accepted and bad.rejection == "score"


def _greedy_reference(src, dst, order, res, min_size):
    """PCL's clustering written plainly (members checked one by one), for comparison."""
    n = len(src)
    taken = np.zeros(n, dtype=bool)
    clusters = []
    for seed in order:
        if taken[seed]:
            continue
        members = [seed]
        for j in order:
            if j == seed or taken[j]:
                continue
            if all(
                abs(np.linalg.norm(src[j] - src[k]) - np.linalg.norm(dst[j] - dst[k])) <= res for k in members
            ):
                members.append(j)
        if len(members) >= min_size:
            taken[members] = True
            clusters.append(members)
    return sorted((sorted(c) for c in clusters), key=lambda c: (-len(c), c))


def test_consistency_grouping_matches_a_plain_reference():
    from placerec.verify import consistency_matrix

    rng = np.random.default_rng(11)
    src = rng.uniform(-20, 20, (90, 3))
    dst = src + [5.0, -3.0, 0.0]
    dst[30:] = rng.uniform(-20, 20, (60, 3))  # two thirds wrong
    q = rng.random(90)
    q[:30] *= 0.3  # true matches tend to have the better descriptor distances
    ok = consistency_matrix(src, dst, 3.0)
    brute = np.abs(
        np.linalg.norm(src[:, None] - src[None], axis=2) - np.linalg.norm(dst[:, None] - dst[None], axis=2)
    )
    np.testing.assert_array_equal(ok, brute <= 3.0)
    params = ConsistencyParams(consensus_resolution=3.0, min_cluster_size=4)
    got = group_correspondences(src, dst, quality=q, params=params)
    want = _greedy_reference(src, dst, np.argsort(q, kind="stable"), 3.0, 4)
    assert sorted((sorted(c.tolist()) for c in got), key=lambda c: (-len(c), c)) == want
    assert len(set(range(30)) & set(got[0].tolist())) >= 28  # the true matches form the largest cluster


def test_verify_with_grouping_reports_the_inlier_mask(sim_scans):
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    rng = np.random.default_rng(12)
    q = scans[13][np.abs(scans[13]).sum(1) > 0][::200].astype(np.float64)[:200]
    m = _apply(T_gt, q) + rng.normal(size=q.shape) * 0.05
    bad = rng.random(len(q)) < 0.5
    m[bad] = rng.uniform(-30, 30, (int(bad.sum()), 3))
    v = verify(scans[13], scans[10], q, m, params=VerifyParams(consistency={"enabled": True}))
    assert v.accepted and v.inlier_mask.shape == (len(q),)
    assert v.inlier_mask.sum() == v.inliers
    assert (v.inlier_mask & bad).sum() <= 2 and v.inlier_mask[~bad].mean() > 0.9


def test_icp_only_from_a_yaw_only_guess_converges(sim_scans):
    # Scan Context gives a yaw and no translation: the guess is ~3 m off; the coarse stage brings it in
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    init = np.eye(4)
    init[:3, :3] = T_gt[:3, :3]
    assert np.linalg.norm(T_gt[:3, 3]) > 2.5
    v = verify_icp(scans[13], scans[10], init=init)
    assert np.linalg.norm((np.linalg.inv(T_gt) @ v.T_match_query)[:3, 3]) < 0.05
    assert v.accepted
    with pytest.raises(ConfigError):
        VerifyParams(icp_only_coarse_distances=[0.0])


def test_a_lazy_match_is_prepared_only_when_icp_runs(sim_scans):
    seq, scans = sim_scans
    calls = []

    def match(which):
        def get():
            calls.append(which)
            return scans[which]

        return get

    rng = np.random.default_rng(11)
    q, m = rng.uniform(-40, 40, (40, 3)), rng.uniform(-40, 40, (40, 3))
    v = verify(scans[13], match(10), q, m)  # random pairs: RANSAC ends it
    assert v.rejected_at == "ransac" and calls == []
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    eager = verify_icp(scans[13], scans[10], init=T_gt)
    lazy = verify_icp(scans[13], match(10), init=T_gt)
    assert calls == [10]
    np.testing.assert_allclose(lazy.T_match_query, eager.T_match_query, atol=1e-9)


def test_icp_top_k_refines_only_the_candidates_with_most_inliers(sim_scans):
    from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, verify_candidates

    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    rng = np.random.default_rng(12)
    q = scans[13][rng.choice(len(scans[13]), 200, replace=False)].astype(np.float64)
    m = _apply(T_gt, q) + rng.normal(size=q.shape) * 0.05
    store = CloudStore()
    prepared = []
    for sid in (10, 36):
        store.add(sid, scans[sid])
    store_target = store.target
    store.target = lambda sid: prepared.append(sid) or store_target(sid)
    # entry 10 twice: with 50 % wrong pairs (fewer inliers, retrieved first) and with all pairs right
    half = m.copy()
    half[:100] = rng.permutation(half[:100])
    retrieved = [Retrieved(10, 0.9, q, half), Retrieved(10, 0.8, q, m), Retrieved(36, 0.7, q, m)]
    params = VerifiedParams(top_k=3, icp_top_k=1)
    cands = verify_candidates(scans[13], retrieved, store, params, query_id=13)
    # entry 36 gets the right pairs too: RANSAC finds the same pose, so inliers tie with the second; the ICP
    # goes to the candidate with the most inliers, the first of equal ones in retrieval order
    assert prepared == [10]
    best = cands[0]
    assert best.accepted and best.retrieval_score == 0.8 and best.inliers >= 190
    others = [c.verification.rejected_at for c in cands[1:]]
    assert others == ["rank", "rank"] and all(c.score == 0.0 for c in cands[1:])
    # without the cap every candidate that passes RANSAC is refined
    prepared.clear()
    cands = verify_candidates(scans[13], retrieved, store, VerifiedParams(top_k=3), query_id=13)
    assert sorted(prepared) == [10, 10, 36]
    assert [c.match_id for c in cands if c.accepted][:2] == [10, 10]


def test_verify_ms_of_candidates_not_returned_is_shared_by_those_returned(sim_scans, monkeypatch):
    import placerec.verify.candidates as vc

    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    rng = np.random.default_rng(13)
    q = scans[13][rng.choice(len(scans[13]), 100, replace=False)].astype(np.float64)
    m = _apply(T_gt, q)
    retrieved = [vc.Retrieved(10, 0.9, q, m), vc.Retrieved(36, 0.8, q, m), vc.Retrieved(36, 0.7)]

    def run(k):
        store = vc.CloudStore()  # a new one: nothing prepared yet, so both runs do the same work
        for sid in (10, 36):
            store.add(sid, scans[sid])
        clock = iter(np.arange(0.0, 10.0, 0.001))  # every reading 1 ms after the previous one
        monkeypatch.setattr(vc.time, "perf_counter", lambda: next(clock))
        return vc.verify_candidates(scans[13], retrieved, store, vc.VerifiedParams(top_k=3), 13, k)

    every = run(None)
    assert len(every) == 3
    one = run(1)
    assert len(one) == 1 and one[0].match_id == 10
    total = sum(c.verify_ms for c in every)
    assert one[0].verify_ms == pytest.approx(total)


def test_a_candidate_a_gate_rejects_scores_zero_and_ranks_below_an_accepted_one(sim_scans):
    """With score acceptance, a candidate rejected by an overlap gate keeps no score (its score would pass a
    threshold it was not accepted at): the accepted candidate ranks first even with the lower verified score."""
    from placerec.verify.candidates import CloudStore, Retrieved, VerifiedParams, verify_candidates

    seq, scans = sim_scans
    rng = np.random.default_rng(14)
    q = scans[13][rng.choice(len(scans[13]), 200, replace=False)].astype(np.float64)
    store = CloudStore()
    for sid in (10, 12):
        store.add(sid, scans[sid])
    far = _apply(relative_pose(seq.poses[10], seq.poses[13]), q)  # 3 m away, every pair right
    near = _apply(relative_pose(seq.poses[12], seq.poses[13]), q[:10])  # 1 m away, 10 pairs
    retrieved = [Retrieved(10, 0.9, q, far), Retrieved(12, 0.8, q[:10], near)]
    plain = verify_candidates(scans[13], retrieved, store, VerifiedParams(top_k=2), query_id=13)
    a, b = sorted(plain, key=lambda c: c.match_id)
    assert a.accepted and b.accepted and a.score > b.score  # more inliers...
    fa, fb = a.verification.fitness, b.verification.fitness
    assert fa < fb  # ... less overlap
    gated = VerifiedParams(top_k=2, score={"min_fitness": (fa + fb) / 2})
    cands = verify_candidates(scans[13], retrieved, store, gated, query_id=13)
    assert [c.match_id for c in cands] == [12, 10]
    assert cands[0].accepted and cands[0].score == pytest.approx(b.score)
    assert not cands[1].accepted and cands[1].verification.rejection == "fitness" and cands[1].score == 0.0
    assert cands[1].verification.score == pytest.approx(a.score)  # the verification keeps what it measured
    # rejected for its score alone, a candidate keeps it (below min_score): the PR curve stays continuous
    strict = VerifiedParams(top_k=2, score={"min_score": (a.score + b.score) / 2})
    low = {c.match_id: c for c in verify_candidates(scans[13], retrieved, store, strict, query_id=13)}
    assert low[10].accepted and not low[12].accepted and low[12].score == pytest.approx(b.score)


def test_an_accepted_pose_is_refined_on_a_finer_query_grid_and_nothing_else_changes(sim_scans, monkeypatch):
    import importlib

    from placerec.verify import as_source, as_target
    from placerec.verify.icp import finer_source

    verify_module = importlib.import_module("placerec.verify.verify")
    seq, scans = sim_scans
    T_gt = relative_pose(seq.poses[10], seq.poses[13])
    init = _pose([0.5, -0.5, 2.0], [0.3, -0.2, 0.1]) @ T_gt

    def error_cm(T: np.ndarray) -> float:
        return float(np.linalg.norm((np.linalg.inv(T_gt) @ T)[:3, 3]) * 100)

    judged = verify_icp(scans[13], scans[10], init=init)
    params = VerifyParams(refine={"enabled": True})
    src, tgt = as_source(scans[13], params), as_target(scans[10], params)
    seen: list[tuple[float, str, float]] = []  # (source voxel, method, gate) of every ICP run
    real_refine = verify_module.refine

    def refine(source, target, init, icp, *args, **kwargs):
        seen.append((source.voxel_size, icp.method, icp.max_correspondence_distance))
        return real_refine(source, target, init, icp, *args, **kwargs)

    monkeypatch.setattr(verify_module, "refine", refine)
    refined = verify_icp(src, tgt, init=init, params=params)
    # the judged ICP on the query's 1.5 m grid, then GICP with the query on its 1.0 m grid
    assert seen[-2:] == [(1.5, "plane", 1.0), (1.0, "gicp", 0.5)]
    assert judged.accepted and refined.accepted
    assert error_cm(refined.T_match_query) < 0.5 * error_cm(judged.T_match_query)
    assert error_cm(refined.T_match_query) < 1.0
    assert (
        error_cm(
            verify_icp(
                src, tgt, init=init, params=VerifyParams(refine={"enabled": True, "voxel_size": 0.4})
            ).T_match_query
        )
        < 1.0
    )
    # the decision and its statistics are the judged ICP's
    assert (refined.score, refined.fitness, refined.rmse) == (judged.score, judged.fitness, judged.rmse)
    assert refined.timings_ms["refine"] > 0 and "refine" not in judged.timings_ms
    fine = src.derived[1.0]
    assert fine.role == "source" and len(fine) > 1.5 * len(src)
    verify_icp(src, tgt, init=init, params=params)  # another candidate of the same query
    assert src.derived[1.0] is fine and finer_source(src, 1.0, params.icp) is fine  # made once
    assert finer_source(src, 2.0, params.icp) is src  # not finer
    # never finer than the match's grid
    seen.clear()
    verify_icp(src, tgt, init=init, params=VerifyParams(refine={"enabled": True, "voxel_size": 0.1}))
    assert seen[-1][0] == 0.4
    with pytest.raises(ScanDataError, match="source"):
        finer_source(tgt, 0.4, params.icp)
    # a refinement that moves the pose farther than max_shift is not used
    capped = verify_icp(src, tgt, init=init, params=VerifyParams(refine={"enabled": True, "max_shift": 1e-9}))
    np.testing.assert_array_equal(capped.T_match_query, judged.T_match_query)
    # a rejected candidate is not refined
    seen.clear()
    strict = VerifyParams(refine={"enabled": True}, score={"min_score": 1.0})
    rejected = verify_icp(src, tgt, init=init, params=strict)
    assert not rejected.accepted and "refine" not in rejected.timings_ms and seen[-1][1] == "plane"
    with pytest.raises(ConfigError, match="refine.method"):
        VerifyParams(icp={"backend": "open3d"}, refine={"enabled": True})
