"""Relocalisation against a map artifact (`placerec.maps.artifact`): where is this scan in the map?

`Localizer` answers a scan with a `Fix`: the scan's pose ``T_world_query`` in the map frame, accepted or not and
why, the keyframe it was verified against, how many candidates were tried and the time of each stage. It only
*queries* the map: the pipelines' databases are never added to (a query that does not insert), the keyframe
clouds are read from their memory map.

Two ways to find a fix, tried in this order:

* **tracking** (when a prior pose is known): ICP of the scan onto the stored clouds of the ``max_keyframes``
  keyframes nearest to the prior (within ``radius_m``), each started from the prior
  (``T_keyframe_query = inv(T_world_keyframe) @ prior``), accepted by the tracking verification's rule
  (`placerec.verify.score`) and refused when it moves the prior by more than ``max_correction_m`` /
  ``max_correction_deg`` (reason ``jump``): a prior is trusted only to that much. Milliseconds. With
  ``icp_moves: keyframe`` the keyframe's cloud is registered onto the scan instead, so the overlap is judged over
  the keyframe's voxels: for scans denser than the map's clouds (another sensor's), whose own voxels overlap a
  sparse keyframe little even at the right pose.
* **global search**: the map pipeline's ``query_description`` over every keyframe (``k`` candidates, verified by
  the pipeline itself); the best *accepted* candidate scoring at least the threshold gives
  ``T_world_query = T_world_keyframe @ T_keyframe_query``. A rejected candidate is no answer, never a fix; with
  ``ambiguity.max_ratio`` neither is a fix that another accepted candidate, placing the scan elsewhere in the map,
  nearly matches (`placerec.verify.ambiguity`; reason ``ambiguous``).

`Localizer.localize` is stateless (a prior in, a fix out); `Localizer.track` keeps the last fix and predicts the
next prior from the caller's odometry (or a constant velocity), falling back to global search after
``fail_after`` tracking failures in a row (a kidnapped robot), `Localizer.reset` forgets it all.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from placerec.errors import ScanDataError
from placerec.eval.pose_error import pose_errors
from placerec.maps.artifact import MapArtifact, MapPipeline
from placerec.params import Params
from placerec.preprocess import preprocess_scan
from placerec.types import (
    Candidate,
    PlaceRecognizer,
    Scan,
    Verification,
    as_pose,
    interpolate_trajectory,
    valid_points,
)
from placerec.verify import IcpCloud, as_source, as_target, verify_icp
from placerec.verify.ambiguity import AmbiguityParams, runner_up_ratio
from placerec.verify.params import IcpParams, ScoreParams, VerifyParams

__all__ = ["TrackingParams", "LocalizerParams", "Fix", "Localizer", "correction", "search_pipelines"]


def _tracking_verify() -> VerifyParams:
    """ICP from a prior that is right to a metre or two: one coarse stage at 2 m, then the 1 m gate, 20 iterations
    each; accepted when the verified score reaches 0.2 and at least 40 % of the scan's voxels overlap the keyframe.
    On the simulator's tuning seed (docs/maps.md, 'Relocalisation') correct fixes scored >= 0.27 with fitness
    >= 0.62 from priors up to 2 m / 10 deg off, ICP onto the wrong place <= 0.08 with fitness <= 0.19."""
    return VerifyParams(
        icp=IcpParams(max_iterations=20),
        score=ScoreParams(min_score=0.2, min_fitness=0.4),
        icp_only_coarse_distances=[2.0],
    )


class TrackingParams(Params):
    """Tracking: verify the scan against the map's keyframes near a prior pose."""

    radius_m: float = Field(15.0, gt=0, description="m; keyframes searched around the prior's position")
    max_keyframes: int = Field(2, ge=1, le=100, description="nearest keyframes tried, nearest first")
    verify: VerifyParams = Field(
        default_factory=_tracking_verify,
        description="ICP-only verification from the prior and its acceptance (score, min_fitness)",
    )
    max_correction_m: float = Field(
        2.0, gt=0, description="m; a fix moving the prior farther than this is refused (reason 'jump')"
    )
    max_correction_deg: float = Field(
        10.0, gt=0, le=180, description="deg; a fix turning the prior more than this is refused ('jump')"
    )
    icp_moves: Literal["scan", "keyframe"] = Field(
        "scan",
        description="which cloud ICP moves: the scan onto the keyframe's cloud (the overlap judged over the "
        "scan's voxels), or the keyframe's cloud onto the scan (over the keyframe's): for scans denser than "
        "the map's clouds, e.g. another sensor's (docs/maps.md)",
    )
    fail_after: int = Field(
        1, ge=1, le=1000, description="tracking failures in a row before track() falls back to global search"
    )
    cached_keyframes: int = Field(
        32, ge=1, le=100_000, description="prepared keyframe clouds kept (least recently used dropped)"
    )


