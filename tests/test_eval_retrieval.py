"""Retrieval recall@1 / @1% and the same- / reverse-direction split (`placerec.eval.retrieval`) on hand-made
trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from placerec.eval import (
    ExclusionWindow,
    direction_summary,
    loop_ground_truth,
    loop_metrics,
    retrieval_metrics,
    revisit_directions,
)


def _poses(xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    P = np.tile(np.eye(4), (len(xy), 1, 1))
    P[:, 0, 0] = P[:, 1, 1] = np.cos(yaw)
    P[:, 1, 0], P[:, 0, 1] = np.sin(yaw), -np.sin(yaw)
    P[:, :2, 3] = xy
    return P


def _out_and_back_then_again() -> np.ndarray:
    """0..99: east along y=0; 100..199: back west along y=2 (reverse revisits); 200..299: east again along y=0
    (same-direction revisits of 0..99)."""
    x = np.arange(100, dtype=float)
    xy = np.concatenate([np.c_[x, 0 * x], np.c_[x[::-1], 0 * x + 2], np.c_[x, 0 * x]])
    yaw = np.concatenate([0 * x, 0 * x + np.pi, 0 * x])
    return _poses(xy, yaw)


def test_directions_of_hand_made_revisits():
    gt = loop_ground_truth(_out_and_back_then_again(), gt_distance=5.0, exclusion=ExclusionWindow(frames=30))
    d = revisit_directions(gt)
    # the first way back: reverse once scans 0.. are out of the window; the drive east again: same (its nearest
    # eligible scan, 2 m away on the first drive, heads east), except its first few, still beside the way back
    assert (d[:100] == 0).all()
    assert (d[130:200] == 2).all()
    assert (d[240:300] == 1).all()


def test_retrieval_recalls_hand_computed():
    poses = _out_and_back_then_again()
    gt = loop_ground_truth(poses, gt_distance=25.0, exclusion=ExclusionWindow(frames=30))
    q = np.arange(300)
    # top-3 candidates: the right place (same x on the first drive) for even queries, a place 40 m away first and
    # the right one third for odd queries
    right = np.where(q < 100, -1, np.where(q < 200, 199 - q, q - 200))
    wrong = (right + 40) % 100
    top = np.stack([np.where(q % 2 == 0, right, wrong), np.full(300, -1), right], axis=1)
    top[right < 0] = -1
    m = retrieval_metrics(q, top, gt)
    evaluated = gt.is_revisit
    assert m.n_queries == int(evaluated.sum())
    ok = (right <= gt.max_eligible[q])[evaluated]  # the right place is out of the exclusion window
    even = q[evaluated] % 2 == 0
    assert m.recall_at_1 == pytest.approx(float((even & ok).mean()))
    # 1% of <= 270 eligible scans: k = 1..3; the right place in third position counts only where k = 3
    n_db = gt.max_eligible[q[evaluated]] + 1
    k = np.ceil(0.01 * n_db)
    expect = ((even | (k >= 3)) & ok).mean()
    assert m.recall_at_1pct == pytest.approx(float(expect))
    assert m.k_max == 3 and m.n_truncated == 0
    m2 = retrieval_metrics(q, top[:, :1], gt)
    assert m2.n_truncated > 0 and m2.recall_at_1pct == m2.recall_at_1


def test_direction_summary_counts_recall_per_direction():
    poses = _out_and_back_then_again()
    gt = loop_ground_truth(poses, gt_distance=5.0, exclusion=ExclusionWindow(frames=30))
    q = np.arange(300)
    right = np.where(q < 100, -1, np.where(q < 200, 199 - q, q - 200))
    # only same-direction loops are found: a detector blind to reverse revisits
    match = np.where(q >= 200, right, -1)
    metrics = loop_metrics(q, match, np.where(match >= 0, 1.0, np.nan), gt)
    out = direction_summary(metrics, gt)
    assert out["same"]["recall_at_1"] == pytest.approx(1.0)
    assert out["reverse"]["recall_at_1"] == 0.0 and out["reverse"]["n_revisits"] >= 70
    assert out["same"]["n_revisits"] + out["reverse"]["n_revisits"] == metrics.n_revisits


def test_direction_summary_at_a_fixed_threshold_counts_only_accepted_closures():
    poses = _out_and_back_then_again()
    gt = loop_ground_truth(poses, gt_distance=5.0, exclusion=ExclusionWindow(frames=30))
    q = np.arange(300)
    right = np.where(q < 100, -1, np.where(q < 200, 199 - q, q - 200))
    # every revisit found, but the same-direction ones score 1.0 and the reverse ones 0.2
    scores = np.where(q >= 200, 1.0, np.where(right >= 0, 0.2, np.nan))
    metrics = loop_metrics(q, right, scores, gt)
    out = direction_summary(metrics, gt, threshold=0.5)
    assert out["same"]["recall_at_threshold"] == pytest.approx(1.0)
    assert out["reverse"]["recall_at_threshold"] == 0.0 and out["reverse"]["recall_at_1"] > 0.9
    assert "recall_at_threshold" not in direction_summary(metrics, gt)["same"]
