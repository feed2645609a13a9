"""The online loop-closure module for SLAM systems.

>>> from placerec.loop_closure import LoopClosureDetector
>>> from placerec.recognizer import make_pipeline
>>> detector = LoopClosureDetector(make_pipeline("scan-context"), threshold=0.8)   # doctest: +SKIP
>>> detector = LoopClosureDetector.for_pipeline("orb-hbst")  # its operating threshold  # doctest: +SKIP
>>> for scan, pose in stream:                                                      # doctest: +SKIP
...     for closure in detector.process(scan, pose=pose):
...         graph.add_edge(closure.match_id, closure.query_id, closure.relative_pose)

Scans get consecutive ids from 0 (from ``prior_entries``, below) in the order they are fed. Each scan first
queries the database restricted to scans older than the exclusion window, then is added. A scan the recognizer
cannot describe (blank, a few points) raises `ScanDataError` and takes no id; `skip` records a frame that is no
place, so ids can follow frame numbers. Candidates with ``score >= threshold`` are accepted and returned; the
threshold is applied here, inside the library. ``relative_pose`` (when the pipeline estimates one) is
``T_match_query``: it maps points of the new scan into the frame of the matched older scan. A stream shorter than
the exclusion window queries nothing: every scan gets no candidates (``last_max_id`` -1).

**Against a prior map** (``prior_entries`` M > 0: the recognizer already holds a saved map's M places under ids
0..M-1, e.g. a loaded map artifact's database) the stream's places get ids M, M+1, ...; the exclusion window
counts only the stream's own places (frames, seconds and metres of this session), and the map's places are always
eligible: a query's bound is ``M - 1 + (the own places' bound)``, so the first scan already queries the map.
A candidate with ``match_id < prior_entries`` is an inter-session closure (`placerec.slam.multisession`).

With ``keyframes`` (`placerec.keyframes.KeyframeParams`) the detector accumulates the scans fed to `process` into
keyframes (`placerec.keyframes.KeyframeBuilder`: a time or distance window, de-skewed, in the frame of the window's
last scan): a scan that does not complete a keyframe returns no closures (an empty list, ``last_candidates`` empty,
``last_max_id`` -1, the build time in ``last_timing_ms["keyframe"]``); the scan that completes one runs the query
and insertion above on the keyframe and returns its closures. Ids are then keyframe ids (0, 1, ... in completion
order), ``relative_pose`` maps the query keyframe's frame into the matched keyframe's, and `keyframe_scans` says
which scans (numbered 0, 1, ... in the order fed) a keyframe holds. ``pose`` is the scan's odometry (needed unless
``keyframes.odometry`` is ``kiss-icp``), ``timestamp`` overrides the scan's own. `flush` makes a keyframe of the
scans fed since the last one (the end of a stream).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanDataError
from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES, ExclusionWindow, path_length
from placerec.keyframes import Keyframe, KeyframeBuilder, KeyframeParams
from placerec.loop_filter import LoopFilter, LoopFilterParams
from placerec.types import Candidate, Description, PlaceRecognizer, Scan, as_pose

__all__ = ["LoopClosureDetector"]


class LoopClosureDetector:
    """Feed scans one by one; get accepted loop closures.

    ``exclusion_frames``/``exclusion_seconds``/``exclusion_metres``: database scans are eligible only if they are
    at least that many frames older / seconds older (needs ``timestamp``) / metres travelled before the current
    scan (needs ``pose``, e.g. odometry); ``None`` = no limit of that kind. Every limit that is set applies — the
    rule of `placerec.eval.exclusion.ExclusionWindow`, which the evaluation's ground truth uses too.
    ``last_max_id`` is the bound the last query used (``-1``: nothing was eligible, the query was skipped).
    ``k``: candidates requested per query (accepted ones are returned best first). ``loop_filter``: DLoopDetector's
    islands and temporal consistency over each query's candidates (`placerec.loop_filter`; None: off); the reason a
    filtered query has no candidate is in ``last_status``. ``prior_entries``: places of a prior map the recognizer
    already holds under ids 0..prior_entries-1, always eligible (module docstring); 0: none.
    """

    @classmethod
    def for_pipeline(
        cls,
        name: str,
        params: Mapping[str, Any] | None = None,
        threshold: float | None = None,
        **options: Any,
    ) -> LoopClosureDetector:
        """A detector over the registered pipeline ``name`` (``params`` overrides its preset) at its operating
        threshold, chosen on the tuning split (docs/protocol.md), unless ``threshold`` is given; ``options`` are
        the other arguments of the constructor. `ConfigError` when the pipeline has no operating threshold and none
        is given."""
        from placerec.recognizer import PIPELINES, make_pipeline

        entry = PIPELINES.get(name)
        if threshold is None:
            if entry is None or entry.threshold is None:
                raise ConfigError(f"pipeline {name!r} has no operating threshold: give threshold=")
            threshold = entry.threshold
        return cls(make_pipeline(name, params), threshold=threshold, **options)

    def __init__(
        self,
        recognizer: PlaceRecognizer,
        threshold: float,
        exclusion_frames: int | None = DEFAULT_EXCLUSION_FRAMES,
        exclusion_seconds: float | None = None,
        exclusion_metres: float | None = None,
        k: int = 1,
        loop_filter: LoopFilterParams | None = None,
        keyframes: KeyframeParams | None = None,
        prior_entries: int = 0,
    ) -> None:
        if prior_entries < 0:
            raise ConfigError(f"prior_entries must be >= 0 (places of a prior map), got {prior_entries}")
        self.prior_entries = int(prior_entries)
        self.exclusion = ExclusionWindow(exclusion_frames, exclusion_seconds, exclusion_metres)
        self.keyframes = None if keyframes is None else KeyframeBuilder(keyframes, label="stream")
        self._keyframe_scans: list[tuple[int, ...]] = []
        self._scans_fed = 0
        if k < 1:
            raise ConfigError(f"k must be >= 1, got {k}")
        self.recognizer = recognizer
        self.threshold = float(threshold)
        self.k = int(k)
        self.loop_filter = None if loop_filter is None else LoopFilter(loop_filter)
        self.last_status = "ok"
        self._times: list[float] = []
        self._path: list[float] = []
        self._last_position: np.ndarray | None = None
        self.last_max_id = -1
        self.last_candidates: list[Candidate] = []
        self.last_timing_ms: dict[str, float] = {}
        self.closures: list[Candidate] = []

    @property
    def n_processed(self) -> int:
        """Places processed (or skipped): scans, or keyframes with ``keyframes`` (the stream's own; a prior map's
        entries are not counted)."""
        return len(self._path)

    @property
    def next_id(self) -> int:
        """The id the next place gets: ``prior_entries + n_processed``."""
        return self.prior_entries + len(self._path)

    def keyframe_scans(self, keyframe_id: int) -> tuple[int, ...]:
        """The scans (numbered in the order fed to `process`, from 0) that keyframe ``keyframe_id`` holds;
        `ConfigError` without ``keyframes``, `IndexError` for an id not given yet or one of a prior map's."""
        if self.keyframes is None:
            raise ConfigError("keyframe_scans: this detector has no keyframes")
        if keyframe_id < self.prior_entries:
            raise IndexError(f"keyframe {keyframe_id} is a prior map's entry (ids < {self.prior_entries})")
        return self._keyframe_scans[keyframe_id - self.prior_entries]

    def _max_eligible_id(self, own_index: int) -> int:
        """The query bound of the stream's place ``own_index`` (0, 1, ... within the stream): the exclusion
        window over the stream's own places, shifted past the prior map's entries, which are all eligible."""
        return self.prior_entries + int(self.exclusion.max_eligible(own_index, self._times, self._path))

    def _record_motion(self, pose: np.ndarray | None, timestamp: float | None) -> None:
        """Append the scan's timestamp and distance travelled (checked first, so a refused scan leaves no trace)."""
        if self.exclusion.seconds is not None:
            if timestamp is None:
                raise ScanDataError("exclusion_seconds is set: process() needs the scan's timestamp")
            if not np.isfinite(timestamp):
                raise ScanDataError(f"timestamps must be finite, got {timestamp}")
            if self._times and timestamp < self._times[-1]:
                raise ScanDataError(f"timestamps must not decrease ({timestamp} after {self._times[-1]})")
        if pose is None and self.exclusion.metres is not None:
            raise ScanDataError(
                "exclusion_metres is set: process() needs the scan's pose (odometry is enough)"
            )
        step = 0.0
        if pose is not None:
            position = as_pose(pose)[:3, 3]
            if self._last_position is not None:  # the ground truth's formula, so both agree to the last bit
                step = float(path_length(np.stack([self._last_position, position]))[1])
            self._last_position = position
        self._times.append(float(timestamp) if timestamp is not None else float(len(self._times)))
        self._path.append((self._path[-1] if self._path else 0.0) + step)

    def process(
        self,
        scan: Scan | None,
        pose: np.ndarray | None = None,
        timestamp: float | None = None,
        description: Description | None = None,
    ) -> list[Candidate]:
        """Query with the next scan, add it, and return the accepted closures (``score >= threshold``).

        ``description`` (the recognizer's ``describe`` of the scan, e.g. cached) may be given instead of ``scan``.
        The scan is described first: a `ScanDataError` there leaves no trace (no id used, nothing recorded).
        All candidates, accepted or not, are kept in ``last_candidates``; stage times (ms) in ``last_timing_ms``.
        With ``keyframes`` the scan is accumulated and a keyframe processed when it completes (module docstring;
        a scan the keyframe builder refuses leaves no trace; a keyframe the recognizer cannot describe takes its id
        as `skip` does, with the reason in ``last_status``).
        """
        if self.keyframes is None:
            return self._process_place(scan, pose, timestamp, description)
        if description is not None or scan is None:
            raise ScanDataError(
                "process() with keyframes needs the scan itself (a description cannot accumulate)"
            )
        t0 = time.perf_counter()
        keyframe = self.keyframes.add(scan, pose, index=self._scans_fed, timestamp=timestamp)
        self._scans_fed += 1
        return self._process_keyframe(keyframe, (time.perf_counter() - t0) * 1e3)

    def flush(self) -> list[Candidate]:
        """With ``keyframes``: process the keyframe of the scans fed since the last one (none: nothing to do) and
        return its closures; without, nothing to do."""
        if self.keyframes is None:
            return []
        t0 = time.perf_counter()
        keyframe = self.keyframes.flush()
        return self._process_keyframe(keyframe, (time.perf_counter() - t0) * 1e3)

    def _process_keyframe(self, keyframe: Keyframe | None, build_ms: float) -> list[Candidate]:
        """Query with and add a completed keyframe (None: no keyframe completed, no closures)."""
        if keyframe is None:
            self.last_max_id, self.last_candidates, self.last_status = -1, [], "ok"
            self.last_timing_ms = {"keyframe": build_ms}
            return []
        try:
            accepted = self._process_place(keyframe.scan, keyframe.pose, keyframe.timestamp, None)
        except ScanDataError as exc:
            self._skip_place(keyframe.pose, keyframe.timestamp)
            self.last_status = f"keyframe {self.next_id - 1} not described: {exc}"
            accepted = []
        self._keyframe_scans.append(keyframe.scan_indices)
        self.last_timing_ms["keyframe"] = build_ms
        return accepted

    def _process_place(
        self,
        scan: Scan | None,
        pose: np.ndarray | None,
        timestamp: float | None,
        description: Description | None,
    ) -> list[Candidate]:
        """`process` of one place (a scan, or a keyframe)."""
        rec = self.recognizer
        timing: dict[str, float] = {}
        if description is None:
            if scan is None:
                raise ScanDataError("process() needs a scan or a description")
            t0 = time.perf_counter()
            description = rec.describe(scan)
            timing["describe"] = (time.perf_counter() - t0) * 1e3
        own, scan_id = self.n_processed, self.next_id
        self._record_motion(pose, timestamp)
        max_id = self.last_max_id = self._max_eligible_id(own)
        t0 = time.perf_counter()
        answered: list[Candidate] = []
        lf = self.loop_filter
        if max_id >= 0:
            k = self.k if lf is None else max(self.k, lf.params.max_candidates)
            answered = rec.query_description(description, k=k, max_id=max_id, query_id=scan_id)
        candidates = answered
        if lf is not None and max_id >= 0:
            candidates, self.last_status = lf.apply(scan_id, answered)
            candidates = candidates[: self.k]
        timing["query"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        rec.add_description(scan_id, description, pose)
        timing["insert"] = (time.perf_counter() - t0) * 1e3
        split_verify_time(answered, timing)
        self.last_candidates = candidates
        self.last_timing_ms = timing
        accepted = [c for c in candidates if c.score >= self.threshold]
        self.closures.extend(accepted)
        return accepted

    def skip(self, pose: np.ndarray | None = None, timestamp: float | None = None) -> int:
        """Record a frame that is not a place (e.g. one `process` refused): it takes the next id and counts in
        the exclusion window, so later ids stay frame numbers, but it is never queried or added. Returns its id.
        With ``keyframes`` it is a keyframe of no scans."""
        scan_id = self._skip_place(pose, timestamp)
        if self.keyframes is not None:
            self._keyframe_scans.append(())
        return scan_id

    def _skip_place(self, pose: np.ndarray | None, timestamp: float | None) -> int:
        """`skip` of one place (a scan or a keyframe)."""
        scan_id = self.next_id
        self._record_motion(pose, timestamp)
        self.last_max_id = -1
        self.last_candidates = []
        self.last_timing_ms = {}
        return scan_id


def split_verify_time(candidates: list[Candidate], timing: dict[str, Any]) -> None:
    """Move the candidates' verification time out of ``timing["query"]`` into ``timing["verify"]``: pipelines that
    verify geometrically give each candidate's milliseconds in ``Candidate.verify_ms``
    (`placerec.verify.candidates.verify_candidates`); nothing changes when no candidate took any."""
    verify = sum(float(c.verify_ms) for c in candidates)
    if verify:
        timing["verify"] = verify
        timing["query"] = max(0.0, timing["query"] - verify)