class LocalizerParams(Params):
    """Everything `Localizer` uses (``placerec localize --set key=value`` sets them)."""

    pipeline: str | None = Field(
        None,
        description="the map pipeline for global search (None: each of the map's pipelines in turn, in the"
        " map's order, until one gives a fix)",
    )
    k: int = Field(5, ge=1, le=1000, description="candidates per global query")
    threshold: float | None = Field(
        None, description="global fixes score at least this (None: each map pipeline's operating threshold)"
    )
    tracking: TrackingParams = Field(default_factory=TrackingParams)
    ambiguity: AmbiguityParams = Field(
        default_factory=AmbiguityParams,
        description="global search refuses a fix another place nearly matches (placerec.verify.ambiguity; off)",
    )
    allow_other_sensor: bool = Field(
        False, description="localise scans of another sensor than the map's (refused by default)"
    )


@dataclass(frozen=True, eq=False)
class Fix:
    """The answer to one scan.

    ``T_world_query``: the scan's pose in the map (4x4), None unless ``accepted``. ``mode``: the stage that gave
    the answer (``tracking`` or ``global``; a global fallback after a failed tracking attempt is ``global``).
    ``reason``: ``ok``, or why there is no fix (e.g. ``no keyframe within 15 m``, ``rejected: low fitness 0.31``,
    ``jump 3.2 m``, ``no candidate``, ``below threshold``). ``keyframe_id``: the keyframe the answer was verified
    against (-1: none); ``score`` / ``fitness``: its verified score and ICP overlap (NaN: none).
    ``candidates_tried``: keyframes verified by tracking plus candidates examined by global search. ``time_ms``:
    the whole call; ``timing_ms``: per stage (``preprocess``, ``prepare``, ``tracking``, ``describe``,
    ``query``)."""

    T_world_query: np.ndarray | None
    accepted: bool
    mode: Literal["tracking", "global"]
    reason: str
    keyframe_id: int = -1
    score: float = float("nan")
    fitness: float = float("nan")
    candidates_tried: int = 0
    time_ms: float = 0.0
    timing_ms: dict[str, float] = field(default_factory=dict)


def search_pipelines(map: MapArtifact, params: LocalizerParams) -> list[MapPipeline]:
    """The map pipelines global search asks, in order: ``params.pipeline``, or every pipeline of the map."""
    name = params.pipeline
    return list(map.manifest.pipelines) if name is None else [map.pipeline(name)]


