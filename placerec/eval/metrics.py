"""Evaluation metrics: loop-closure precision/recall (VPR paper protocol), localisation success (ISHOT paper),
timing summaries. Pose errors of closures: `placerec.eval.pose_error`.

Loop mode definitions
---------------------
Each evaluated query contributes its top candidate ``(query_id, match_id, score)``; ``match_id = -1`` means no
candidate. Ids are indices into the poses (see `placerec.eval.ground_truth`). At a score threshold ``t``:

* the candidate is **accepted** when ``match_id >= 0`` and ``score >= t``;
* **TP**: accepted and a true match (eligible and within ``gt_distance`` of the query, optionally within the yaw
  limit — the distance is that between the query's and the match's own poses);
* **FP**: accepted and not a true match (whether or not the query is a revisit);
* **FN**: a revisit query without an accepted true match. A revisit query whose accepted candidate is wrong is
  therefore counted **both** as FP and as FN — it reported a wrong loop and missed the right one;
* TN: a non-revisit query with nothing accepted (not used by P/R).

``P = TP / (TP + FP)``, ``R = TP / (TP + FN) = TP / n_revisits``, ``F1 = 2PR / (P + R)``. The PR curve has one point
per distinct candidate score, thresholds descending (recall non-decreasing); no artificial ``(R=0, P=1)`` point is
added. ``average_precision`` is the step-wise area ``sum_k (R_k - R_{k-1}) P_k`` with ``R_{-1} = 0`` (as
scikit-learn's ``average_precision_score``); it is below 1 when some revisits are never found. ``recall_at_1`` is
the fraction of revisit queries whose top candidate is a true match at any threshold; ``recall_at_n[n-1]`` the
fraction with a true match among their first ``n`` candidates. With no revisit query, recalls are reported as 0 and
``no_revisits`` is set.

``recall_at_100_precision`` (R_P100) is the highest recall of a curve point with no false positive (0 when the
best-scored candidate is already wrong); ``precision_at_min_recall`` (P_R0) the precision of the first curve point
(the highest threshold); ``extended_precision`` EP = (P_R0 + R_P100) / 2 (Ferrarini et al., "Exploring
Performance Bounds of Visual Place Recognition Using Extended Precision", IEEE RA-L 2020). All three are 0 with no
candidate.

The same functions serve live runs and recomputation from a ``query_id,match_id,score`` CSV plus the poses.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from placerec.errors import ScanDataError
from placerec.eval.ground_truth import LoopGroundTruth, loop_ground_truth
from placerec.eval.pose_error import pose_errors

log = logging.getLogger(__name__)

__all__ = [
    "GroundTruth",
    "LoopMetrics",
    "loop_metrics",
    "evaluate_loop",
    "LocalizationMetrics",
    "localization_metrics",
    "timing_summary",
]


class GroundTruth(Protocol):
    """What `loop_metrics` reads of a ground truth (`LoopGroundTruth`, `placerec.eval.pose_truth.PoseGroundTruth`,
    `placerec.eval.icp_truth.IcpGroundTruth`)."""

    @property
    def max_eligible(self) -> np.ndarray: ...

    @property
    def is_revisit(self) -> np.ndarray: ...

    def __len__(self) -> int: ...

    def is_true_match(self, query: np.ndarray, match: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class LoopMetrics:
    """Loop-closure metrics (definitions in the module docstring). Arrays of the PR curve are aligned with
    ``thresholds`` (distinct candidate scores, descending); per-query arrays with ``query_ids``."""

    n_queries: int
    n_revisits: int
    n_candidates: int
    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    max_f1: float
    precision_at_max_f1: float
    recall_at_max_f1: float
    threshold_at_max_f1: float
    average_precision: float
    recall_at_100_precision: float
    precision_at_min_recall: float
    extended_precision: float
    recall_at_1: float
    recall_at_n: np.ndarray | None
    no_revisits: bool
    query_ids: np.ndarray
    match_ids: np.ndarray
    scores: np.ndarray
    correct: np.ndarray
    revisit: np.ndarray

    @property
    def f1(self) -> np.ndarray:
        """F1 at every point of the PR curve (0 where P + R = 0)."""
        return _f1(self.precision, self.recall)

    def outcomes_at(self, threshold: float) -> dict[str, np.ndarray]:
        """Per-query boolean masks ``accepted``, ``tp``, ``fp``, ``fn``, ``tn`` at ``threshold``."""
        accepted = (self.match_ids >= 0) & (self.scores >= threshold)
        tp = accepted & self.correct
        return {
            "accepted": accepted,
            "tp": tp,
            "fp": accepted & ~self.correct,
            "fn": self.revisit & ~tp,
            "tn": ~self.revisit & ~accepted,
        }

    def confusion_at(self, threshold: float) -> dict[str, int]:
        """Counts ``tp``, ``fp``, ``fn``, ``tn`` at ``threshold``."""
        out = self.outcomes_at(threshold)
        return {k: int(out[k].sum()) for k in ("tp", "fp", "fn", "tn")}

    def summary(self) -> dict[str, Any]:
        """The scalar metrics as a JSON-friendly dict."""
        return {
            "n_queries": self.n_queries,
            "n_revisits": self.n_revisits,
            "n_candidates": self.n_candidates,
            "max_f1": self.max_f1,
            "precision_at_max_f1": self.precision_at_max_f1,
            "recall_at_max_f1": self.recall_at_max_f1,
            "threshold_at_max_f1": self.threshold_at_max_f1,
            "average_precision": self.average_precision,
            "recall_at_100_precision": self.recall_at_100_precision,
            "precision_at_min_recall": self.precision_at_min_recall,
            "extended_precision": self.extended_precision,
            "recall_at_1": self.recall_at_1,
            "recall_at_n": None if self.recall_at_n is None else [float(v) for v in self.recall_at_n],
            "no_revisits": self.no_revisits,
        }


def _f1(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    s = p + r
    return np.divide(2 * p * r, s, out=np.zeros_like(s, dtype=np.float64), where=s > 0)


def _as_ids(values: Any, name: str) -> np.ndarray:
    a = np.asarray(values)
    if a.size == 0:
        return np.zeros(a.shape, dtype=np.int64)
    if not np.issubdtype(a.dtype, np.integer):
        if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise ScanDataError(f"{name} must be integers")
    return a.astype(np.int64)


def loop_metrics(
    query_ids: Sequence[int] | np.ndarray,
    match_ids: Sequence[int] | np.ndarray,
    scores: Sequence[float] | np.ndarray,
    gt: GroundTruth,
    topn_match_ids: np.ndarray | None = None,
) -> LoopMetrics:
    """Loop-mode metrics from the top candidate of every evaluated query.

    ``query_ids``, ``match_ids`` (``-1`` = no candidate) and ``scores`` are aligned 1-D arrays; each query id must
    appear once (the evaluated set is exactly these queries). Scores of rows without a candidate are ignored and
    may be NaN; a NaN score of a real candidate raises `ScanDataError`. ``topn_match_ids`` (Q, N), ``-1`` padded,
    aligned with ``query_ids``, gives ``recall_at_n``.
    """
    q = _as_ids(query_ids, "query_ids").reshape(-1)
    m = _as_ids(match_ids, "match_ids").reshape(-1)
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if not (q.shape == m.shape == s.shape):
        raise ScanDataError(f"query_ids, match_ids, scores differ in length: {q.size}, {m.size}, {s.size}")
    n = len(gt)
    if q.size and (q.min() < 0 or q.max() >= n):
        raise ScanDataError(f"query ids must lie in [0, {n}) (indices into the poses)")
    if np.unique(q).size != q.size:
        raise ScanDataError("each query id may appear only once")
    has = m >= 0
    if np.any(m >= n):
        raise ScanDataError(f"match ids must be < {n} (indices into the poses), got {int(m.max())}")
    if np.any(np.isnan(s[has])):
        raise ScanDataError(f"{int(np.isnan(s[has]).sum())} candidate scores are NaN")
    correct = gt.is_true_match(q, m)
    late = has & (m > gt.max_eligible[q])
    if np.any(late):
        log.warning(
            "%d candidates are inside the exclusion window; counted as false positives", int(late.sum())
        )
    revisit = gt.is_revisit[q]
    n_rev = int(revisit.sum())

    # PR sweep: sort candidates by score (descending), cumulative TP/FP, keep the last row of each distinct score.
    cs, cc = s[has], correct[has]
    order = np.argsort(-cs, kind="stable")
    cs, cc = cs[order], cc[order]
    tp_cum = np.cumsum(cc).astype(np.int64)
    fp_cum = np.cumsum(~cc).astype(np.int64)
    last = np.flatnonzero(np.r_[cs[1:] != cs[:-1], True]) if cs.size else np.zeros(0, dtype=np.int64)
    thresholds, tp, fp = cs[last], tp_cum[last], fp_cum[last]
    fn = n_rev - tp
    precision = tp / np.maximum(tp + fp, 1)
    recall = tp / n_rev if n_rev else np.zeros(tp.shape, dtype=np.float64)
    f1 = _f1(precision, recall)
    if f1.size:
        b = int(np.argmax(f1))  # first maximum = highest threshold reaching it
        max_f1, p_best, r_best, t_best = (float(v[b]) for v in (f1, precision, recall, thresholds))
    else:
        max_f1, p_best, r_best, t_best = 0.0, 0.0, 0.0, float("nan")
    ap = float(np.sum(np.diff(np.r_[0.0, recall]) * precision))
    clean = fp == 0  # a prefix of the curve: precision 1 (every point holds at least one candidate)
    r_p100 = float(recall[clean][-1]) if clean.any() else 0.0
    p_r0 = float(precision[0]) if precision.size else 0.0
    r1 = float(correct.sum() / n_rev) if n_rev else 0.0

    r_at_n = None
    if topn_match_ids is not None:
        top = _as_ids(topn_match_ids, "topn_match_ids")
        if top.ndim != 2 or top.shape[0] != q.size:
            raise ScanDataError(f"topn_match_ids must have shape ({q.size}, N), got {top.shape}")
        if np.any(top >= n):
            raise ScanDataError(f"topn_match_ids must be < {n} (indices into the poses)")
        found = np.logical_or.accumulate(gt.is_true_match(q[:, None], top), axis=1)
        r_at_n = found.sum(axis=0) / n_rev if n_rev else np.zeros(top.shape[1])
    if n_rev == 0:
        log.warning(
            "no revisit among the %d evaluated queries: recall is undefined and reported as 0", q.size
        )
    return LoopMetrics(
        n_queries=int(q.size),
        n_revisits=n_rev,
        n_candidates=int(has.sum()),
        thresholds=thresholds,
        precision=precision,
        recall=recall,
        tp=tp,
        fp=fp,
        fn=fn,
        max_f1=max_f1,
        precision_at_max_f1=p_best,
        recall_at_max_f1=r_best,
        threshold_at_max_f1=t_best,
        average_precision=ap,
        recall_at_100_precision=r_p100,
        precision_at_min_recall=p_r0,
        extended_precision=(p_r0 + r_p100) / 2,
        recall_at_1=r1,
        recall_at_n=None if r_at_n is None else np.asarray(r_at_n, dtype=np.float64),
        no_revisits=n_rev == 0,
        query_ids=q,
        match_ids=m,
        scores=s,
        correct=correct,
        revisit=revisit,
    )


def evaluate_loop(
    query_ids: Sequence[int] | np.ndarray,
    match_ids: Sequence[int] | np.ndarray,
    scores: Sequence[float] | np.ndarray,
    poses: np.ndarray,
    topn_match_ids: np.ndarray | None = None,
    **gt_options: Any,
) -> tuple[LoopMetrics, LoopGroundTruth]:
    """`loop_ground_truth` (``gt_options``: gt_distance, gt_yaw_deg, planar, exclusion, timestamps)
    followed by `loop_metrics`; e.g. to recompute metrics from a candidates CSV and the poses."""
    gt = loop_ground_truth(poses, **gt_options)
    return loop_metrics(query_ids, match_ids, scores, gt, topn_match_ids), gt


@dataclass(frozen=True, eq=False)
class LocalizationMetrics:
    """Localize-mode metrics (ISHOT paper): a query succeeds when its position error is <= ``success_distance``.
    Each query is exactly one of: localised (an answer within the distance: ``n_success``), no answer (a NaN
    estimate: ``n_no_estimate``) or answered wrongly (an answer beyond the distance: ``n_wrong``, what a user would
    act on). ``answer_rule`` says what counted as an answer: ``"accepted"`` (the verification's accepted top
    candidate; a rejected one is no answer) or ``"top"`` (a pipeline without verification: its top candidate).

    ``basis`` says what the estimate is: ``"pose"`` (the matched map pose composed with the candidate's 6-DoF
    relative pose) or ``"retrieval"`` (the matched map scan's position: place retrieval only). ``errors`` (Q,)
    metres (inf where no estimate was given), ``success`` (Q,) bool, ``answered`` (Q,) bool (an estimate was
    given). ``rotation_errors`` (Q,) degrees where a pose was estimated (NaN elsewhere). ``fine_success`` (Q,): within ``fine_distance`` and ``fine_rotation_deg``
    (1 m / 5 deg); defined only for pose estimates (None, and ``fine_success_rate`` NaN, for ``retrieval``).
    ``mean_error``, ``median_error`` and ``median_rotation_error`` are over queries with an estimate (NaN if none).
    """

    errors: np.ndarray
    success: np.ndarray
    success_rate: float
    n_queries: int
    n_success: int
    n_no_estimate: int
    n_wrong: int
    no_answer_rate: float
    wrong_rate: float
    answered: np.ndarray
    mean_error: float
    median_error: float
    success_distance: float
    basis: str = "retrieval"
    answer_rule: str = "accepted"
    rotation_errors: np.ndarray | None = None
    fine_success: np.ndarray | None = None
    fine_success_rate: float = float("nan")
    median_rotation_error: float = float("nan")
    fine_distance: float = 1.0
    fine_rotation_deg: float = 5.0

    def summary(self) -> dict[str, Any]:
        """The scalar metrics as a JSON-friendly dict: ``n_success`` localised, ``n_no_estimate`` no answer,
        ``n_wrong`` answered but wrong, and their rates (``success_rate``, ``no_answer_rate``, ``wrong_rate``)."""
        return {
            "n_queries": self.n_queries,
            "n_success": self.n_success,
            "n_no_estimate": self.n_no_estimate,
            "n_wrong": self.n_wrong,
            "no_answer_rate": self.no_answer_rate,
            "wrong_rate": self.wrong_rate,
            "answer_rule": self.answer_rule,
            "success_basis": self.basis,
            "success_rate": self.success_rate,
            "mean_error": self.mean_error,
            "median_error": self.median_error,
            "median_rotation_error_deg": self.median_rotation_error,
            "success_distance": self.success_distance,
            "fine_success_rate": self.fine_success_rate,
            "fine_distance": self.fine_distance,
            "fine_rotation_deg": self.fine_rotation_deg,
        }


def _as_positions(a: Any, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim == 3 and p.shape[1:] == (4, 4):
        return p[:, :3, 3]
    if p.ndim == 2 and p.shape[1] in (2, 3):
        return p
    raise ScanDataError(f"{name} must be positions (Q, 2|3) or poses (Q, 4, 4), got shape {p.shape}")


def localization_metrics(
    estimated: np.ndarray,
    truth: np.ndarray,
    success_distance: float = 3.0,
    planar: bool = False,
    basis: str = "retrieval",
    fine_distance: float = 1.0,
    fine_rotation_deg: float = 5.0,
    answer_rule: str = "accepted",
) -> LocalizationMetrics:
    """Success rate of localisation: ``estimated`` and ``truth`` are (Q, 2|3) positions or (Q, 4, 4) poses.
    Rows of ``estimated`` with NaN mean "no answer" and fail. The error is 3D Euclidean (xy with ``planar=True``).

    ``basis="pose"``: the rows are estimated query poses (map pose @ relative pose); with (Q, 4, 4) poses on both
    sides the rotation error and the fine success (``fine_distance`` m and ``fine_rotation_deg``) are computed too.
    ``basis="retrieval"``: the rows are the matched map scans' positions; no fine success (it is not a pose).
    ``answer_rule`` labels what the caller counted as an answer (`LocalizationMetrics`); a query without one is a
    NaN row either way.
    """
    if basis not in ("pose", "retrieval"):
        raise ScanDataError(f"basis must be 'pose' or 'retrieval', got {basis!r}")
    if answer_rule not in ("accepted", "top"):
        raise ScanDataError(f"answer_rule must be 'accepted' or 'top', got {answer_rule!r}")
    est = _as_positions(estimated, "estimated")
    gt = _as_positions(truth, "truth")
    if est.shape[0] != gt.shape[0]:
        raise ScanDataError(f"{est.shape[0]} estimates for {gt.shape[0]} ground-truth positions")
    if est.shape[1] != gt.shape[1]:
        raise ScanDataError(f"estimated and truth differ in dimension: {est.shape[1]} vs {gt.shape[1]}")
    if not np.all(np.isfinite(gt)):
        raise ScanDataError("ground-truth positions contain NaN or inf")
    if not (success_distance > 0 and fine_distance > 0 and fine_rotation_deg > 0):
        raise ScanDataError(
            f"success_distance, fine_distance, fine_rotation_deg must be > 0, got {success_distance},"
            f" {fine_distance}, {fine_rotation_deg}"
        )
    dims = 2 if planar else est.shape[1]
    n = int(est.shape[0])
    answered = np.all(np.isfinite(est), axis=1)
    errors = np.full(n, np.inf)
    errors[answered] = np.linalg.norm(est[answered, :dims] - gt[answered, :dims], axis=1)
    success = errors <= success_distance
    fin = errors[answered]
    rot, fine, fine_rate, med_rot = None, None, float("nan"), float("nan")
    if basis == "pose" and np.ndim(estimated) == 3 and np.ndim(truth) == 3:
        E = np.asarray(estimated, dtype=np.float64)
        ok = answered & np.isfinite(E).all(axis=(1, 2))
        rot = np.full(n, np.nan)
        if ok.any():
            rot[ok] = pose_errors(E[ok], np.asarray(truth, dtype=np.float64)[ok])[1]
            med_rot = float(np.median(rot[ok]))
        fine = ok & (errors <= fine_distance) & (np.nan_to_num(rot, nan=np.inf) <= fine_rotation_deg)
        fine_rate = float(fine.mean()) if n else 0.0
    return LocalizationMetrics(
        errors=errors,
        success=success,
        success_rate=float(success.mean()) if n else 0.0,
        n_queries=n,
        n_success=int(success.sum()),
        n_no_estimate=int((~answered).sum()),
        n_wrong=int((answered & ~success).sum()),
        no_answer_rate=float((~answered).mean()) if n else 0.0,
        wrong_rate=float((answered & ~success).mean()) if n else 0.0,
        answered=answered,
        mean_error=float(fin.mean()) if fin.size else float("nan"),
        median_error=float(np.median(fin)) if fin.size else float("nan"),
        success_distance=float(success_distance),
        basis=basis,
        answer_rule=answer_rule,
        rotation_errors=rot,
        fine_success=fine,
        fine_success_rate=fine_rate,
        median_rotation_error=med_rot,
        fine_distance=float(fine_distance),
        fine_rotation_deg=float(fine_rotation_deg),
    )


def timing_summary(times_ms: Sequence[float] | np.ndarray) -> dict[str, float]:
    """``{"n", "mean", "median", "p95", "max"}`` of per-query times in milliseconds (NaN statistics when empty)."""
    t = np.asarray(times_ms, dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(t)):
        raise ScanDataError("timings contain NaN or inf")
    if t.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "median": nan, "p95": nan, "max": nan}
    return {
        "n": int(t.size),
        "mean": float(t.mean()),
        "median": float(np.median(t)),
        "p95": float(np.percentile(t, 95)),
        "max": float(t.max()),
    }
