"""DLoopDetector's normalised similarity score on top of DBoW database queries.

Following ``DLoopDetector::TemplatedLoopDetector::detectLoop`` (Galvez-Lopez & Tardos 2012), step 1: with
``use_nss`` the scores are divided by ``eta = s(v_t, v_{t-1})``, the score of the query against the previous frame;
when ``eta < min_nss_factor`` the query is rejected. Results whose (normalised) score is below ``alpha`` are removed
(DLoopDetector: alpha 0.3; placerec default 0 = keep all). Off by default: the VPR paper uses DBoW2's database
queries as they are.

DLoopDetector's islands and temporal consistency work on any recognizer's candidates and keep state between
queries: they are the loop detector's optional filter, `placerec.loop_filter`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from placerec.params import Params

__all__ = ["LoopDetectorParams", "LoopResult", "normalised_results"]


class LoopDetectorParams(Params):
    """DLoopDetector's score normalisation (defaults: off; DLoopDetector's own defaults in the descriptions)."""

    use_nss: bool = Field(False, description="normalised similarity score [DLoopDetector: true]")
    alpha: float = Field(0.0, ge=0, description="minimum (normalised) score [DLoopDetector: 0.3]")
    min_nss_factor: float = Field(0.005, ge=0, description="minimum score against the previous frame")
    max_db_results: int = Field(50, ge=1, description="database results considered [DLoopDetector: 50]")

    @property
    def enabled(self) -> bool:
        return self.use_nss or self.alpha > 0


@dataclass(frozen=True)
class LoopResult:
    """Results after the normalisation (best first) and why a query was rejected (``status``, DLoopDetector's
    names in lower case: ``ok``, ``no_db_results``, ``low_nss_factor``, ``low_scores``)."""

    ids: np.ndarray
    scores: np.ndarray
    status: str


def normalised_results(
    params: LoopDetectorParams, ids: np.ndarray, scores: np.ndarray, eta: float | None = None
) -> LoopResult:
    """Normalise and cut one query's results (best first); ``eta`` is the score against the previous frame
    (needed with ``use_nss``; None = no previous frame yet)."""
    p = params
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
    return LoopResult(ids, scores, "ok")