def correction(T_prior: np.ndarray, T_fix: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) that ``T_fix`` moves and turns ``T_prior`` by (`pose_errors` of one pose)."""
    metres, degrees = pose_errors(T_fix, T_prior)
    return float(metres[0]), float(degrees[0])


class Localizer:
    """Localise scans in ``map`` (a `MapArtifact` or its folder) with ``params`` (module docstring).

    Raw scans are preprocessed as the map's were (its manifest's ``preprocess``); a scan from another sensor
    than the map's is a `placerec.maps.artifact.MapMismatchError` unless ``params.allow_other_sensor``. The global
    search pipeline's database is loaded here (a damaged one fails before any scan); keyframe clouds as needed."""

    def __init__(self, map: MapArtifact | str | Path, params: LocalizerParams | None = None) -> None:
        self.map = map if isinstance(map, MapArtifact) else MapArtifact.open(map)
        self.params = params or LocalizerParams()
        pipes = search_pipelines(self.map, self.params)
        t = self.params.threshold
        #: (pipeline, its database, its threshold) for global search, in the order they are asked; the databases
        #: are loaded now, so a damaged one fails here, before any scan
        self.searches = [(p, self.map.recognizer(p.name), t if t is not None else p.threshold) for p in pipes]
        self.preprocess = self.map.preprocess()
        self._clouds: OrderedDict[tuple[int, str], IcpCloud | None] = OrderedDict()
        self._sensors_checked: set[str] = set()
        self.reset()

    # -- state of track() -------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the tracked state (a new start, a kidnap): the next `track` searches globally."""
        self._scan = 0  # scans seen by track()
        self._fixes: list[
            tuple[int, np.ndarray, np.ndarray | None]
        ] = []  # (scan, T_world, odometry) of the last 2
        self._failures = 0

    def prior(self, odometry_pose: np.ndarray | None = None) -> np.ndarray | None:
        """The pose `track` predicts for its next scan: the last fix moved by the odometry since then (with
        ``odometry_pose``, the caller's ``T_odom_scan``), else by the velocity between the last two fixes; None
        before the first fix."""
        if not self._fixes:
            return None
        k, T, odo = self._fixes[-1]
        if odometry_pose is not None and odo is not None:
            return T @ np.linalg.inv(odo) @ as_pose(odometry_pose, "odometry_pose")
        if len(self._fixes) < 2:
            return T
        (k0, T0, _), at = self._fixes[0], np.array([float(self._scan)])
        return interpolate_trajectory(np.array([float(k0), float(k)]), np.stack([T0, T]), at)[0]

    def track(self, scan: Scan, odometry_pose: np.ndarray | None = None) -> Fix:
        """Localise the next scan of a drive: tracking from the predicted pose (`prior`), global search when
        there is no prior yet or tracking failed ``fail_after`` times in a row."""
        odo = None if odometry_pose is None else as_pose(odometry_pose, "odometry_pose")
        prior = self.prior(odo)
        fallback = prior is None or self._failures + 1 >= self.params.tracking.fail_after
        fix = self._localize(scan, prior, allow_global=fallback)
        if fix.accepted:
            assert fix.T_world_query is not None
            # a velocity spans two fixes of one track: a global fix (a new start, maybe after a kidnap) starts one
            kept = self._fixes[-1:] if fix.mode == "tracking" else []
            self._fixes = [*kept, (self._scan, fix.T_world_query, odo)]
            self._failures = 0
        else:
            self._failures += 1
        self._scan += 1
        return fix

    # -- one scan ---------------------------------------------------------------------------------------------
    def localize(self, scan: Scan, prior: np.ndarray | None = None) -> Fix:
        """The fix of one raw ``scan``: tracking from ``prior`` (a guess of ``T_world_query``) when given, then
        global search if that fails or there is no prior (module docstring)."""
        return self._localize(scan, None if prior is None else as_pose(prior, "prior"), allow_global=True)

    def _localize(self, raw: Scan, prior: np.ndarray | None, allow_global: bool) -> Fix:
        t_start = time.perf_counter()
        self._check_sensor(raw)
        timing: dict[str, float] = {}
        t = time.perf_counter()
        scan = preprocess_scan(raw, self.preprocess, keep_organized=True)
        timing["preprocess"] = (time.perf_counter() - t) * 1e3
        tracked: Fix | None = None
        if prior is not None:
            tracked = self._track(scan, prior, timing)
            if tracked.accepted or not allow_global:
                return _finish(tracked, timing, t_start)
        found = self._global(scan, timing)
        if tracked is not None and not found.accepted:
            found = replace(found, reason=f"tracking: {tracked.reason}; global: {found.reason}")
        tried = found.candidates_tried + (tracked.candidates_tried if tracked else 0)
        return _finish(replace(found, candidates_tried=tried), timing, t_start)

    def _check_sensor(self, scan: Scan) -> None:
        name = scan.sensor.name
        if name not in self._sensors_checked:
            self.map.check_query(scan.sensor, allow_other_sensor=self.params.allow_other_sensor)
            self._sensors_checked.add(name)

    # -- tracking ---------------------------------------------------------------------------------------------
    def _track(self, scan: Scan, prior: np.ndarray, timing: dict[str, float]) -> Fix:
        tp = self.params.tracking
        ids, _ = self.map.nearest(prior[:3, 3], k=tp.max_keyframes, radius=tp.radius_m)
        if not len(ids):
            return Fix(None, False, "tracking", f"no keyframe within {tp.radius_m:g} m")
        moving_scan = tp.icp_moves == "scan"
        t = time.perf_counter()
        try:
            points = scan.xyz[valid_points(scan)]
            own = as_source(points, tp.verify) if moving_scan else as_target(points, tp.verify)
        except ScanDataError as exc:
            timing["prepare"] = (time.perf_counter() - t) * 1e3
            return Fix(None, False, "tracking", f"scan cannot be verified: {exc}")
        timing["prepare"] = (time.perf_counter() - t) * 1e3
        icp_ms = 0.0
        reason, tried, best = "no keyframe cloud", 0, None
        for kf in (int(i) for i in ids):
            t = time.perf_counter()
            cloud = self._keyframe_cloud(kf, "target" if moving_scan else "source")
            t_icp = time.perf_counter()
            timing["prepare"] += (t_icp - t) * 1e3
            if cloud is None:
                continue
            T_kf = self.map.poses[kf]
            guess = np.linalg.inv(T_kf) @ prior  # T_keyframe_scan
            if moving_scan:
                v = verify_icp(own, cloud, guess, tp.verify)
                T_kf_scan = v.T_match_query
            else:  # the keyframe's cloud registered onto the scan: T_scan_keyframe, inverted
                v = verify_icp(cloud, own, np.linalg.inv(guess), tp.verify)
                T_kf_scan = np.linalg.inv(v.T_match_query)
            icp_ms += (time.perf_counter() - t_icp) * 1e3
            tried += 1
            if best is None or v.score > best[1].score:
                best = (kf, v)
            if not v.accepted:
                reason = _rejection(v)
                continue
            T = T_kf @ T_kf_scan
            metres, degrees = correction(prior, T)
            if metres > tp.max_correction_m or degrees > tp.max_correction_deg:
                reason = f"jump {metres:.1f} m" if metres > tp.max_correction_m else f"jump {degrees:.1f} deg"
                continue
            timing["tracking"] = icp_ms
            return Fix(T, True, "tracking", "ok", kf, v.score, v.fitness, tried)
        timing["tracking"] = icp_ms
        if best is None:
            return Fix(None, False, "tracking", reason, candidates_tried=tried)
        kf, v = best
        return Fix(None, False, "tracking", reason, kf, v.score, v.fitness, tried)

    def _keyframe_cloud(self, kf: int, role: Literal["source", "target"]) -> IcpCloud | None:
        """Keyframe ``kf``'s cloud prepared for ICP as ``role`` (None: too few points), from the LRU when it is
        there."""
        key = (kf, role)
        if key in self._clouds:
            self._clouds.move_to_end(key)
            return self._clouds[key]
        prepare = as_target if role == "target" else as_source
        try:
            cloud: IcpCloud | None = prepare(self.map.cloud(kf), self.params.tracking.verify)
        except ScanDataError:
            cloud = None
        self._clouds[key] = cloud
        while len(self._clouds) > self.params.tracking.cached_keyframes:
            self._clouds.popitem(last=False)
        return cloud

    # -- global search ----------------------------------------------------------------------------------------
    def _global(self, scan: Scan, timing: dict[str, float]) -> Fix:
        """Global search: each pipeline of `searches` in turn until one gives a fix; the reasons of all when none
        does."""
        reasons, tried = [], 0
        for pipe, rec, threshold in self.searches:
            fix = self._global_one(scan, rec, threshold, timing)
            tried += fix.candidates_tried
            if fix.accepted or len(self.searches) == 1:
                return replace(fix, candidates_tried=tried)
            reasons.append(f"{pipe.name}: {fix.reason}")
        return replace(fix, reason="; ".join(reasons), candidates_tried=tried)

    def _global_one(
        self, scan: Scan, rec: PlaceRecognizer, threshold: float | None, timing: dict[str, float]
    ) -> Fix:
        """One pipeline's global search: its best candidate it accepted with a score >= ``threshold``."""
        t = time.perf_counter()
        try:
            desc = rec.describe(scan)
        except ScanDataError as exc:
            timing["describe"] = timing.get("describe", 0.0) + (time.perf_counter() - t) * 1e3
            return Fix(None, False, "global", f"scan cannot be described: {exc}")
        timing["describe"] = timing.get("describe", 0.0) + (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        candidates = rec.query_description(desc, k=self.params.k, max_id=None)
        timing["query"] = timing.get("query", 0.0) + (time.perf_counter() - t) * 1e3
        if not candidates:
            return Fix(None, False, "global", "no candidate")
        threshold = -math.inf if threshold is None else threshold
        first_rejection = None
        for c in candidates:
            fitness = float("nan") if c.verification is None else c.verification.fitness
            if c.accepted is False or c.relative_pose is None:
                first_rejection = first_rejection or (c, "rejected by verification")
                continue
            if c.accepted is None:
                first_rejection = first_rejection or (c, "not verified by the pipeline")
                continue
            if c.score < threshold:
                first_rejection = first_rejection or (c, f"below threshold ({c.score:.3f} < {threshold:g})")
                continue
            T = self.map.poses[c.match_id] @ np.asarray(c.relative_pose, np.float64)
            why = self._ambiguity(candidates, c)
            if why:
                return Fix(
                    None, False, "global", why, int(c.match_id), float(c.score), fitness, len(candidates)
                )
            return Fix(T, True, "global", "ok", int(c.match_id), float(c.score), fitness, len(candidates))
        c, why = first_rejection if first_rejection else (candidates[0], "no accepted candidate")
        fitness = float("nan") if c.verification is None else c.verification.fitness
        return Fix(None, False, "global", why, int(c.match_id), float(c.score), fitness, len(candidates))

    def _ambiguity(self, candidates: list[Candidate], best: Candidate) -> str:
        """Why ``best`` (the fix global search would give) is refused as ambiguous, or "" when it is not."""
        params = self.params.ambiguity
        if params.max_ratio is None:
            return ""
        rest = [c for c in candidates if c is not best and c.accepted and c.relative_pose is not None]
        answers = [best, *rest]
        poses = np.stack(
            [self.map.poses[c.match_id] @ np.asarray(c.relative_pose, np.float64) for c in answers]
        )
        ratio = runner_up_ratio(np.array([c.score for c in answers]), poses[:, :3, 3], params.separation_m)
        if not params.refuses(ratio):
            return ""
        return f"ambiguous: a place elsewhere in the map scores {ratio:.2f} of the best"


def _rejection(v: Verification) -> str:
    """Why the tracking verification refused a keyframe (its `Verification.rejection`), in the rule's words."""
    if v.rejection == "fitness":
        return f"rejected: low fitness {v.fitness:.2f}"
    if v.rejection == "fitness_ratio":
        return f"rejected: fitness {v.fitness:.2f} low for the displacement"
    if v.rejection == "constraint":
        return f"rejected: translation left free (constraint {v.constraint:.3f})"
    return f"rejected: low score {v.score:.2f}"


def _finish(fix: Fix, timing: dict[str, float], t_start: float) -> Fix:
    return replace(fix, time_ms=(time.perf_counter() - t_start) * 1e3, timing_ms=dict(timing))
