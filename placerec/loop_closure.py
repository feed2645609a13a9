"""The online loop-closure module for SLAM systems.

>>> from placerec.loop_closure import LoopClosureDetector
>>> from placerec.recognizer import make_pipeline
>>> detector = LoopClosureDetector(make_pipeline("scan-context"), threshold=0.8)   # doctest: +SKIP
>>> for scan, pose in stream:                                                      # doctest: +SKIP
...     for closure in detector.process(scan, pose=pose):
...         graph.add_edge(closure.match_id, closure.query_id, closure.relative_pose)

Scans get consecutive ids from 0 in the order they are fed. Each scan first queries the database restricted to
scans older than the exclusion window, then is added. Candidates with ``score >= threshold`` are accepted and
returned; the threshold is applied here, inside the library. ``relative_pose`` (when the pipeline estimates one)
is ``T_match_query``: it maps points of the new scan into the frame of the matched older scan.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanDataError
from placerec.recognizer import DescribingRecognizer, Description
from placerec.types import Candidate, PlaceRecognizer, Scan, as_pose

__all__ = ["LoopClosureDetector"]


class LoopClosureDetector:
    """Feed scans one by one; get accepted loop closures.

    ``exclusion_frames``/``exclusion_seconds``/``exclusion_metres``: database scans are eligible only if they are
    at least that many frames older / seconds older (needs ``timestamp``) / metres travelled before the current
    scan (needs ``pose``, e.g. odometry). When several are set, a scan must satisfy all of them.
    ``k``: candidates requested per query (accepted ones are returned best first).
    """

    def __init__(
        self,
        recognizer: PlaceRecognizer,
        threshold: float,
        exclusion_frames: int = 120,
        exclusion_seconds: float | None = None,
        exclusion_metres: float | None = None,
        k: int = 1,
    ) -> None:
        if exclusion_frames < 0 or (exclusion_seconds or 0) < 0 or (exclusion_metres or 0) < 0:
            raise ConfigError("exclusion windows must be non-negative")
        if k < 1:
            raise ConfigError(f"k must be >= 1, got {k}")
        self.recognizer = recognizer
        self.threshold = float(threshold)
        self.exclusion_frames = int(exclusion_frames)
        self.exclusion_seconds = exclusion_seconds
        self.exclusion_metres = exclusion_metres
        self.k = int(k)
        self._times: list[float] = []
        self._path: list[float] = []
        self._last_position: np.ndarray | None = None
        self.last_candidates: list[Candidate] = []
        self.last_timing_ms: dict[str, float] = {}
        self.closures: list[Candidate] = []

    @property
    def n_processed(self) -> int:
        return len(self._path)

    def _max_eligible_id(self, scan_id: int) -> int:
        bound = scan_id - max(self.exclusion_frames, 1)  # the scan itself is added after its query
        if self.exclusion_seconds is not None:
            cutoff = self._times[scan_id] - self.exclusion_seconds
            bound = min(bound, int(np.searchsorted(self._times[:scan_id], cutoff, side="right")) - 1)
        if self.exclusion_metres is not None:
            cutoff = self._path[scan_id] - self.exclusion_metres
            bound = min(bound, int(np.searchsorted(self._path[:scan_id], cutoff, side="right")) - 1)
        return bound

    def _record_motion(self, pose: np.ndarray | None, timestamp: float | None) -> None:
        if self.exclusion_seconds is not None:
            if timestamp is None:
                raise ScanDataError("exclusion_seconds is set: process() needs the scan's timestamp")
            if self._times and timestamp < self._times[-1]:
                raise ScanDataError(f"timestamps must not decrease ({timestamp} after {self._times[-1]})")
        self._times.append(float(timestamp) if timestamp is not None else float(len(self._times)))
        step = 0.0
        if pose is not None:
            position = as_pose(pose)[:3, 3]
            if self._last_position is not None:
                step = float(np.linalg.norm(position - self._last_position))
            self._last_position = position
        elif self.exclusion_metres is not None:
            raise ScanDataError(
                "exclusion_metres is set: process() needs the scan's pose (odometry is enough)"
            )
        self._path.append((self._path[-1] if self._path else 0.0) + step)

    def process(
        self,
        scan: Scan | None,
        pose: np.ndarray | None = None,
        timestamp: float | None = None,
        description: Description | None = None,
    ) -> list[Candidate]:
        """Query with the next scan, add it, and return the accepted closures (``score >= threshold``).

        ``description`` may be given instead of ``scan`` for a `DescribingRecognizer` (a cached front end).
        All candidates, accepted or not, are kept in ``last_candidates``; stage times in ``last_timing_ms``.
        """
        scan_id = self.n_processed
        self._record_motion(pose, timestamp)
        max_id = self._max_eligible_id(scan_id)
        rec = self.recognizer
        timing: dict[str, float] = {}
        describing = isinstance(rec, DescribingRecognizer)
        if description is None and describing:
            if scan is None:
                raise ScanDataError("process() needs a scan or a description")
            t0 = time.perf_counter()
            description = rec.describe(scan)
            timing["features"] = (time.perf_counter() - t0) * 1e3
        elif description is not None and not describing:
            raise ScanDataError(f"{rec.name} does not take descriptions; pass the scan")
        t0 = time.perf_counter()
        candidates: list[Candidate] = []
        if max_id >= 0:
            if describing:
                candidates = rec.query_description(description, k=self.k, max_id=max_id, query_id=scan_id)
            else:
                candidates = rec.query(scan, k=self.k, max_id=max_id, query_id=scan_id)
        timing["query"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        if describing:
            rec.add_description(scan_id, description, pose)
        else:
            rec.add(scan_id, scan, pose)
        timing["insert"] = (time.perf_counter() - t0) * 1e3
        split_verify_time(candidates, timing)
        self.last_candidates = candidates
        self.last_timing_ms = timing
        accepted = [c for c in candidates if c.score >= self.threshold]
        self.closures.extend(accepted)
        return accepted


def split_verify_time(candidates: list[Candidate], timing: dict[str, Any]) -> None:
    """Pipelines that verify geometrically report ``extra['verify_ms']`` on their candidates."""
    verify = sum(float(c.extra.get("verify_ms", 0.0)) for c in candidates)
    if verify:
        timing["verify"] = verify
        timing["query"] = max(0.0, timing["query"] - verify)
