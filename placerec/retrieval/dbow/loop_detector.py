"""DLoopDetector's options on top of database queries: normalised score, islands, temporal consistency.

Following ``DLoopDetector::TemplatedLoopDetector::detectLoop`` (Galvez-Lopez & Tardos 2012):

1. *Normalised similarity score* (``use_nss``): scores are divided by ``eta = s(v_t, v_{t-1})``, the score of the
   query against the previous frame; when ``eta < min_nss_factor`` the query is rejected. Results whose
   (normalised) score is below ``alpha`` are removed (DLoopDetector: alpha 0.3; placerec default 0 = keep all).
2. *Islands* (``islands``): results are sorted by entry id and grouped while consecutive ids differ by less than
   ``max_intragroup_gap``; groups spanning fewer than ``min_matches_per_group`` ids are dropped. An island's score
   is the sum of its members' scores, its representative the member with the highest score.
3. *Temporal consistency* (``temporal_k`` > 0): the best island must overlap, or lie within
   ``max_distance_between_groups`` ids of, the best island of the previous query (itself at most
   ``max_distance_between_queries`` queries earlier); a loop needs more than ``temporal_k`` consistent queries
   in a row.

All options are off by default (the VPR paper uses DBoW2's database queries as they are). `LoopFilter` holds the
temporal window, so one filter serves one sequence of queries in acquisition order.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from placerec.params import Params

log = logging.getLogger(__name__)

__all__ = ["LoopDetectorParams", "LoopFilter", "LoopResult", "Island", "compute_islands"]


class LoopDetectorParams(Params):
    """DLoopDetector options (defaults: all off; DLoopDetector's own defaults in the descriptions)."""

    use_nss: bool = Field(False, description="normalised similarity score [DLoopDetector: true]")
    alpha: float = Field(0.0, ge=0, description="minimum (normalised) score [DLoopDetector: 0.3]")
    min_nss_factor: float = Field(0.005, ge=0, description="minimum score against the previous frame")
    max_db_results: int = Field(50, ge=1, description="database results considered [DLoopDetector: 50]")
    islands: bool = Field(False, description="group results by id [DLoopDetector: always on]")
    max_intragroup_gap: int = Field(3, ge=1, description="ids; DLoopDetector default")
    min_matches_per_group: int = Field(1, ge=1, description="DLoopDetector default")
    temporal_k: int = Field(0, ge=0, description="consistent queries needed [DLoopDetector: 3 or 4]")
    max_distance_between_groups: int = Field(3, ge=0, description="ids; DLoopDetector default")
    max_distance_between_queries: int = Field(2, ge=0, description="queries; DLoopDetector default")


@dataclass(frozen=True)
class Island:
    """A group of results with close entry ids."""

    first: int
    last: int
    score: float
    best_id: int
    best_score: float


@dataclass(frozen=True)
class LoopResult:
    """Candidates after the filter (best first) and why a query was rejected (``status``, DLoopDetector's
    names in lower case: ``ok``, ``no_db_results``, ``low_nss_factor``, ``low_scores``, ``no_groups``,
    ``no_temporal_consistency``)."""

    ids: np.ndarray
    scores: np.ndarray
    status: str
    islands: tuple[Island, ...] = ()


def compute_islands(ids: np.ndarray, scores: np.ndarray, max_gap: int, min_length: int) -> list[Island]:
    """Group results into islands (ids sorted ascending; a new island starts where ``id - last >= max_gap``)."""
    ids = np.asarray(ids, np.int64)
    scores = np.asarray(scores, np.float64)
    if ids.size == 0:
        return []
    order = np.argsort(ids, kind="stable")
    i, s = ids[order], scores[order]
    breaks = np.flatnonzero(np.diff(i) >= max_gap) + 1
    starts = np.r_[0, breaks]
    ends = np.r_[breaks, i.size]
    sums = np.add.reduceat(s, starts)
    out = []
    for a, b, total in zip(starts, ends, sums, strict=True):
        if i[b - 1] - i[a] + 1 < min_length:
            continue
        best = a + int(np.argmax(s[a:b]))
        out.append(Island(int(i[a]), int(i[b - 1]), float(total), int(i[best]), float(s[best])))
    return out


class LoopFilter:
    """Applies `LoopDetectorParams` to one query's database results, keeping the temporal window."""

    def __init__(self, params: LoopDetectorParams | None = None) -> None:
        self.params = params or LoopDetectorParams()
        self.reset()

    def reset(self) -> None:
        self._window_n = 0
        self._last_island: Island | None = None
        self._last_query: int | None = None

    def apply(self, query: int, ids: np.ndarray, scores: np.ndarray, eta: float | None = None) -> LoopResult:
        """Filter results (best first) of query number ``query``; ``eta`` is the score against the previous
        frame (needed with ``use_nss``; None = no previous frame yet)."""
        p = self.params
        ids = np.asarray(ids, np.int64)[: p.max_db_results]
        scores = np.asarray(scores, np.float64)[: p.max_db_results]
        empty = np.zeros(0, np.int64), np.zeros(0)
        if ids.size == 0:
            return LoopResult(*empty, "no_db_results")
        if p.use_nss:
            if eta is None or eta < p.min_nss_factor:
                return LoopResult(*empty, "low_nss_factor")
            scores = scores / eta
        keep = scores >= p.alpha
        ids, scores = ids[keep], scores[keep]
        if ids.size == 0:
            return LoopResult(*empty, "low_scores")
        if not p.islands:
            return LoopResult(ids, scores, "ok")
        islands = compute_islands(ids, scores, p.max_intragroup_gap, p.min_matches_per_group)
        if not islands:
            return LoopResult(*empty, "no_groups")
        islands.sort(key=lambda isl: (-isl.score, isl.first))
        if p.temporal_k > 0:
            self._update_window(islands[0], query)
            if self._window_n <= p.temporal_k:
                return LoopResult(*empty, "no_temporal_consistency", tuple(islands))
        return LoopResult(
            np.array([isl.best_id for isl in islands], np.int64),
            np.array([isl.best_score for isl in islands]),
            "ok",
            tuple(islands),
        )

    def _update_window(self, island: Island, query: int) -> None:
        p = self.params
        prev, last_q = self._last_island, self._last_query
        if prev is None or last_q is None or query - last_q > p.max_distance_between_queries:
            self._window_n = 1
        else:
            overlap = (island.first <= prev.first <= island.last) or (prev.first <= island.first <= prev.last)
            gap = max(prev.first - island.last, island.first - prev.last)
            self._window_n = self._window_n + 1 if overlap or gap <= p.max_distance_between_groups else 1
        self._last_island = island
        self._last_query = query
