"""DLoopDetector's islands and temporal consistency, as an optional filter of the loop detector.

Following ``DLoopDetector::TemplatedLoopDetector::detectLoop`` (Galvez-Lopez & Tardos 2012), over the
candidates a recognizer returns for one query (best first; the detector asks for ``max_candidates`` of them):

1. *Islands*: the candidates are sorted by match id and grouped while consecutive ids differ by less than
   ``max_intragroup_gap``; groups spanning fewer than ``min_matches_per_group`` ids are dropped. An island's
   score is the sum of its members' scores, its representative the member with the highest score; the
   representatives are the filtered candidates, best island first.
2. *Temporal consistency* (``temporal_k`` > 0): the best island must overlap, or lie within
   ``max_distance_between_groups`` ids of, the best island of the previous query (itself at most
   ``max_distance_between_queries`` queries earlier); a loop needs more than ``temporal_k`` consistent queries
   in a row.

The filter keeps the temporal window of one stream of queries in acquisition order, which is why it belongs to
the detector (`placerec.loop_closure.LoopClosureDetector`, ``loop_filter``) and not to a recognizer, whose
queries must not change its state. The normalised similarity score, which needs the bag-of-words vectors,
stays with the DBoW pipeline (`placerec.retrieval.dbow.loop_detector`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from placerec.params import Params
from placerec.types import Candidate

__all__ = ["Island", "LoopFilter", "LoopFilterParams", "compute_islands"]

#: why the filter returned no candidate (DLoopDetector's names in lower case), or ``ok``
FilterStatus = Literal["ok", "no_candidates", "no_groups", "no_temporal_consistency"]


class LoopFilterParams(Params):
    """DLoopDetector's islands and temporal consistency (its defaults in the descriptions)."""

    max_candidates: int = Field(
        50, ge=1, description="candidates asked of the recognizer [DLoopDetector: 50]"
    )
    max_intragroup_gap: int = Field(3, ge=1, description="ids; DLoopDetector default")
    min_matches_per_group: int = Field(1, ge=1, description="DLoopDetector default")
    temporal_k: int = Field(0, ge=0, description="consistent queries needed [DLoopDetector: 3 or 4]")
    max_distance_between_groups: int = Field(3, ge=0, description="ids; DLoopDetector default")
    max_distance_between_queries: int = Field(2, ge=0, description="queries; DLoopDetector default")


@dataclass(frozen=True)
class Island:
    """A group of candidates with close match ids."""

    first: int
    last: int
    score: float
    best_id: int
    best_score: float


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
    """`LoopFilterParams` applied to each query's candidates, keeping the temporal window between queries."""

    def __init__(self, params: LoopFilterParams | None = None) -> None:
        self.params = params or LoopFilterParams()
        self.reset()

    def reset(self) -> None:
        self._window_n = 0
        self._last_island: Island | None = None
        self._last_query: int | None = None
        #: the islands of the last query, best first
        self.islands: list[Island] = []

    def apply(self, query: int, candidates: list[Candidate]) -> tuple[list[Candidate], FilterStatus]:
        """The island representatives among ``candidates`` (best island first) of query number ``query``, and
        the status (``ok``, or why none is returned)."""
        p = self.params
        cands = candidates[: p.max_candidates]
        self.islands = []
        if not cands:
            return [], "no_candidates"
        ids = np.array([c.match_id for c in cands], np.int64)
        scores = np.array([c.score for c in cands], np.float64)
        islands = compute_islands(ids, scores, p.max_intragroup_gap, p.min_matches_per_group)
        if not islands:
            return [], "no_groups"
        islands.sort(key=lambda isl: (-isl.score, isl.first))
        self.islands = islands
        if p.temporal_k > 0:
            self._update_window(islands[0], query)
            if self._window_n <= p.temporal_k:
                return [], "no_temporal_consistency"
        best: dict[int, Candidate] = {}
        for c in cands:  # the first (best) candidate of each id represents it
            best.setdefault(c.match_id, c)
        return [best[isl.best_id] for isl in islands], "ok"

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
