"""Pose errors of loop closures and pose-based localisation success, on hand-made poses with known errors."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from placerec.errors import ScanDataError
from placerec.eval import (
    ExclusionWindow,
    closure_pose_errors,
    error_stats,
    full_pose_mask,
    localization_metrics,
    loop_ground_truth,
    loop_metrics,
    pose_errors,
)
from placerec.types import relative_pose


def pose(xyz=(0.0, 0.0, 0.0), rpy_deg=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    T[:3, 3] = xyz
    return T


def test_pose_errors_of_known_transforms():
    gt = pose((1.0, 2.0, 3.0), (0, 0, 30))
    est = pose((1.3, 2.4, 3.0), (10, 0, 30))  # 0.5 m off; 10 deg about x on top of the yaw
    near_flip = pose((1.0, 2.0, 3.0), (0, 0, 30 + 179.9))
    t, r = pose_errors(np.stack([gt, est, near_flip, np.full((4, 4), np.nan)]), np.stack([gt] * 4))
    np.testing.assert_allclose(t[:3], [0.0, 0.5, 0.0], atol=1e-12)
    # R_gt^T R_est: gt's yaw, then 10 deg about x (extrinsic xyz: roll applied first) -> angle 10 deg
    np.testing.assert_allclose(r[:3], [0.0, 10.0, 179.9], atol=1e-9)
    assert np.isnan(t[3]) and np.isnan(r[3])
    one_t, one_r = pose_errors(est, gt)  # a single 4x4 is one row
    assert one_t.shape == (1,) and one_t[0] == pytest.approx(0.5) and one_r[0] == pytest.approx(10.0)
    tiny = pose_errors(pose(rpy_deg=(0, 1e-7, 0)), np.eye(4))[1][0]
    assert tiny == pytest.approx(1e-7, rel=1e-6)  # exact near 0 (arccos of the trace would give 0 or 1e-6)
    with pytest.raises(ScanDataError):
        pose_errors(np.eye(4)[None].repeat(2, 0), np.eye(4)[None])
    with pytest.raises(ScanDataError):
        pose_errors(np.eye(4), np.full((4, 4), np.nan))


def test_full_pose_mask_skips_orientation_only_and_missing_poses():
    P = np.stack([pose((0.1, 0, 0)), pose(rpy_deg=(0, 0, 40)), np.full((4, 4), np.nan), pose((0, 0, -2))])
    assert full_pose_mask(P).tolist() == [True, False, False, True]


def test_error_stats():
    s = error_stats(np.array([0.1, np.nan, 0.2, 0.4]))
    assert s == pytest.approx({"median": 0.2, "p95": 0.2 + 0.9 * 0.2, "max": 0.4})
    assert all(np.isnan(v) for v in error_stats(np.array([np.nan])).values())


def loop_world():
    """Scans 0..4 100 m apart, 5..9 revisit scan i-5 from 1 m further on with a 90 deg turn; 10, 11 far away."""
    x = np.r_[np.arange(5) * 100.0, np.arange(5) * 100.0 + 1.0, 1000.0, 2000.0]
    P = np.stack([pose((xi, 0.0, 0.0), (0, 0, 90.0 if i >= 5 else 0.0)) for i, xi in enumerate(x)])
    return P, loop_ground_truth(P, gt_distance=5.0, exclusion=ExclusionWindow(frames=5))


Q = [5, 6, 7, 8, 9, 10, 11]
M = [0, 0, 2, -1, 4, 1, 3]  # correct, wrong (revisit), correct, none, correct, wrong, wrong
S = [0.9, 0.8, 0.7, np.nan, 0.3, 0.6, 0.7]  # max F1 at threshold 0.3 (tests/test_eval_metrics.py)


def hand_relative_poses(P):
    """Top-candidate poses with known errors: q5 0.1 m, q7 0.2 m and 2 deg, q9 none; the false q6 a pose 0.5 m
    from its own scan (100.5 m from the truth); q10, q11 orientation-only."""
    R = np.full((len(Q), 4, 4), np.nan)
    R[0] = relative_pose(P[0], P[5]) @ pose((0.1, 0, 0))
    R[1] = pose((0.5, 0, 0))
    R[2] = relative_pose(P[2], P[7]) @ pose((0, 0.2, 0), (0, 0, 2))
    R[5] = R[6] = pose(rpy_deg=(0, 0, 90))
    return R


def test_closure_pose_errors_at_the_operating_threshold():
    P, gt = loop_world()
    m = loop_metrics(Q, M, S, gt)
    assert m.threshold_at_max_f1 == pytest.approx(0.3)
    e = closure_pose_errors(m, hand_relative_poses(P), P)
    np.testing.assert_allclose(e.translation_m, [0.1, 100.5, 0.2, np.nan, np.nan, np.nan, np.nan], atol=1e-9)
    np.testing.assert_allclose(e.rotation_deg, [0, 90, 2, np.nan, np.nan, np.nan, np.nan], atol=1e-9)
    s = e.summary()
    assert (s["threshold"], s["n_tp"], s["n_tp_with_pose"]) == (0.3, 3, 2)
    assert s["tp_translation_m"] == pytest.approx({"median": 0.15, "p95": 0.195, "max": 0.2})
    assert s["tp_rotation_deg"] == pytest.approx({"median": 1.0, "p95": 1.9, "max": 2.0})
    # every accepted closure counts for the worst error, the false q6 included; q10, q11 have no 6-DoF pose
    assert (s["n_accepted"], s["n_accepted_with_pose"]) == (6, 3)
    assert s["accepted_max_translation_m"] == pytest.approx(100.5)
    assert s["accepted_max_rotation_deg"] == pytest.approx(90.0)  # q6's pose lacks the 90 deg turn


def test_closure_pose_errors_at_a_given_threshold_and_without_poses():
    P, gt = loop_world()
    m = loop_metrics(Q, M, S, gt)
    high = closure_pose_errors(m, hand_relative_poses(P), P, threshold=0.85).summary()
    assert (high["n_tp"], high["n_accepted"], high["accepted_max_translation_m"]) == (
        1,
        1,
        pytest.approx(0.1),
    )
    assert high["tp_translation_m"]["median"] == pytest.approx(0.1)
    yaw_only = np.stack([pose(rpy_deg=(0, 0, 90))] * len(Q))  # e.g. Scan Context before verification
    s = closure_pose_errors(m, yaw_only, P).summary()
    assert (s["n_tp"], s["n_tp_with_pose"], s["n_accepted_with_pose"]) == (3, 0, 0)
    assert np.isnan(s["tp_translation_m"]["median"]) and np.isnan(s["accepted_max_translation_m"])
    none = loop_metrics(Q, [-1] * 7, [np.nan] * 7, gt)  # no candidate: no threshold, nothing accepted
    s = closure_pose_errors(none, np.full((7, 4, 4), np.nan), P).summary()
    assert (s["n_accepted"], s["n_tp"]) == (0, 0) and np.isnan(s["threshold"])
    with pytest.raises(ScanDataError, match="relative poses for 7"):
        closure_pose_errors(m, yaw_only[:3], P)


def test_the_inverse_convention_is_caught():
    """T_query_match instead of T_match_query: with a turn and an offset between the scans, a large error."""
    P, gt = loop_world()
    m = loop_metrics([5], [0], [1.0], gt)
    right = closure_pose_errors(m, relative_pose(P[0], P[5])[None], P).summary()
    wrong = closure_pose_errors(m, np.linalg.inv(relative_pose(P[0], P[5]))[None], P).summary()
    assert right["tp_translation_m"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert right["tp_rotation_deg"]["max"] == pytest.approx(0.0, abs=1e-6)
    assert wrong["tp_rotation_deg"]["max"] == pytest.approx(180.0)  # +90 against -90 deg
    assert wrong["tp_translation_m"]["max"] == pytest.approx(np.sqrt(2.0))  # (1, 0) against (0, 1)


def test_localization_success_from_estimated_poses_and_fine_success():
    truth = np.stack([pose((10.0 * i, 0, 0), (0, 0, 45)) for i in range(5)])
    est = np.stack(
        [
            truth[0] @ pose((0.5, 0, 0), (0, 0, 3)),  # 0.5 m, 3 deg: fine
            truth[1] @ pose((0.5, 0, 0), (0, 0, 6)),  # 0.5 m, 6 deg: success, not fine
            truth[2] @ pose((2.0, 0, 0), (0, 0, 1)),  # 2 m: success, not fine
            truth[3] @ pose((0, 3.5, 0)),  # 3.5 m: failure
            np.full((4, 4), np.nan),  # no estimate
        ]
    )
    m = localization_metrics(est, truth, success_distance=3.0, basis="pose")
    np.testing.assert_allclose(m.errors, [0.5, 0.5, 2.0, 3.5, np.inf])
    np.testing.assert_allclose(m.rotation_errors, [3, 6, 1, 0, np.nan], atol=1e-9)
    assert m.success.tolist() == [True, True, True, False, False]
    assert m.fine_success.tolist() == [True, False, False, False, False]
    assert (m.success_rate, m.fine_success_rate, m.median_rotation_error) == pytest.approx((0.6, 0.2, 2.0))
    s = m.summary()
    assert (s["success_basis"], s["fine_distance"], s["fine_rotation_deg"]) == ("pose", 1.0, 5.0)
    retrieval = localization_metrics(est, truth, basis="retrieval")
    assert retrieval.success.tolist() == m.success.tolist() and retrieval.fine_success is None
    assert np.isnan(retrieval.fine_success_rate) and retrieval.summary()["success_basis"] == "retrieval"
    with pytest.raises(ScanDataError, match="basis"):
        localization_metrics(est, truth, basis="guess")
    with pytest.raises(ScanDataError, match="must be > 0"):
        localization_metrics(est, truth, fine_rotation_deg=0.0)
