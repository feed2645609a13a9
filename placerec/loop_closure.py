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

**Real-time mode** (``realtime``: `placerec.realtime.RealtimeParams`, a time budget per scan and a most backlog):
`process` does in the caller's thread only what must happen in order and is cheap to keep (the keyframe, the
description, the motion record, the exclusion bound), then hands "query with that bound, then add" to one worker
thread (`placerec.realtime.SerialWorker`) that runs those steps in scan order, so the database sees exactly the
sequential mode's operations and the same closures are accepted, only later: each call returns the closures that
completed since the last call (each `Candidate` names its ``query_id``; ``last_completed`` holds their places'
results). When the worker is more than ``max_backlog`` places behind, `process` waits; counters (scans over
budget, closures deferred and by how many places) are in ``realtime_stats`` (`placerec.realtime.RealtimeStats`).
`flush` (the end of a stream) waits for the worker and returns every closure still due; `close` (or leaving a
``with`` block) does that and ends the thread. A query that failed in the worker is raised at the next call as
`placerec.realtime.LateScanError` naming its scan, before that call's own scan is touched. The recognizer is the
worker's while it runs: `flush` before reading or saving it.
"""

from __future__ import annotations

import inspect
import time
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanDataError
from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES, ExclusionWindow, path_length
from placerec.keyframes import Keyframe, KeyframeBuilder, KeyframeParams
from placerec.loop_filter import LoopFilter, LoopFilterParams
from placerec.odometry_gate import ChainPrior, LoopChain, OdometryGateParams, pose_disagreement
from placerec.realtime import LateScanError, RealtimeParams, RealtimeStats, SerialWorker
from placerec.types import Candidate, Description, MotionPrior, PlaceRecognizer, Scan, as_pose

__all__ = ["LoopClosureDetector", "PlaceResult", "RealtimeParams", "RealtimeStats", "LateScanError"]


@dataclass
class PlaceResult:
    """One place's query and insertion: its id, the bound it queried with, every candidate, the accepted ones,
    the loop filter's or odometry gate's status (None: neither ran) and the stage times (ms: query, insert, verify)."""

    place_id: int
    max_id: int
    candidates: list[Candidate]
    accepted: list[Candidate]
    status: str | None
    timing_ms: dict[str, float]


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
    already holds under ids 0..prior_entries-1, always eligible (module docstring); 0: none. ``realtime``:
    the real-time mode (module docstring; None: sequential). ``odometry_gate``: a closure is accepted only where
    it agrees with the odometry ``pose`` given to `process` (`placerec.odometry_gate`; each place then needs its
    pose; a prior map's places, in another frame, are not gated); a query whose candidates passed the threshold
    but not the gate has ``last_status`` ``odometry_gate``, and ``refused_by_gate`` keeps every closure it refused;
    with its ``through_loops`` the motion is predicted through the closures it accepted before
    (`placerec.odometry_gate.LoopChain`). None: off.
    """

    @classmethod
    def for_pipeline(
        cls,
        name: str,
        params: Mapping[str, Any] | None = None,
        threshold: float | None = None,
        sensor: str | None = None,
        **options: Any,
    ) -> LoopClosureDetector:
        """A detector over the registered pipeline ``name`` (``params`` overrides its preset) at its operating
        threshold, chosen on the tuning split (docs/protocol.md), unless ``threshold`` is given. For ``sensor``, a
        sensor model name, the settings and threshold chosen on that sensor's tuning cells where they differ
        (`placerec.sensor_presets`; with ``odometry_gate`` among ``options``, those chosen with the gate),
        ``params`` still winning. ``options`` are the other arguments of the constructor. `ConfigError` when the
        pipeline has no operating threshold and none is given."""
        from placerec.recognizer import PIPELINES, make_pipeline

        entry = PIPELINES.get(name)
        odometry = options.get("odometry_gate") is not None
        if threshold is None:
            threshold = None if entry is None else entry.threshold_for(sensor, odometry)
            if threshold is None:
                raise ConfigError(f"pipeline {name!r} has no operating threshold: give threshold=")
        return cls(
            make_pipeline(name, params, sensor=sensor, odometry=odometry), threshold=threshold, **options
        )

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
        realtime: RealtimeParams | None = None,
        odometry_gate: OdometryGateParams | None = None,
    ) -> None:
        if prior_entries < 0:
            raise ConfigError(f"prior_entries must be >= 0 (places of a prior map), got {prior_entries}")
        self.prior_entries = int(prior_entries)
        self.exclusion = ExclusionWindow(exclusion_frames, exclusion_seconds, exclusion_metres)
        self.keyframes = None if keyframes is None else KeyframeBuilder(keyframes, label="stream")
        self._keyframe_scans: list[tuple[int, ...]] = []
        self.last_keyframe: Keyframe | None = None  # with keyframes: the one the last call completed
        self._scans_fed = 0
        if k < 1:
            raise ConfigError(f"k must be >= 1, got {k}")
        self.recognizer = recognizer
        # a recognizer written before `query_description` took a motion prior is called without one
        self._takes_prior = "prior" in inspect.signature(recognizer.query_description).parameters
        self.threshold = float(threshold)
        self.k = int(k)
        self.loop_filter = None if loop_filter is None else LoopFilter(loop_filter)
        self.odometry_gate = odometry_gate
        self.last_status = "ok"
        self._times: list[float] = []
        self._path: list[float] = []
        self._poses: list[np.ndarray] = []  # with the odometry gate: each own place's pose
        # with the gate: the own places' closures it predicts through (through_loops; else none: the odometry alone)
        self._chain = LoopChain()
        self.refused_by_gate: list[Candidate] = []  # closures over the threshold the odometry gate refused
        self._last_position: np.ndarray | None = None
        self._position_before: np.ndarray | None = None  # the position before the last recorded place
        self.last_max_id = -1
        self.last_candidates: list[Candidate] = []
        self.last_timing_ms: dict[str, float] = {}
        self.closures: list[Candidate] = []
        self.last_completed: list[PlaceResult] = []
        self.realtime = realtime
        self.realtime_stats = None if realtime is None else RealtimeStats(realtime.budget_ms)
        self._worker = None if realtime is None else SerialWorker(lambda job: self._query_and_add(*job))
        self._calls = 0  # process / flush calls (real-time mode)
        self._submitted: dict[int, int] = {}  # place id -> the call that fed it
        self._ready: list[Candidate] = []  # closures collected, not yet returned
        self._late: deque[tuple[int, Exception]] = deque()  # failed places, raised at the next call
        self._waited = 0.0

    def __enter__(self) -> LoopClosureDetector:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()  # an error is on its way: end the thread without raising another

    def abort(self) -> None:
        """End the real-time worker's thread (after the places queued) without handing anything over or raising:
        for a caller that is failing; `flush` can still hand over what is due."""
        if self._worker is not None:
            self._worker.stop()

    @property
    def n_processed(self) -> int:
        """Places processed (or skipped): scans, or keyframes with ``keyframes`` (the stream's own; a prior map's
        entries are not counted)."""
        return len(self._path)

    def path_at(self, own: Iterable[int]) -> np.ndarray:
        """The odometry path (m) travelled up to each of the stream's own places ``own`` (0-based: place id minus
        ``prior_entries``; 0 at the first place, and no step where a place came without a pose)."""
        return np.array([self._path[i] for i in own], dtype=np.float64)

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

    def _forget_motion(self) -> None:
        """Undo the last `_record_motion` (its time, its path length and the position it moved to)."""
        self._times.pop()
        self._path.pop()
        if self.odometry_gate is not None:
            self._poses.pop()
        self._last_position = self._position_before

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
        if pose is None and self.odometry_gate is not None:
            raise ScanDataError("odometry_gate is set: process() needs the scan's odometry pose")
        step = 0.0
        self._position_before = self._last_position
        if pose is not None:
            pose = as_pose(pose)
            position = pose[:3, 3]
            if self._last_position is not None:  # the ground truth's formula, so both agree to the last bit
                step = float(path_length(np.stack([self._last_position, position]))[1])
            self._last_position = position
        self._times.append(float(timestamp) if timestamp is not None else float(len(self._times)))
        self._path.append((self._path[-1] if self._path else 0.0) + step)
        if pose is not None and self.odometry_gate is not None:  # a pose is required then (above)
            self._poses.append(pose)

    def process(
        self,
        scan: Scan | None,
        pose: np.ndarray | None = None,
        timestamp: float | None = None,
        description: Description | None = None,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        """Query with the next scan, add it, and return the accepted closures (``score >= threshold``).

        ``description`` (the recognizer's ``describe`` of the scan, e.g. cached) may be given instead of ``scan``.
        The scan is described first: a `ScanDataError` there leaves no trace (no id used, nothing recorded).
        All candidates, accepted or not, are kept in ``last_candidates``; stage times (ms) in ``last_timing_ms``.
        With ``keyframes`` the scan is accumulated and a keyframe processed when it completes (module docstring;
        a scan the keyframe builder refuses leaves no trace; a keyframe the recognizer cannot describe takes its id
        as `skip` does, with the reason in ``last_status``). In real-time mode: the closures completed since the
        last call, ``last_candidates`` empty, ``last_timing_ms`` the caller's stages (``describe``, ``wait``).
        ``prior``: what the caller's odometry predicts for this place (`placerec.types.MotionPrior`, over the
        detector's ids; not with ``keyframes``), given to the recognizer's query; without it a detector with the
        ``odometry_gate`` gives its own (`placerec.odometry_gate.ChainPrior`, through the closures it accepted).
        """
        if prior is not None and self.keyframes is not None:
            raise ConfigError("process(prior=...) predicts for a place: not with keyframes being built")
        if self._worker is None:
            self.last_completed = []
            return self._process(scan, pose, timestamp, description, prior)
        if self._worker.closed:
            raise ConfigError("this real-time detector is closed: it takes no more scans")
        t0 = time.perf_counter()
        self._start_call()
        self._process(scan, pose, timestamp, description, prior)
        out = self._end_call()
        st = self.realtime_stats
        assert st is not None
        ms = (time.perf_counter() - t0) * 1e3
        st.scans += 1
        st.process_ms.append(ms)
        st.waited += self._waited > 0
        st.over_budget += ms > st.budget_ms
        return out

    def _process(
        self,
        scan: Scan | None,
        pose: np.ndarray | None,
        timestamp: float | None,
        description: Description | None,
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        if self.keyframes is None:
            return self._process_place(scan, pose, timestamp, description, prior)
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
        return its closures; without, nothing to do. In real-time mode also wait for the worker to finish every
        place queued and return every closure not returned yet."""
        if self._worker is None:
            self.last_completed = []
            return self._flush()
        self._start_call()
        self._flush()
        self._worker.wait(0)
        return self._end_call(raise_late=True)

    def close(self) -> list[Candidate]:
        """`flush`, then end the real-time worker's thread (also when `flush` raises); a closed detector takes no
        more scans (`flush` still hands over what is due)."""
        try:
            return self.flush()
        finally:
            if self._worker is not None:
                self._worker.stop()

    def _start_call(self) -> None:
        """Real-time mode, a call's start: raise the oldest failed place, else count the call."""
        assert self._worker is not None
        self._raise_late()
        self.last_completed = []
        self._waited = 0.0
        self._calls += 1

    def _raise_late(self) -> None:
        if not self._late:
            return
        place, exc = self._late.popleft()
        if isinstance(exc, ScanDataError):
            raise LateScanError(place, exc) from exc
        exc.add_note(f"scan {place}: raised in the real-time loop-closure worker")
        raise exc

    def _end_call(self, raise_late: bool = False) -> list[Candidate]:
        """Real-time mode, a call's end: collect the places the worker finished; return the closures due."""
        assert self._worker is not None and self.realtime_stats is not None
        st = self.realtime_stats
        for done in self._worker.take():
            st.worker_ms.append(done.ms)
            call = self._submitted.pop(done.key)
            if done.error is not None or done.result is None:
                st.worker_errors += 1
                self._late.append((done.key, done.error or RuntimeError("no result")))
                continue
            result = done.result
            self.last_completed.append(result)
            st.closures += len(result.accepted)
            if result.accepted and self._calls > call:  # returned by a later call than its place's
                st.deferred_closures += len(result.accepted)
                st.max_delay = max(st.max_delay, self.next_id - 1 - done.key)
            self._ready.extend(result.accepted)
            self.closures.extend(result.accepted)
        if raise_late:
            self._raise_late()
        out, self._ready = self._ready, []
        return out

    def _flush(self) -> list[Candidate]:
        if self.keyframes is None:
            return []
        t0 = time.perf_counter()
        keyframe = self.keyframes.flush()
        return self._process_keyframe(keyframe, (time.perf_counter() - t0) * 1e3)

    def _process_keyframe(self, keyframe: Keyframe | None, build_ms: float) -> list[Candidate]:
        """Query with and add a completed keyframe (None: no keyframe completed, no closures)."""
        self.last_keyframe = keyframe
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
        prior: MotionPrior | None = None,
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
        if self._worker is not None:
            return self._submit(scan_id, description, pose, max_id, timing, prior)
        try:
            result = self._query_and_add(scan_id, description, pose, max_id, prior)
        except ScanDataError:
            self._forget_motion()  # a refused place leaves no trace: a `skip` of it records it once
            raise
        if result.status is not None:
            self.last_status = result.status
        self.last_candidates = result.candidates
        self.last_timing_ms = timing | result.timing_ms
        self.last_completed = [result]
        self.closures.extend(result.accepted)
        return result.accepted

    def _submit(
        self,
        scan_id: int,
        description: Description,
        pose: np.ndarray | None,
        max_id: int,
        timing: dict[str, float],
        prior: MotionPrior | None = None,
    ) -> list[Candidate]:
        """Real-time mode: queue the place's query and insertion; wait while the worker is too far behind."""
        assert self._worker is not None and self.realtime is not None and self.realtime_stats is not None
        self._submitted[scan_id] = self._calls
        backlog = self._worker.submit(scan_id, (scan_id, description, pose, max_id, prior))
        st = self.realtime_stats
        st.max_backlog = max(st.max_backlog, backlog)
        t0 = time.perf_counter()
        if backlog > self.realtime.max_backlog:
            self._worker.wait(self.realtime.max_backlog)
            self._waited = timing["wait"] = (time.perf_counter() - t0) * 1e3
        self.last_candidates = []
        self.last_timing_ms = timing
        return []

    def _query_and_add(
        self,
        scan_id: int,
        description: Description,
        pose: np.ndarray | None,
        max_id: int,
        prior: MotionPrior | None = None,
    ) -> PlaceResult:
        """Query the database with ``description`` restricted to ids <= ``max_id`` (none when -1), filter,
        threshold, then add the place: the only steps that touch the recognizer's database (in real-time mode
        they run in the worker thread, in place order). ``prior`` as in `process`."""
        rec = self.recognizer
        timing: dict[str, float] = {}
        t0 = time.perf_counter()
        answered: list[Candidate] = []
        status: str | None = None
        lf = self.loop_filter
        if max_id >= 0:
            k = self.k if lf is None else max(self.k, lf.params.max_candidates)
            if prior is None and self.odometry_gate is not None:
                own = scan_id - self.prior_entries
                prior = ChainPrior(
                    self._chain, own, self._poses, self._path, self.odometry_gate, self.prior_entries
                )
            extra = {"prior": prior} if prior is not None and self._takes_prior else {}
            answered = rec.query_description(description, k=k, max_id=max_id, query_id=scan_id, **extra)
        candidates = answered
        if lf is not None and max_id >= 0:
            candidates, status = lf.apply(scan_id, answered)
            candidates = candidates[: self.k]
        timing["query"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        rec.add_description(scan_id, description, pose)
        timing["insert"] = (time.perf_counter() - t0) * 1e3
        split_verify_time(answered, timing)
        accepted = [c for c in candidates if c.score >= self.threshold]
        if self.odometry_gate is not None:
            kept = self._gated(scan_id, accepted) if accepted else accepted
            status = "odometry_gate" if accepted and not kept else status or "ok"
            accepted = kept
        return PlaceResult(scan_id, max_id, candidates, accepted, status, timing)

    def _gated(self, scan_id: int, accepted: list[Candidate]) -> list[Candidate]:
        """The ``accepted`` closures of place ``scan_id`` that agree with the odometry (`odometry_gate`); a
        prior map's place and a closure without a relative pose pass."""
        assert self.odometry_gate is not None
        own = scan_id - self.prior_entries
        checked = [c for c in accepted if c.match_id >= self.prior_entries and c.relative_pose is not None]
        if not checked:
            return accepted
        matches = [c.match_id - self.prior_entries for c in checked]
        closures = np.stack([np.asarray(c.relative_pose, dtype=np.float64) for c in checked])
        predicted = [self._chain.predict(m, own, self._poses, self._path) for m in matches]
        trans, rot = pose_disagreement(closures, np.stack([T for T, _ in predicted]))
        ok = self.odometry_gate.admits(trans, rot, np.array([along for _, along in predicted]))
        if self.odometry_gate.through_loops:
            for m, T, good in zip(matches, closures, ok, strict=True):
                if good:
                    self._chain.add(m, own, T)
        refused = {id(c) for c, good in zip(checked, ok, strict=True) if not good}
        self.refused_by_gate += [c for c in checked if id(c) in refused]
        return [c for c in accepted if id(c) not in refused]

    def skip(self, pose: np.ndarray | None = None, timestamp: float | None = None) -> int:
        """Record a frame that is not a place (e.g. one `process` refused): it takes the next id and counts in
        the exclusion window, so later ids stay frame numbers, but it is never queried or added. Returns its id.
        With ``keyframes`` it is a keyframe of no scans."""
        scan_id = self._skip_place(pose, timestamp)
        if self.keyframes is not None:
            self._keyframe_scans.append(())
            self.last_keyframe = None
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
