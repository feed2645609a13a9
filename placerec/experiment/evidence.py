"""Why a loop closed, or did not: the closures the report shows per pipeline and why its candidates were rejected.

A pipeline is judged at the threshold the report uses (max F1, `placerec.eval.LoopMetrics.outcomes_at`); at it
each query's top candidate is an *accepted true closure*, a *false closure* (accepted, wrong place) or nothing;
a revisit with no accepted answer is a *missed revisit*. `select_cases` picks a few of each kind, spread evenly
over the sequence (deterministic: the same run gives the same gallery):

* accepted and false closures show the query's top candidate;
* a missed revisit shows its best candidate: the first correct one among the query's candidates (its rejection
  says why the right place lost), else the top one (a wrong place that was rejected or scored below the
  threshold), else, with no candidate at all, the scan it revisits (the nearest eligible one), posed by the
  ground truth. A revisit whose top candidate was accepted but wrong is a false closure and shown there.

`rejection_counts` tallies why candidates were rejected (`placerec.types.REJECTIONS`), over every candidate and
over each query's top one: the confusion summary of the report. The figures are drawn by
`placerec.experiment.evidence_figures`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace

import numpy as np

from placerec.eval import LocalizationMetrics, LoopGroundTruth, LoopMetrics, full_pose_mask, pose_errors
from placerec.experiment.runner import PipelineRecord
from placerec.types import REJECTIONS, Candidate, relative_pose

__all__ = [
    "KINDS",
    "ACCEPTED",
    "UNVERIFIED",
    "REJECTED",
    "EvidenceCase",
    "RejectionCounts",
    "rejection_key",
    "rejection_counts",
    "decision_text",
    "select_cases",
    "select_localize_cases",
    "spread",
    "with_truth",
]

#: the galleries of a pipeline, in the order the report shows them
KINDS = ("accepted", "false", "missed")
#: `rejection_key` of a candidate its verification accepted
ACCEPTED = "accepted"
#: `rejection_key` of a candidate of a pipeline that does not verify (its score alone decides)
UNVERIFIED = "not verified"
#: `rejection_key` of a rejected candidate whose verification names no reason (`Candidate.rejection`'s word)
REJECTED = "rejected"


@dataclass(frozen=True, eq=False)
class EvidenceCase:
    """One closure of a gallery: ``kind`` (one of `KINDS`), the ``query_id`` and the ``match_id`` shown,
    ``rank`` of the candidate shown among the query's (0 = top; -1 when the query had no candidate and the
    revisited scan is shown), the ``candidate`` (None then), ``decision`` (`decision_text`), whether the match
    shown is the right place (``correct``, by the ground truth the metrics use), and by the ground truth poses
    (`with_truth`) the distance between the two scans (``distance_m``) and the pose error of the candidate's
    relative pose (``translation_m``, ``rotation_deg``; NaN without a 6-DoF estimate)."""

    kind: str
    query_id: int
    match_id: int
    rank: int
    candidate: Candidate | None
    decision: str
    correct: bool
    translation_m: float = float("nan")
    rotation_deg: float = float("nan")
    distance_m: float = float("nan")

    @property
    def T_match_query(self) -> np.ndarray | None:
        """The candidate's relative pose (None when it has none, or there is no candidate)."""
        return None if self.candidate is None else self.candidate.relative_pose


@dataclass(frozen=True)
class RejectionCounts:
    """How many candidates ended how (`rejection_key` -> count): ``all`` candidates of the run, and the ``top``
    candidate of each query."""

    all: dict[str, int]
    top: dict[str, int]

    def as_dict(self) -> dict[str, dict[str, int]]:
        """``metrics.json``'s ``rejections`` entry."""
        return {"all": dict(self.all), "top": dict(self.top)}


def rejection_key(candidate: Candidate) -> str:
    """How verification ended for ``candidate``: `ACCEPTED`, a key of `placerec.types.REJECTIONS`, `REJECTED`
    (rejected, no reason given) or `UNVERIFIED` (a pipeline that does not verify)."""
    if candidate.accepted is None:
        return UNVERIFIED
    return candidate.rejection or ACCEPTED


def rejection_counts(candidates: list[list[Candidate]]) -> RejectionCounts:
    """`RejectionCounts` of a run's candidate lists (one list per query, best first); keys in a fixed order
    (`ACCEPTED`, the verification's reasons as `placerec.types.REJECTIONS` lists them, the rest), each present
    only when counted."""
    order = [ACCEPTED, *REJECTIONS, REJECTED, UNVERIFIED]
    every = Counter(rejection_key(c) for cands in candidates for c in cands)
    top = Counter(rejection_key(cands[0]) for cands in candidates if cands)

    def ordered(counts: Counter[str]) -> dict[str, int]:
        return {
            k: counts[k] for k in sorted(counts, key=lambda k: order.index(k) if k in order else len(order))
        }

    return RejectionCounts(ordered(every), ordered(top))


def decision_text(candidate: Candidate | None, threshold: float) -> str:
    """What became of ``candidate`` at ``threshold``, in words: ``accepted``, ``rejected: <reason>`` (the
    verification's, `placerec.types.REJECTIONS`), ``below threshold (<score> < <threshold>)`` (a pipeline that
    does not verify, or a verified score under the max-F1 threshold; a NaN threshold, a run without candidates,
    accepts nothing, ``-inf`` everything verification did not reject), or ``no candidate``."""
    if candidate is None:
        return "no candidate"
    key = rejection_key(candidate)
    if key not in (ACCEPTED, UNVERIFIED):
        return f"rejected: {REJECTIONS.get(key, 'by verification')}"
    if np.isnan(threshold) or candidate.score < threshold:
        return f"below threshold ({candidate.score:.3g} < {threshold:.3g})"
    return "accepted"


