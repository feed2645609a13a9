"""Multi-session SLAM: a new session's scans against a prior map, joined to it only when the overlap is certain.

>>> from placerec.maps import MapArtifact
>>> from placerec.slam import MultiSessionSlam
>>> m = MapArtifact.open("town_map")                                                   # doctest: +SKIP
>>> slam = MultiSessionSlam(m.recognizer(), 0.25, m.poses)                             # doctest: +SKIP
>>> for scan, odom in stream:                                                          # doctest: +SKIP
...     slam.process(scan, odom)             # odometry in the session's own frame
>>> result = slam.finish()                   # result.joined, result.T_map_session, result.summary()  # doctest: +SKIP

The recognizer already holds the prior map's M places under ids 0..M-1 (a loaded map's database); the session's
scans get ids M, M+1, ... (`LoopClosureDetector` with ``prior_entries=M``: the exclusion window counts only the
session's own scans, the map's places are always eligible). A closure whose match is a map place is
**inter-session**. The session runs in two phases:

1. **Separate** (until the join): the session is its own pose graph in its own frame, exactly as `OnlineSlam`
   (a tight prior on its first odometry pose, odometry factors, intra-session loops, iSAM2 per scan). Its
   inter-session closures (verified, accepted, a 6-DoF pose: `placerec.slam.online.detect_closures`) are kept
   **pending**, out of any graph. Each implies where the session lies in the map:
   ``T_map_session = T_world_match (map) @ T_match_query @ inv(T_session_query)`` (the query's current estimate).
2. **Joined**: once ``min_join_loops`` pending closures, from at least 2 different query scans, agree with each
   other, the sessions are joined. Two closures *agree* when each one's alignment puts the other's query pose
   within ``join_translation_m`` / ``join_rotation_deg`` of where the other closure itself puts it in the map
   (comparing the alignments at the queries, not their translations, so a small rotation about a far origin is
   not taken for a disagreement); the largest set of mutually agreeing closures is kept (greedy, from the closure
   with the most agreements). A single closure, true or false, never joins two sessions; a session that never
   overlaps the map stays separate (`MultiSessionResult.summary`: "sessions never overlapped: kept separate").

On the join one GTSAM graph is built (`PoseGraph`; keys: **the detector's ids**, map poses 0..M-1 and session
scan ``s`` at key M+s, so a closure's ids are its factor's keys): the prior map's poses at their map values, with
``anchor="fixed"`` a tight prior on every one (the map does not move) or with ``"anchored"`` a tight prior on map
pose 0 only and the map's own odometry and loop factors (``prior_odometry``, ``prior_loops``) holding the rest,
so closures may move the map within its covariance; then the session's poses at ``T_map_session @`` their current
estimates, its odometry and intra-session loop factors, **no prior** on its first pose, and every agreeing
inter-session closure as a robust loop factor. The closures that did not agree are reported as rejected at the
join and never enter the graph. After the join every new closure, intra- or inter-session, goes straight into the
graph (robust kernel online; the batch at `finish` is `GraphParams.batch`, GNC by default, which can still
reject any loop factor).

With ``odometry_gate`` (`placerec.odometry_gate`) the session's own closures are checked against its odometry by
the detector, and after the join the inter-session ones against the **joined estimate**: a closure must put its
query within the gate's bounds of where the joined graph has it, ``inv(T_map_match) @ T_map_query``, with ``L`` the
session's odometry path from the nearest session scan already tied to the map by an inter-session loop in the
graph (the query's estimate can have drifted from the map only since then). A refused closure never enters the
graph (``refused_by_gate``). Before the join there is no common frame: the join's consensus test stands in.

With ``keyframes`` (`placerec.keyframes.KeyframeParams`, as in `placerec.slam.online`) the session's places are
keyframes of its scans while the graph keeps a pose a scan: a closure's ids are turned into the graph's keys
(`placerec.slam.online.PlaceIds`: a session keyframe at its window's last scan, a map place as it is).

The session's places enter the recognizer with their odometry poses, in the session's frame: pipelines that use
entry poses (local-map verification of the 3D pipelines) would mix the two frames; ORB-HBST and Scan Context do
not use them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from placerec.errors import ConfigError, ScanDataError
from placerec.eval.exclusion import DEFAULT_EXCLUSION_FRAMES
from placerec.eval.pose_error import pose_errors
from placerec.keyframes import KeyframeParams
from placerec.loop_closure import LoopClosureDetector
from placerec.odometry_gate import OdometryGateParams, odometry_disagreement
from placerec.realtime import RealtimeParams
from placerec.slam.graph import GraphParams, LoopFactor, PoseGraph
from placerec.slam.online import PlaceIds, detect_closures, finish_closures
from placerec.types import Candidate, Description, PlaceRecognizer, Scan, rigid_problem

__all__ = ["MultiSessionSlam", "MultiSessionResult", "Anchor", "OdometryFactor"]

log = logging.getLogger(__name__)

Anchor = Literal["fixed", "anchored"]
#: A prior map's odometry factor: (i, j, T_ij, sigmas (6,): rotation (rad) then translation (m)).
OdometryFactor = tuple[int, int, np.ndarray, np.ndarray]


@dataclass
class MultiSessionResult:
    """What `MultiSessionSlam.finish` produced. Loop ids are the detector's: map places 0..M-1, the session's
    scan ``s`` is M+s (``session_poses[s]``).

    ``joined``: whether the session was joined to the map; then ``session_poses`` (N, 4, 4) and ``map_poses``
    (M, 4, 4; moved by the closures with ``anchor="anchored"``) are in the map's frame, and ``T_map_session`` maps
    the session's odometry frame into it (from the batch solution: the session's first pose solved, times the
    inverse of its first odometry pose). Not joined: ``session_poses`` are in the session's own frame, ``map_poses``
    the prior map's as given, ``T_map_session`` None. ``inter_loops``: the inter-session closures in the graph,
    with ``inter_weights`` (the batch's weight of each: below 0.5 the back end rejected it);
    ``rejected_at_join``: closures that disagreed with the join's consensus; ``pending``: the inter-session
    closures of a session never joined (kept out of any graph); ``refused_by_gate``: inter-session closures after
    the join that the odometry gate refused against the joined estimate (kept out of the graph); ``joined_at``:
    the session scan whose closure completed the join. ``batch``: `PoseGraph.optimize`'s info, its loop lists
    aligned with ``graph.loops``.
    """

    joined: bool
    T_map_session: np.ndarray | None
    session_poses: np.ndarray
    map_poses: np.ndarray
    intra_loops: list[LoopFactor]
    inter_loops: list[LoopFactor]
    inter_weights: list[float]
    rejected_at_join: list[LoopFactor]
    pending: list[LoopFactor]
    joined_at: int | None
    batch: dict[str, Any]
    graph: PoseGraph
    anchor: Anchor = "fixed"
    refused_by_gate: list[LoopFactor] = field(default_factory=list)
    rejected_by_graph: int = field(init=False)

    def __post_init__(self) -> None:
        self.rejected_by_graph = sum(w < 0.5 for w in self.inter_weights)

    @property
    def frame(self) -> Literal["map", "session"]:
        """The frame of ``session_poses``."""
        return "map" if self.joined else "session"

    def summary(self) -> str:
        """One line for a report: joined (how, with which closures) or kept separate (why)."""
        if self.joined:
            return (
                f"joined to the prior map ({self.anchor}) at session scan {self.joined_at}: "
                f"{len(self.inter_loops)} inter-session loops in the graph ({self.rejected_by_graph} rejected by "
                f"the graph), {len(self.rejected_at_join)} rejected at the join"
                + (
                    f", {len(self.refused_by_gate)} refused by the odometry gate"
                    if self.refused_by_gate
                    else ""
                )
            )
        if not self.pending:
            return "sessions never overlapped: kept separate (no inter-session closure)"
        return (
            f"sessions never overlapped: kept separate ({len(self.pending)} inter-session closures, "
            "too few that agree with each other to join)"
        )


class MultiSessionSlam:
    """A new session's loop closure and pose graph against a prior map (see the module docstring).

    ``recognizer`` holds the prior map's places under ids 0..M-1, ``prior_poses`` (M, 4, 4) their poses
    ``T_world_keyframe`` in the map's frame (rigid, finite: else `ScanDataError` naming the pose).
    ``threshold``, ``graph``, the exclusion limits and ``k`` are `OnlineSlam`'s. ``anchor``: ``"fixed"`` (every
    map pose held by a tight prior; ``prior_odometry`` / ``prior_loops`` unused) or ``"anchored"`` (map pose 0
    held; the map's own factors, which must connect every map pose to pose 0, hold the rest: `ConfigError`
    otherwise). ``min_join_loops`` (>= 2), ``join_translation_m``, ``join_rotation_deg``: the join's consistency
    test. The map's part of the graph is built (and its factors checked) here; it is solved at the join.
    ``realtime``: the detector's real-time mode (`placerec.slam.online`): closures arrive a few scans late and are
    routed as they come; `finish` waits for the rest. The closures are the sequential mode's, but the join is
    tested on the estimates of when they arrive, so it may happen at another scan. ``odometry_gate``: the
    detector's check of the session's own closures against its odometry and, after the join, of the inter-session
    closures against the joined estimate (module docstring; None: off).
    """

    def __init__(
        self,
        recognizer: PlaceRecognizer,
        threshold: float,
        prior_poses: np.ndarray,
        graph: GraphParams | None = None,
        exclusion_frames: int | None = DEFAULT_EXCLUSION_FRAMES,
        exclusion_seconds: float | None = None,
        exclusion_metres: float | None = None,
        k: int = 1,
        prior_odometry: list[OdometryFactor] | None = None,
        prior_loops: list[LoopFactor] | None = None,
        anchor: Anchor = "fixed",
        min_join_loops: int = 2,
        join_translation_m: float = 1.0,
        join_rotation_deg: float = 5.0,
        realtime: RealtimeParams | None = None,
        odometry_gate: OdometryGateParams | None = None,
        keyframes: KeyframeParams | None = None,
    ) -> None:
        if anchor not in ("fixed", "anchored"):
            raise ConfigError(f"anchor must be 'fixed' or 'anchored', got {anchor!r}")
        if min_join_loops < 2:
            raise ConfigError(
                f"min_join_loops must be >= 2 (one closure cannot be checked against another), got {min_join_loops}"
            )
        for name, value in (
            ("join_translation_m", join_translation_m),
            ("join_rotation_deg", join_rotation_deg),
        ):
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be finite and > 0, got {value}")
        self.prior_poses = _checked_prior_poses(prior_poses)
        self.n_map = M = len(self.prior_poses)
        self.anchor: Anchor = anchor
        self.min_join_loops = int(min_join_loops)
        self.join_translation_m = float(join_translation_m)
        self.join_rotation_deg = float(join_rotation_deg)
        self.params = graph or GraphParams()
        self.detector = LoopClosureDetector(
            recognizer, threshold, exclusion_frames, exclusion_seconds, exclusion_metres, k=k, prior_entries=M,
            realtime=realtime, odometry_gate=odometry_gate, keyframes=keyframes,
        )  # fmt: skip
        self.ids = PlaceIds(self.detector)  # graph ids: map places 0..M-1, then M + the session's scan
        self._scans = 0
        self._map = self._map_graph(prior_odometry or [], prior_loops or [])
        self.session = PoseGraph(self.params)  # the session in its own frame, keys 0..N-1 (detector ids - M)
        self.graph = self.session  # the graph new scans go into: the joined one after the join
        self.joined = False
        self.joined_at: int | None = None
        self.T_map_session: np.ndarray | None = None  # the alignment the join used
        self.intra_loops: list[LoopFactor] = []
        self.inter_loops: list[LoopFactor] = []
        self.pending: list[LoopFactor] = []
        self.rejected_at_join: list[LoopFactor] = []
        self.odometry_gate = odometry_gate
        self.refused_by_gate: list[LoopFactor] = []
        self._tied: set[int] = set()  # session scans (detector ids) with an inter-session loop in the graph
        self.candidates: list[list[Candidate]] = []
        self.last_timing_ms: dict[str, float] = {}

    def _map_graph(self, odometry: list[OdometryFactor], loops: list[LoopFactor]) -> PoseGraph:
        """The prior map's part of the joined graph (poses 0..M-1, priors, and with ``anchored`` its factors)."""
        g = PoseGraph(self.params)
        fixed = self.anchor == "fixed"
        for i, T in enumerate(self.prior_poses):
            g.add_free_pose(T, prior=fixed or i == 0)
        if fixed:
            return g
        for n, (i, j, T_ij, sigmas) in enumerate(odometry):
            try:
                g.add_odometry(int(i), int(j), T_ij, sigmas)
            except ScanDataError as exc:
                raise ScanDataError(f"prior map odometry factor {n}: {exc}") from None
        for lp in loops:
            if max(lp.match_id, lp.query_id) >= self.n_map or min(lp.match_id, lp.query_id) < 0:
                raise ScanDataError(
                    f"prior map loop {lp.match_id} -> {lp.query_id}: ids must be map poses 0..{self.n_map - 1}"
                )
            g.add_loop(lp)
        _require_connected(
            self.n_map, [(i, j) for i, j, _, _ in g.odometry] + [(lp.match_id, lp.query_id) for lp in g.loops]
        )
        return g

    @property
    def n_scans(self) -> int:
        """The session's scans so far."""
        return self._scans

    def process(
        self,
        scan: Scan | None,
        odometry_pose: np.ndarray,
        timestamp: float | None = None,
        description: Description | None = None,
        extra_loops: list[LoopFactor] | None = None,
    ) -> list[LoopFactor]:
        """Add the session's next scan with its odometry pose (``T_session_sensor``, the session's own frame);
        returns its closures (intra- and inter-session, detector ids), in the graph or, before the join, the
        inter-session ones pending. ``extra_loops`` (e.g. injected false loops) are routed the same way. A scan the
        recognizer cannot describe still gets its pose. Stage times (ms) in ``last_timing_ms`` (``join``: the
        consistency test and, when it succeeds, building the joined graph)."""
        self.ids.check_description(description)
        added = self.ids.loops(detect_closures(self.detector, scan, odometry_pose, timestamp, description))
        timing = dict(self.detector.last_timing_ms)
        self._scans += 1
        self.ids.record(self.candidates, self._scans)
        t0 = time.perf_counter()
        self.graph.add_pose(odometry_pose)
        added += list(extra_loops or [])
        self._route(added, timing, t0)
        self.last_timing_ms = timing
        return added

    def _route(self, added: list[LoopFactor], timing: dict[str, float], t0: float) -> None:
        """``added`` into the graph (intra-session, or anything once joined) or pending (inter-session before the
        join, which is then tried); iSAM2 updated; stage times into ``timing``."""
        inter = [lp for lp in added if self._is_inter(lp)]
        intra = [lp for lp in added if lp.match_id >= self.n_map]
        if self.joined:
            refused = self._refused(inter)
            inter = [lp for lp in inter if id(lp) not in refused]
            for lp in added:  # keys are the detector's ids
                if id(lp) not in refused:
                    self.graph.add_loop(lp)
            self.refused_by_gate += [lp for lp in added if id(lp) in refused]
            self.inter_loops += inter
            self._tied.update(lp.query_id for lp in inter)
        else:
            M = self.n_map
            for lp in intra:
                self.session.add_loop(replace(lp, match_id=lp.match_id - M, query_id=lp.query_id - M))
        self.intra_loops += intra
        timing["graph"] = (time.perf_counter() - t0) * 1e3
        timing["isam2"] = self.graph.update()
        if inter and not self.joined:
            t0 = time.perf_counter()
            self.pending += inter
            self._try_join(max(lp.query_id for lp in inter) - self.n_map)
            timing["join"] = (time.perf_counter() - t0) * 1e3

    def _refused(self, inter: list[LoopFactor]) -> set[int]:
        """The ``id``s of the inter-session closures (after the join) that the odometry gate refuses against the
        joined estimate (module docstring); empty without a gate."""
        if self.odometry_gate is None or not inter:
            return set()
        M = self.n_map
        # the session's odometry path (the detector's) at its tied scans and at each closure's query
        tied = self.detector.path_at(self.ids.place_id(i) - M for i in self._tied)
        trans, rot = odometry_disagreement(
            np.stack([lp.T_match_query for lp in inter]),
            np.stack([self.graph.pose(lp.match_id) for lp in inter]),
            np.stack([self.graph.pose(lp.query_id) for lp in inter]),
        )
        at = self.detector.path_at(self.ids.place_id(lp.query_id) - M for lp in inter)
        since = np.abs(tied[None, :] - at[:, None]).min(axis=1)
        ok = self.odometry_gate.admits(trans, rot, since)
        return {id(lp) for lp, good in zip(inter, ok, strict=True) if not good}

    def _is_inter(self, lp: LoopFactor) -> bool:
        """Whether ``lp`` (detector ids) is inter-session; `ScanDataError` unless its query is one of the session's
        scans so far and its match another pose (a map place or an older session scan)."""
        M, n = self.n_map, self.n_map + self.n_scans
        if not (M <= lp.query_id < n) or not (0 <= lp.match_id < n) or lp.match_id == lp.query_id:
            raise ScanDataError(
                f"loop {lp.match_id} -> {lp.query_id}: the query must be one of this session's scans "
                f"(ids {M}..{n - 1}) and the match another pose (map places 0..{M - 1}, or a session scan)"
            )
        return lp.match_id < M

    def _alignments(self, loops: list[LoopFactor]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each inter-session loop: its query's pose in the map by the closure (``T_world_match @
        T_match_query``), the query's current estimate in the session's frame, and the alignment
        ``T_map_session`` they imply; each (L, 4, 4)."""
        M = self.n_map
        in_map = np.stack([self.prior_poses[lp.match_id] @ lp.T_match_query for lp in loops])
        in_session = np.stack([self.session.pose(lp.query_id - M) for lp in loops])
        return in_map, in_session, in_map @ np.linalg.inv(in_session)

    def _agreeing(self) -> tuple[list[int], np.ndarray]:
        """The largest set of pending closures (indices) that agree pairwise (module docstring), greedy, and the
        alignment ``T_map_session`` each pending closure implies (P, 4, 4)."""
        in_map, in_session, align = self._alignments(self.pending)
        L = len(self.pending)
        # predicted[b, a]: where closure b's alignment puts closure a's query, against a's own map pose
        predicted = np.einsum("bij,ajk->baik", align, in_session).reshape(-1, 4, 4)
        own = np.broadcast_to(in_map[None], (L, L, 4, 4)).reshape(-1, 4, 4)
        dt, dr = (e.reshape(L, L) for e in pose_errors(predicted, own))
        close = (dt <= self.join_translation_m) & (dr <= self.join_rotation_deg)
        agree = close & close.T
        best: list[int] = []
        for seed in np.argsort(-agree.sum(axis=1), kind="stable"):
            group = [int(seed)]
            for b in np.flatnonzero(agree[seed]):
                if b != seed and agree[b, group].all():
                    group.append(int(b))
            if len(group) > len(best):
                best = group
        return best, align

    def _try_join(self, latest: int) -> None:
        """Join the sessions if enough pending closures agree (module docstring); ``latest``: the session scan of
        the newest closure (the join's ``joined_at``)."""
        group, align = self._agreeing()
        queries = {self.pending[i].query_id for i in group}
        if len(group) < self.min_join_loops or len(queries) < 2:
            return
        joined = self._map
        joined.add_graph(self.session, transform=align[group[0]], priors=False)
        for i in group:
            joined.add_loop(self.pending[i])
        joined.update()
        self.graph, self.joined = joined, True
        self.T_map_session = align[group[0]]
        self.joined_at = latest
        self.inter_loops = [self.pending[i] for i in group]
        self._tied = {lp.query_id for lp in self.inter_loops}
        kept = set(group)
        self.rejected_at_join = [lp for i, lp in enumerate(self.pending) if i not in kept]
        self.pending = []
        log.info(
            "session joined to the prior map at scan %d: %d agreeing inter-session closures, %d rejected",
            self.joined_at,
            len(group),
            len(self.rejected_at_join),
        )

    def poses(self) -> np.ndarray:
        """The session's current (iSAM2) poses (N, 4, 4): in the map's frame once joined, else its own."""
        return self.graph.poses()[self.n_map :] if self.joined else self.graph.poses()

    def finish(self) -> MultiSessionResult:
        """The final batch optimisation (`GraphParams.batch`) of the joined graph, or of the session alone when it
        was never joined; see `MultiSessionResult`. A real-time detector's closures still due are routed first."""
        late = self.ids.loops(finish_closures(self.detector))
        self.ids.record(self.candidates, self._scans)
        if late:
            self._route(late, {}, time.perf_counter())
        poses, info = self.graph.optimize()
        M = self.n_map
        if not self.joined:
            return MultiSessionResult(
                False, None, poses, self.prior_poses.copy(), list(self.intra_loops), [], [], [],
                list(self.pending), None, info, self.graph, self.anchor,
            )  # fmt: skip
        weights = info.get("loop_weights", [1.0] * len(self.graph.loops))
        inter_weights = [
            float(w)
            for lp, w in zip(self.graph.loops, weights, strict=True)
            if lp.match_id < M <= lp.query_id
        ]
        first = self.session.prior
        assert first is not None  # the session's first add_pose set it
        T_map_session = poses[M] @ np.linalg.inv(first)
        return MultiSessionResult(
            True, T_map_session, poses[M:], poses[:M], list(self.intra_loops), list(self.inter_loops),
            inter_weights, list(self.rejected_at_join), [], self.joined_at, info, self.graph, self.anchor,
            list(self.refused_by_gate),
        )  # fmt: skip


def _checked_prior_poses(prior_poses: np.ndarray) -> np.ndarray:
    """``prior_poses`` as (M, 4, 4) float64 rigid motions, M >= 1; `ScanDataError` naming the first that is not."""
    P = np.asarray(prior_poses, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape[0] == 0:
        raise ScanDataError(f"prior map poses must be (M, 4, 4) with M >= 1, got shape {P.shape}")
    problem = rigid_problem(P)
    if problem is not None:
        raise ScanDataError(f"prior map pose {problem[0]} is no rigid motion: {problem[1]}")
    return P


def _require_connected(n: int, edges: list[tuple[int, int]]) -> None:
    """`ConfigError` unless the factors ``edges`` connect every map pose to pose 0 (``anchor="anchored"``: a pose
    they do not reach would be held by nothing)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    adjacency = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    loose = np.flatnonzero(labels != labels[0])
    if loose.size:
        raise ConfigError(
            f"anchor 'anchored': prior map pose {int(loose[0])} ({loose.size} poses in all) is not connected to "
            "pose 0 by the map's odometry and loop factors; give the map's factors (prior_odometry, prior_loops) "
            "or use anchor='fixed'"
        )
