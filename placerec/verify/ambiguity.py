"""Refusing an answer that another place nearly matches: the ambiguity rule of localisation against a map.

A query that repeated structure makes look like two places (a row of identical sheds; a 70 deg cone that sees one
facade and the road) can be registered onto either, and verification accepts both: each registration is good,
only one is in the right place. Where the matched entries' poses are known (a map), the answers can be compared:
each accepted candidate places the query at ``T_world_match @ T_match_query``. The best accepted answer's
runner-up is the best-scoring accepted candidate that places the query more than ``separation_m`` from it; the
answer is refused (no answer, never a guess) when

    ratio = score(runner-up) / score(best) >= max_ratio          (ratio 0 without a runner-up)

Candidates that agree (one place in two passes of the map, neighbouring keyframes) never count against each other,
so a place seen many times is not made ambiguous by its own keyframes. Off by default (``max_ratio`` None): the
value is chosen per use on tuning data (docs/sensors.md, "A map from one sensor, queried with another").
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params

__all__ = ["AmbiguityParams", "runner_up_ratio"]


class AmbiguityParams(Params):
    """When a localisation answer is refused because another place scores nearly as well (module docstring)."""

    max_ratio: float | None = Field(
        None,
        gt=0,
        le=1,
        description="refuse the best accepted answer when an accepted one placing the query more than "
        "separation_m away scores at least this share of its score (None: never refuse)",
    )
    separation_m: float = Field(
        5.0, gt=0, allow_inf_nan=False, description="m; answers closer than this to the best agree with it"
    )

    def refuses(self, ratio: float) -> bool:
        """Whether an answer whose runner-up scores ``ratio`` of it is refused."""
        return self.max_ratio is not None and ratio >= self.max_ratio


def runner_up_ratio(scores: np.ndarray, positions: np.ndarray, separation_m: float) -> float:
    """``score(runner-up) / score(best)`` of accepted answers (module docstring): ``scores`` (K,) and the query
    positions (K, 3) they give, the best answer first; 0 when no answer lies more than ``separation_m`` from the
    best one. `ScanDataError` for shapes that disagree, an empty set, or a best score that is not positive."""
    s = np.asarray(scores, np.float64).reshape(-1)
    p = np.asarray(positions, np.float64)
    if s.size == 0 or p.shape != (s.size, 3):
        raise ScanDataError(f"ambiguity: {s.size} scores need ({s.size}, 3) positions, got {p.shape}")
    if not (np.isfinite(s[0]) and s[0] > 0):
        raise ScanDataError(f"ambiguity: the best answer's score must be positive, got {s[0]}")
    far = np.linalg.norm(p[1:] - p[0], axis=1) > separation_m
    if not far.any():
        return 0.0
    return float(np.max(s[1:][far]) / s[0])