def spread(rows: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of ``rows`` (in sequence order), evenly spaced from the first to the last."""
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size <= n:
        return rows
    return rows[np.unique(np.round(np.linspace(0, rows.size - 1, n)).astype(np.int64))]


def with_truth(
    case: EvidenceCase, match_poses: np.ndarray, query_poses: np.ndarray | None = None
) -> EvidenceCase:
    """``case`` with what the ground truth says of it: the distance between its scans and the error of its
    candidate's relative pose (when a 6-DoF estimate, `placerec.eval.full_pose_mask`). Its match id indexes the
    ``T_world_sensor`` of ``match_poses``, its query id those of ``query_poses`` (default: the same, loop mode)."""
    queries = match_poses if query_poses is None else query_poses
    truth = relative_pose(match_poses[case.match_id], queries[case.query_id])
    case = replace(case, distance_m=float(np.linalg.norm(truth[:3, 3])))
    rel = case.T_match_query
    if rel is None or not full_pose_mask(rel)[0]:
        return case
    t, r = pose_errors(rel, truth)
    return replace(case, translation_m=float(t[0]), rotation_deg=float(r[0]))


def select_cases(
    record: PipelineRecord,
    metrics: LoopMetrics,
    truth: LoopGroundTruth,
    poses: np.ndarray,
    per_gallery: int,
) -> list[EvidenceCase]:
    """Up to ``per_gallery`` closures of each of `KINDS` (see the module docstring) at ``metrics``'s max-F1
    threshold; ``metrics`` are those of ``record``'s top candidates under ``truth`` (rows aligned with
    ``record.query_ids``), ``poses`` the ground truth the ids index into."""
    threshold = metrics.threshold_at_max_f1
    if metrics.n_candidates and np.isfinite(threshold):
        outcome = metrics.outcomes_at(threshold)
    else:
        none = np.zeros(metrics.query_ids.size, dtype=bool)
        outcome = {"tp": none, "fp": none, "accepted": none, "fn": metrics.revisit.copy()}
    rows = {
        "accepted": outcome["tp"],
        "false": outcome["fp"],
        "missed": outcome["fn"] & ~outcome["accepted"],
    }
    cases = []
    for kind in KINDS:
        for row in spread(np.flatnonzero(rows[kind]), per_gallery):
            q = int(record.query_ids[row])
            cands = record.candidates[row]
            right = truth.is_true_match(
                np.full(len(cands), q), np.array([c.match_id for c in cands], np.int64)
            )
            rank = 0 if cands else -1
            if kind == "missed" and right.any():
                rank = int(np.argmax(right))
            cand = cands[rank] if rank >= 0 else None
            m = int(truth.nearest_index[q]) if cand is None else int(cand.match_id)
            if m < 0:
                continue  # a revisit always has an eligible scan; nothing to show otherwise
            correct = cand is None or bool(right[rank])
            case = EvidenceCase(kind, q, m, rank, cand, decision_text(cand, threshold), correct)
            cases.append(with_truth(case, poses))
    return cases


def select_localize_cases(
    record: PipelineRecord,
    metrics: LocalizationMetrics,
    map_poses: np.ndarray,
    query_poses: np.ndarray,
    per_gallery: int,
) -> list[EvidenceCase]:
    """Localize mode's galleries, up to ``per_gallery`` queries each (spread over the queries): ``accepted``, the
    queries localised (`placerec.eval.LocalizationMetrics.success`), ``false``, those answered wrongly, and
    ``missed``, those with no answer. A localised or wrong query shows its top candidate (its answer); one with
    no answer its best candidate: the first whose map scan lies within the success distance of the query's true
    position, else the top one, else, with no candidate, the nearest map scan posed by the ground truth. A case
    is ``correct`` when the map scan shown lies within the success distance (the answer's position is what
    localised or not).
    ``metrics`` are ``record``'s (rows aligned with ``record.query_ids``); query ids index ``query_poses``, match
    ids ``map_poses``."""
    rows = {
        "accepted": metrics.success,
        "false": metrics.answered & ~metrics.success,
        "missed": ~metrics.answered,
    }
    cases = []
    for kind in KINDS:
        for row in spread(np.flatnonzero(rows[kind]), per_gallery):
            q = int(record.query_ids[row])
            cands = record.candidates[row]
            here = query_poses[q, :3, 3]
            distance = np.linalg.norm(map_poses[[c.match_id for c in cands], :3, 3] - here, axis=1)
            right = distance <= metrics.success_distance
            rank = 0 if cands else -1
            if kind == "missed" and right.any():
                rank = int(np.argmax(right))
            cand = cands[rank] if rank >= 0 else None
            to_map = np.linalg.norm(map_poses[:, :3, 3] - here, axis=1)
            if cand is None and not to_map.size:
                continue  # an empty map: nothing to show
            m = int(np.argmin(to_map)) if cand is None else int(cand.match_id)
            correct = bool(to_map[m] <= metrics.success_distance)
            case = EvidenceCase(kind, q, m, rank, cand, decision_text(cand, -np.inf), correct)
            cases.append(with_truth(case, map_poses, query_poses))
    return cases
