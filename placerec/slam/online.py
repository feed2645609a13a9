"""The online SLAM back end: odometry poses in, verified loop closures found, a GTSAM pose graph kept current.

>>> from placerec.recognizer import make_pipeline
>>> from placerec.slam import OnlineSlam
>>> slam = OnlineSlam(make_pipeline("orb-hbst"), threshold=0.25)          # doctest: +SKIP
>>> for scan, odom in stream:                                             # doctest: +SKIP
...     loops = slam.process(scan, odom)      # this scan's accepted closures, already in the graph
>>> poses = slam.finish()                     # the batch-optimised trajectory (N, 4, 4)   # doctest: +SKIP

Each scan: the `placerec.loop_closure.LoopClosureDetector` queries with it (exclusion window over the odometry
poses) and adds it; the graph gets the scan's pose with an odometry factor from the previous odometry pose, and a
robust loop factor per accepted closure (``T_match_query``); then iSAM2 updates (every scan, and with extra passes
when a loop arrived). ``extra_loops`` lets a caller add loop edges of its own (the robustness benchmarks inject
false ones this way). Stage times (ms) of the last scan are in ``last_timing_ms``.

With ``realtime`` (`placerec.realtime.RealtimeParams`) the detector runs in its real-time mode: a scan's query and
verification run in a worker thread while the next scans come in, and a closure enters the graph when it
completes, a few scans after its query scan (a loop factor between two poses already in the graph, which iSAM2
takes as any other). `finish` first waits for the worker and adds the closures still due. The closures are the
sequential mode's; the iSAM2 estimates along the way differ (the loops come later).

With ``keyframes`` (`placerec.keyframes.KeyframeParams`: a Livox-style or solid-state scanner's frames, each too
small a part of a place) the detector accumulates the scans into keyframes (`LoopClosureDetector`'s keyframe mode)
while the graph keeps a pose per scan: a keyframe is in the frame of its window's last scan, so a closure between
two keyframes is a loop factor between those two scans' poses. The loop factors and ``candidates`` are in scan
ids (a keyframe's candidates at its last scan); the exclusion limits count keyframes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Any

import numpy as np

from placerec.errors import ConfigError, ScanDataError
from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES
from placerec.eval.pose_error import full_pose_mask
from placerec.keyframes import KeyframeParams
from placerec.loop_closure import LoopClosureDetector
from placerec.odometry_gate import OdometryGateParams
from placerec.realtime import LateScanError, RealtimeParams
from placerec.slam.graph import GraphParams, LoopFactor, PoseGraph
from placerec.types import Candidate, Description, PlaceRecognizer, Scan

__all__ = ["OnlineSlam", "PlaceIds", "detect_closures", "finish_closures", "record_candidates"]

log = logging.getLogger(__name__)


def _usable(c: Candidate) -> bool:
    """A closure the graph can use: a 6-DoF ``relative_pose`` (not a yaw-only guess) that the pipeline's
    verification accepted (``Candidate.accepted``; None: the pipeline does not verify)."""
    if c.relative_pose is None or not full_pose_mask(c.relative_pose)[0]:
        return False
    return c.accepted is not False


def detect_closures(
    detector: LoopClosureDetector,
    scan: Scan | None,
    odometry_pose: np.ndarray,
    timestamp: float | None = None,
    description: Description | None = None,
) -> list[LoopFactor]:
    """Query with and add one scan (`LoopClosureDetector.process`); the accepted closures a pose graph can use
    (`_usable`) as loop factors, with the detector's ids. A scan the recognizer cannot describe (`ScanDataError`)
    is `LoopClosureDetector.skip`-ped: it takes its id, so ids stay the graph's keys, and gives no closure.
    A real-time detector returns the closures completed since the last call (earlier scans' too); a query that
    failed in its worker (`LateScanError`) is logged (that scan keeps its id and gets no closure, as a skipped
    one) and this scan fed again."""
    while True:
        try:
            accepted = detector.process(scan, odometry_pose, timestamp, description)
            break
        except LateScanError as exc:  # an earlier scan's; this one was left untouched
            log.warning("%s: that scan gets no loop closure", exc)
        except ScanDataError:
            detector.skip(odometry_pose, timestamp)
            accepted = []
            break
    return _loop_factors(accepted)


def finish_closures(detector: LoopClosureDetector) -> list[LoopFactor]:
    """The end of a stream: `LoopClosureDetector.close` (a real-time detector's worker finished and ended), the
    closures still due as loop factors; failed queries logged as in `detect_closures`."""
    accepted: list[Candidate] = []
    while True:
        try:
            accepted += detector.close()
            return _loop_factors(accepted)
        except LateScanError as exc:
            log.warning("%s: that scan gets no loop closure", exc)


def record_candidates(candidates: list[list[Any]], detector: LoopClosureDetector) -> None:
    """Keep ``candidates`` one list per place of the stream (``candidates[i]``: its place ``prior_entries + i``),
    filled in as the detector completes their queries (``last_completed``; a real-time detector's come late)."""
    candidates += [[] for _ in range(detector.n_processed - len(candidates))]
    for done in detector.last_completed:
        candidates[done.place_id - detector.prior_entries] = done.candidates


def _loop_factors(accepted: list[Candidate]) -> list[LoopFactor]:
    """The accepted closures a pose graph can use (`_usable`), as loop factors with the detector's ids."""
    return [
        LoopFactor(c.match_id, c.query_id, np.asarray(c.relative_pose, dtype=np.float64), float(c.score))
        for c in accepted
        if _usable(c)
    ]


class PlaceIds:
    """The graph's ids of a `LoopClosureDetector`'s places (module docstring): a prior map's entries (ids below
    ``detector.prior_entries``, P) keep theirs; the stream's own place ``P + k`` is the graph's pose ``P + s`` of the
    scan ``s`` it stands at: itself without keyframes, its window's last scan with them (the keyframe's frame)."""

    def __init__(self, detector: LoopClosureDetector) -> None:
        self.detector = detector
        self._place: dict[int, int] = {}  # graph id -> place id (with keyframes)

    def graph_id(self, place_id: int) -> int:
        """The graph's pose of the detector's place ``place_id``."""
        P = self.detector.prior_entries
        if self.detector.keyframes is None or place_id < P:
            return place_id
        gid = P + self.detector.keyframe_scans(place_id)[-1]
        self._place[gid] = place_id
        return gid

    def place_id(self, graph_id: int) -> int:
        """The detector's place a graph id stands for (one `graph_id` gave)."""
        return graph_id if self.detector.keyframes is None else self._place.get(graph_id, graph_id)

    def loops(self, loops: list[LoopFactor]) -> list[LoopFactor]:
        """The detector's loop factors between the graph's poses."""
        if self.detector.keyframes is None:
            return loops
        return [
            replace(lp, match_id=self.graph_id(lp.match_id), query_id=self.graph_id(lp.query_id))
            for lp in loops
        ]

    def completed(self) -> list[list[Candidate]]:
        """The candidates of the queries the detector's last call completed (``last_completed``), one list a query,
        in the graph's ids."""
        out = []
        for done in self.detector.last_completed:
            at = self.graph_id(done.place_id)
            out.append([replace(c, query_id=at, match_id=self.graph_id(c.match_id)) for c in done.candidates])
        return out

    def record(self, candidates: list[list[Any]], n_scans: int) -> None:
        """``candidates`` one list per scan of the stream's ``n_scans``; with keyframes a keyframe's candidates (in
        the graph's ids) at its scan, the other scans' lists empty."""
        if self.detector.keyframes is None:
            record_candidates(candidates, self.detector)
            return
        P = self.detector.prior_entries
        candidates += [[] for _ in range(n_scans - len(candidates))]
        for cands in self.completed():
            if cands:
                candidates[cands[0].query_id - P] = cands

    def check_description(self, description: Description | None) -> None:
        """`ConfigError` for a ``description`` given with keyframes (they are built from scans)."""
        if description is not None and self.detector.keyframes is not None:
            raise ConfigError(
                "process(description=...): with keyframes give the scan (descriptions do not accumulate)"
            )


class OnlineSlam:
    """Loop closure + pose graph for a stream of scans with odometry (see the module docstring).

    ``threshold``: verified score from which a closure is accepted (closures without a 6-DoF pose, or that the
    pipeline's verification rejected, never enter the graph); ``k``: closures accepted per scan at most;
    the exclusion limits are those of `LoopClosureDetector`; ``graph``: `GraphParams`; ``realtime``: the
    detector's real-time mode (module docstring; None: sequential); ``odometry_gate``: the detector's check of
    each closure against the odometry poses given to `process` (`placerec.odometry_gate`; None: off); ``keyframes``:
    places accumulated from several scans (module docstring; None: each scan a place). ``candidates[i]``: scan i's
    candidates (in real-time mode filled in when its query completes).
    """

    def __init__(
        self,
        recognizer: PlaceRecognizer,
        threshold: float,
        graph: GraphParams | None = None,
        exclusion_frames: int | None = DEFAULT_EXCLUSION_FRAMES,
        exclusion_seconds: float | None = None,
        exclusion_metres: float | None = None,
        k: int = 1,
        realtime: RealtimeParams | None = None,
        odometry_gate: OdometryGateParams | None = None,
        keyframes: KeyframeParams | None = None,
    ) -> None:
        self.detector = LoopClosureDetector(
            recognizer,
            threshold,
            exclusion_frames,
            exclusion_seconds,
            exclusion_metres,
            k=k,
            realtime=realtime,
            odometry_gate=odometry_gate,
            keyframes=keyframes,
        )
        self.ids = PlaceIds(self.detector)
        self.graph = PoseGraph(graph or GraphParams())
        self.loops: list[LoopFactor] = []
        self.last_timing_ms: dict[str, float] = {}
        self.candidates: list[list[Any]] = []

    def process(
        self,
        scan: Scan | None,
        odometry_pose: np.ndarray,
        timestamp: float | None = None,
        description: Description | None = None,
        extra_loops: list[LoopFactor] | None = None,
    ) -> list[LoopFactor]:
        """Add the next scan with its odometry pose ``T_world_sensor``; returns the loop factors added for it
        (real-time mode: those completed since the last call, of this scan or earlier ones).

        A scan the recognizer cannot describe (`ScanDataError`) still gets its pose and odometry factor, but is
        never queried or matched. With keyframes the scan itself is needed (`ConfigError` for a ``description``:
        a description does not accumulate)."""
        self.ids.check_description(description)
        added = self.ids.loops(detect_closures(self.detector, scan, odometry_pose, timestamp, description))
        timing = dict(self.detector.last_timing_ms)  # empty for a skipped scan
        self.ids.record(self.candidates, self.graph.n_poses + 1)  # this scan's pose is added next
        t0 = time.perf_counter()
        self.graph.add_pose(odometry_pose)
        added += list(extra_loops or [])
        for loop in added:
            self.graph.add_loop(loop)
        self.loops.extend(added)
        timing["graph"] = (time.perf_counter() - t0) * 1e3
        timing["isam2"] = self.graph.update()
        self.last_timing_ms = timing
        return added

    @property
    def n_scans(self) -> int:
        return self.graph.n_poses

    def poses(self) -> np.ndarray:
        """The current (iSAM2) estimate of every pose so far, (N, 4, 4)."""
        return self.graph.poses()

    def finish(self) -> np.ndarray:
        """The final batch optimisation (`GraphParams.batch`); details in ``batch_info``. A real-time detector's
        closures still due are added first (one more iSAM2 update), and its worker ended."""
        late = self.ids.loops(finish_closures(self.detector))
        self.ids.record(self.candidates, self.graph.n_poses)
        if late:
            for loop in late:
                self.graph.add_loop(loop)
            self.loops.extend(late)
            self.graph.update()
        poses, self.batch_info = self.graph.optimize()
        return poses
