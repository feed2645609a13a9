"""Protocols beside the loop protocol of `placerec.eval.metrics`: place retrieval (PointNetVLAD-style) and the
split of revisits into same- and reverse-direction loops.

Retrieval (Uy & Lee, "PointNetVLAD", CVPR 2018): a query is evaluated when some eligible database scan (the loop
protocol's exclusion window applies) lies within ``distance`` (25 m) of it; **recall@1** is the fraction of those
whose top candidate is within ``distance``, **recall@1%** the fraction with one among their first
``k = max(1, ceil(1% of the eligible database))`` candidates. A run keeps ``evaluation.top_n`` candidates per
query: where ``k`` exceeds them only those are looked at, and ``n_truncated`` counts such queries (raise
``top_n`` to at least ``k_max`` for the exact figure).

Direction: a revisit of the loop protocol is **reverse** when the heading (yaw of the sensor x axis) of the query
and of its nearest eligible true match differ by more than ``reverse_yaw_deg`` (90 deg), **same** otherwise (KITTI
08 is mostly reverse). Each group reports its revisits, recall@1 and the recall at the max-F1 threshold of all
queries.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from placerec.eval.ground_truth import LoopGroundTruth
from placerec.eval.metrics import LoopMetrics

__all__ = [
    "RetrievalMetrics",
    "retrieval_metrics",
    "revisit_directions",
    "direction_summary",
    "recall_by_direction",
]


@dataclass(frozen=True, eq=False)
class RetrievalMetrics:
    """Recall@1 and recall@1% at ``distance`` (module docstring); per-query arrays aligned with ``query_ids``
    of the evaluated queries."""

    distance: float
    n_queries: int
    recall_at_1: float
    recall_at_1pct: float
    k_max: int
    n_truncated: int
    query_ids: np.ndarray
    hit_at_1: np.ndarray
    hit_at_1pct: np.ndarray

    def summary(self) -> dict[str, Any]:
        return {
            "distance_m": self.distance,
            "n_queries": self.n_queries,
            "recall_at_1": self.recall_at_1,
            "recall_at_1pct": self.recall_at_1pct,
            "k_1pct_max": self.k_max,
            "n_truncated": self.n_truncated,
        }


def retrieval_metrics(
    query_ids: np.ndarray, topn_match_ids: np.ndarray, gt: LoopGroundTruth
) -> RetrievalMetrics:
    """Retrieval recalls of ranked candidates ``topn_match_ids`` (Q, N), ``-1`` padded, aligned with
    ``query_ids``; ``gt`` is the ground truth at the retrieval distance (`loop_ground_truth` with
    ``gt_distance=25``)."""
    q = np.asarray(query_ids, dtype=np.int64).reshape(-1)
    top = np.asarray(topn_match_ids, dtype=np.int64)
    top = top.reshape(q.size, -1) if top.size else np.full((q.size, 1), -1, np.int64)
    evaluated = gt.is_revisit[q]
    q, top = q[evaluated], top[evaluated]
    n_db = gt.max_eligible[q] + 1
    k = np.maximum(1, np.ceil(0.01 * n_db)).astype(np.int64)
    true = gt.is_true_match(q[:, None], top) if q.size else np.zeros((0, top.shape[1]), bool)
    within_k = np.arange(top.shape[1])[None, :] < k[:, None]
    hit1 = true[:, 0] if top.shape[1] else np.zeros(q.size, bool)
    hit_pct = (true & within_k).any(axis=1)
    n = int(q.size)
    return RetrievalMetrics(
        distance=gt.gt_distance,
        n_queries=n,
        recall_at_1=float(hit1.mean()) if n else 0.0,
        recall_at_1pct=float(hit_pct.mean()) if n else 0.0,
        k_max=int(k.max()) if n else 0,
        n_truncated=int((k > top.shape[1]).sum()),
        query_ids=q,
        hit_at_1=hit1,
        hit_at_1pct=hit_pct,
    )


def revisit_directions(gt: LoopGroundTruth, reverse_yaw_deg: float = 90.0) -> np.ndarray:
    """(N,) per scan: 0 not a revisit, 1 same direction, 2 reverse direction (heading difference to the nearest
    eligible true match over ``reverse_yaw_deg``)."""
    out = np.zeros(len(gt), dtype=np.int8)
    rev = np.flatnonzero(gt.is_revisit)
    if rev.size == 0:
        return out
    near = gt.nearest_index[rev]
    if gt.gt_yaw_deg is not None:  # the nearest scan may fail the yaw limit: take the nearest true match
        near = np.array([gt.true_matches(i)[np.argmin(_dist(gt, i))] for i in rev.tolist()], dtype=np.int64)
    d = np.degrees(np.abs(np.angle(np.exp(1j * (gt.yaws[rev] - gt.yaws[near])))))
    out[rev] = np.where(d > reverse_yaw_deg, 2, 1)
    return out


def _dist(gt: LoopGroundTruth, i: int) -> np.ndarray:
    c = gt.positions[:, :2] if gt.planar else gt.positions
    return np.linalg.norm(c[gt.true_matches(i)] - c[i], axis=1)


def direction_summary(
    metrics: LoopMetrics, gt: LoopGroundTruth, reverse_yaw_deg: float = 90.0, threshold: float | None = None
) -> dict[str, Any]:
    """``{"same": {...}, "reverse": {...}}``: revisits, recall@1 and recall at the max-F1 threshold per direction,
    and with ``threshold`` (a fixed operating threshold) the recall at it (``recall_at_threshold``): a sensor with
    a limited horizontal field of view is judged on the revisits it can see, those driven the same way."""
    return recall_by_direction(metrics, revisit_directions(gt, reverse_yaw_deg)[metrics.query_ids], threshold)


def recall_by_direction(
    metrics: LoopMetrics, direction: np.ndarray, threshold: float | None = None
) -> dict[str, Any]:
    """`direction_summary`'s figures for revisits whose ``direction`` (per query of ``metrics``: 1 same, 2
    reverse, 0 not a revisit) is given, e.g. by the pose truth's overlap (`placerec.eval.pose_truth`)."""
    none = np.zeros(metrics.query_ids.size, bool)
    tp = metrics.outcomes_at(metrics.threshold_at_max_f1)["tp"] if metrics.n_candidates else none
    tp_fixed = (
        metrics.outcomes_at(threshold)["tp"] if metrics.n_candidates and threshold is not None else none
    )
    out: dict[str, Any] = {}
    for name, code in (("same", 1), ("reverse", 2)):
        sel = direction == code
        n = int(sel.sum())
        out[name] = {
            "n_revisits": n,
            "recall_at_1": float((metrics.correct & sel).sum() / n) if n else None,
            "recall_at_max_f1": float((tp & sel).sum() / n) if n else None,
        }
        if threshold is not None:
            out[name]["recall_at_threshold"] = float((tp_fixed & sel).sum() / n) if n else None
    return out
