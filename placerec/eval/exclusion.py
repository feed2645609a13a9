"""The exclusion window: which older scans a query may match (one rule for the detector and the ground truth).

Scans are numbered by acquisition order. A database scan ``j`` is **eligible** for query ``i`` when it is older
than *every* limit that is set (``None`` = no limit of that kind):

* ``j <= i - frames``;
* ``t_j <= t_i - seconds`` (``t``: timestamps, non-decreasing);
* ``s_j <= s_i - metres`` (``s``: distance travelled, the cumulative length of the position path).

Whatever the limits, ``j < i`` (a scan never matches itself). Each bound is inclusive: with ``frames=120`` scan
``i - 120`` is eligible and ``i - 119`` is not. Because indices are acquisition-ordered, eligibility is one bound
per query, ``j <= max_eligible[i]`` (``-1`` = nothing eligible) — the ``max_id`` that
``PlaceRecognizer.query`` takes. The default, 120 frames and nothing else, is the VPR paper's protocol.
`placerec.loop_closure.LoopClosureDetector` (online) and `placerec.eval.ground_truth.loop_ground_truth` (offline)
both compute it with `ExclusionWindow.max_eligible`, so a revisit counted by the evaluation is one the detector
was allowed to find.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.params import Params
from placerec.types import path_length

__all__ = ["DEFAULT_EXCLUSION_FRAMES", "ExclusionWindow", "path_length"]

DEFAULT_EXCLUSION_FRAMES = 120  # VPR paper: "results from the most recent 120 steps are ignored"


class ExclusionWindow(Params):
    """Limits of the exclusion window (see the module docstring); all the limits that are set apply together.

    ``frames`` >= 0 or None, ``seconds`` >= 0 or None (needs timestamps), ``metres`` >= 0 or None (needs
    positions); anything else is a `ConfigError`. The limits may be given by position, in that order.
    """

    frames: int | None = Field(
        DEFAULT_EXCLUSION_FRAMES,
        ge=0,
        description="frames before the query (VPR paper: the last 120 ignored)",
    )
    seconds: float | None = Field(None, ge=0, description="s before the query (needs timestamps)")
    metres: float | None = Field(None, ge=0, description="m travelled before the query (needs poses)")

    def __init__(
        self,
        frames: int | None = DEFAULT_EXCLUSION_FRAMES,
        seconds: float | None = None,
        metres: float | None = None,
        **data: Any,
    ) -> None:
        super().__init__(frames=frames, seconds=seconds, metres=metres, **data)

    def max_eligible(
        self,
        query: int | np.ndarray,
        timestamps: np.ndarray | list[float] | None = None,
        travelled: np.ndarray | list[float] | None = None,
    ) -> np.ndarray:
        """Largest eligible database index for each query index (``-1`` when none), int64 of ``query``'s shape.

        ``timestamps`` and ``travelled`` (distance along the path, e.g. `path_length`) are indexed by scan index
        and must cover every ``query``; scans after the query do not change its bound, so a prefix ending at the
        query is enough (what the online detector has). They are needed only when ``seconds`` / ``metres`` are
        set; their validity (non-decreasing, finite) is the caller's to check (`sequence_bounds` does).
        """
        q = np.asarray(query, dtype=np.int64)
        bound = q - 1
        if self.frames:
            bound = np.minimum(bound, q - self.frames)
        for limit, values, unit, needs in (
            (self.seconds, timestamps, "seconds", "the timestamps"),
            (self.metres, travelled, "metres", "the positions (poses; odometry is enough)"),
        ):
            if limit is None:
                continue
            if values is None:
                raise ScanDataError(f"an exclusion window in {unit} needs {needs}")
            v = np.asarray(values, dtype=np.float64)
            bound = np.minimum(bound, np.searchsorted(v, v[q] - limit, side="right") - 1)
        return np.maximum(bound, -1).astype(np.int64)

    def sequence_bounds(
        self, n: int, timestamps: np.ndarray | None = None, positions: np.ndarray | None = None
    ) -> np.ndarray:
        """`max_eligible` of every index ``0..n-1`` of a whole sequence, after checking the inputs it needs:
        ``timestamps`` (N,) finite and non-decreasing, ``positions`` (N, 2|3)."""
        n = int(n)
        if self.seconds is not None and timestamps is not None:
            t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
            if t.shape[0] != n:
                raise ScanDataError(f"{t.shape[0]} timestamps for {n} scans")
            if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
                raise ScanDataError("timestamps must be finite and non-decreasing")
            timestamps = t
        travelled = None
        if self.metres is not None and positions is not None:
            travelled = path_length(positions)
            if travelled.shape[0] != n:
                raise ScanDataError(f"{travelled.shape[0]} positions for {n} scans")
        return self.max_eligible(np.arange(n, dtype=np.int64), timestamps, travelled)
