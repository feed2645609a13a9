"""``placerec slam``: a config's sequence through odometry, verified loop closure and the pose graph.

`run_slam` opens the dataset, builds the loop-closure pipeline and the odometry source (all checked before a
results folder is made), runs `slam_sequence` and writes the results (`placerec.slam_app.report`).
`slam_sequence` is the online loop: for every scan, in order, read + preprocess it, get its odometry pose, feed
`placerec.slam.online.OnlineSlam` (loop closure, graph, iSAM2); then the final batch optimisation. With a prior map
(`open_prior_map`) the session runs in `placerec.slam.multisession.MultiSessionSlam`, and each scan is also
localised in the map by its ``prior_map.join_pipelines`` (`placerec.maps.Localizer`), whose accepted fixes are
inter-session closures. `map_writer_for` saves the run as a map: the loop pipeline's database and those of
``output.map_pipelines``.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from placerec.config import PipelineSpec
from placerec.errors import ConfigError, ScanDataError
from placerec.experiment.datasets import SlicedSequence, open_dataset
from placerec.experiment.run_folder import interruptible, make_run_dir
from placerec.experiment.runner import progress_bars
from placerec.io import read_poses
from placerec.maps.artifact import MapArtifact, MapGraph, MapWriter
from placerec.maps.localizer import Localizer, LocalizerParams
from placerec.preprocess import preprocess_scan
from placerec.recognizer import make_pipeline
from placerec.slam.graph import LoopFactor, PoseGraph
from placerec.slam.multisession import MultiSessionSlam
from placerec.slam.online import OnlineSlam
from placerec.slam.result import ONLINE_STAGES, SlamResult
from placerec.slam_app.config import SlamConfig
from placerec.slam_app.report import report_slam
from placerec.types import (
    MAX_TRANSLATION_M,
    Description,
    PlaceRecognizer,
    Scan,
    Sequence,
    valid_points,
)
from placerec.viewer import active

if TYPE_CHECKING:
    from placerec.loop_closure import LoopClosureDetector
    from placerec.viewer.recorder import Recorder

__all__ = ["slam_sequence", "run_slam", "odometry_source", "false_loops", "map_writer_for", "open_prior_map"]

log = logging.getLogger(__name__)

Odometry = Callable[[int, Scan], np.ndarray]


def _drift_odometry(cfg: SlamConfig, seq: Sequence) -> np.ndarray:
    from placerec.sim.odometry import drift_poses

    if seq.poses is None:
        raise ConfigError(
            f"odometry.source 'dataset' makes drifting odometry from true poses; {seq.name} has none"
        )
    drift = cfg.odometry.drift
    seed = drift.seed
    if seed is None:
        seed = cfg.dataset.simulator.seed if cfg.dataset.source == "simulator" else 0
    with np.errstate(over="ignore", invalid="ignore"):
        poses = drift_poses(seq.poses, drift, seed)
    # finite and within MAX_TRANSLATION_M (rigid_problem's orthonormality test is left out: composing the rounded
    # rotations of a long pose file drifts past its tolerance without anything being wrong)
    far = ~(np.abs(poses) <= MAX_TRANSLATION_M).all(axis=(1, 2))  # NaN compares False
    if far.any():
        k = int(np.argmax(far))
        raise ConfigError(
            f"odometry.drift: the drifting odometry of {seq.name} is not finite or beyond {MAX_TRANSLATION_M:g} m "
            f"at scan {k}: odometry.drift.translation={drift.translation:g}, rotation_deg={drift.rotation_deg:g}, "
            f"yaw_bias_deg_per_100m={drift.yaw_bias_deg_per_100m:g}, scale_bias={drift.scale_bias:g} are too "
            "large for its poses"
        )
    return poses


def _file_odometry(cfg: SlamConfig, seq: Sequence) -> np.ndarray:
    assert cfg.odometry.path is not None  # OdometryConfig requires it for source 'file'
    poses, _ = read_poses(cfg.odometry.path, cfg.odometry.format)
    if len(poses) == len(seq):
        return poses
    if isinstance(seq, SlicedSequence) and len(poses) > int(seq.base_indices.max()):
        return poses[seq.base_indices]
    raise ConfigError(
        f"odometry.path {cfg.odometry.path}: {len(poses)} poses for {len(seq)} scans of {seq.name}"
    )


def odometry_source(cfg: SlamConfig, seq: Sequence) -> Odometry:
    """``f(index, scan) -> T_world_sensor`` for the configured odometry (`ConfigError` when it cannot work)."""
    source = cfg.odometry.source
    if source in ("dataset", "file"):
        poses = _drift_odometry(cfg, seq) if source == "dataset" else _file_odometry(cfg, seq)
        return lambda i, scan: poses[i]
    from placerec.slam.odometry import KissIcpOdometry

    origin = None if seq.poses is None else seq.poses[0]
    kiss = KissIcpOdometry(cfg.odometry.kiss_icp, origin)
    return lambda i, scan: kiss.register(scan)


def false_loops(cfg: SlamConfig, reference: np.ndarray, n_scans: int) -> dict[int, list[LoopFactor]]:
    """``robustness.false_loops`` wrong loop edges by query scan: random pairs at least ``min_distance`` apart
    (on ``reference``, the true poses when known) and older than the exclusion window, each given the kind of
    relative pose a real closure has (up to 3 m in x and y, yaw up to 30 deg), seeded by ``robustness.seed``."""
    rb = cfg.robustness
    if rb.false_loops == 0:
        return {}
    rng = np.random.default_rng([rb.seed, 0xFA15E])
    gap = max(1, cfg.loops.exclusion.frames or 1)
    pos = reference[:, :3, 3]
    pairs: set[tuple[int, int]] = set()
    for _ in range(100 * rb.false_loops):  # a random query, then a random far enough older scan
        if len(pairs) == rb.false_loops or n_scans <= gap:
            break
        q = int(rng.integers(gap, n_scans))
        far = np.flatnonzero(np.linalg.norm(pos[: q - gap + 1] - pos[q], axis=1) >= rb.min_distance)
        if far.size:
            pairs.add((int(rng.choice(far)), q))
    if len(pairs) < rb.false_loops:
        raise ConfigError(
            f"robustness.false_loops: found {len(pairs)} of {rb.false_loops} scan pairs {rb.min_distance} m apart "
            f"beyond the exclusion window ({n_scans} scans)"
        )
    out: dict[int, list[LoopFactor]] = {}
    for m, q in sorted(pairs):
        yaw = np.radians(rng.uniform(-30, 30))
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[:2, 3] = rng.uniform(-3, 3, 2)
        out.setdefault(q, []).append(LoopFactor(m, q, T, float("nan"), injected=True))
    return out


def _injected(cfg: SlamConfig, seq: Sequence) -> dict[int, list[LoopFactor]]:
    """`false_loops` on the sequence's true poses; `ConfigError` when they are asked for and it has none."""
    if not cfg.robustness.false_loops:
        return {}
    if seq.poses is None:
        raise ConfigError(
            "robustness.false_loops needs a dataset with true poses (to pick truly wrong pairs)"
        )
    return false_loops(cfg, seq.poses, len(seq))


def _timestamps(seq: Sequence) -> np.ndarray | None:
    """The sequence's scan times, which must be finite when it has them (`ScanDataError` naming the scan)."""
    stamps = seq.timestamps
    if stamps is None:
        return None
    stamps = np.asarray(stamps, np.float64)
    bad = ~np.isfinite(stamps)
    if bad.any():
        i = int(np.argmax(bad))
        raise ScanDataError(
            f"{seq.name}: timestamp of scan {i} is {stamps[i]}; SLAM needs finite scan times (the sequence's "
            "times.txt or its dataset's time stamps; loops.exclusion.seconds compares them)"
        )
    return stamps


def _backend(
    cfg: SlamConfig, rec: PlaceRecognizer, prior: MapArtifact | None, graph: MapGraph | None
) -> OnlineSlam | MultiSessionSlam:
    """The online back end: `OnlineSlam`, or against ``prior`` a `MultiSessionSlam` (its ``graph``'s factors held
    when ``prior_map.anchor`` is ``anchored``)."""
    ex = cfg.loops.exclusion
    if prior is None:
        return OnlineSlam(
            rec, cfg.loops.threshold, cfg.graph, ex.frames, ex.seconds, ex.metres, k=cfg.loops.k,
            realtime=cfg.loops.realtime, odometry_gate=cfg.loops.odometry_gate, keyframes=cfg.loops.keyframes,
        )  # fmt: skip
    pm = cfg.prior_map
    return MultiSessionSlam(
        rec, cfg.loops.threshold, prior.poses, cfg.graph, ex.frames, ex.seconds, ex.metres, k=cfg.loops.k,
        prior_odometry=None if graph is None else graph.odometry,
        prior_loops=None if graph is None else graph.loops,
        anchor=pm.anchor, min_join_loops=pm.min_join_loops, join_translation_m=pm.join_translation_m,
        join_rotation_deg=pm.join_rotation_deg, realtime=cfg.loops.realtime, odometry_gate=cfg.loops.odometry_gate,
        keyframes=cfg.loops.keyframes,
    )  # fmt: skip


def _warn_single_frames(cfg: SlamConfig, name: str, first: Scan) -> None:
    """A warning when the scans (``first`` of sequence ``name``) are not 360 deg spinning sweeps and each is its
    own place: one frame of a Livox-style or solid-state scanner holds too little of a place (docs/sensors.md,
    "Keyframes")."""
    if cfg.loops.keyframes is None and not first.sensor.is_spinning:
        log.warning(
            "%s: %s scans are not 360 deg spinning sweeps and each is a place; set loops.keyframes (e.g. "
            "{seconds: 1.0, every_metres: 1.8}, docs/slam.md) so that places hold more than one frame",
            name,
            first.sensor.name,
        )


def loop_pipeline(cfg: SlamConfig, seq: Sequence) -> PlaceRecognizer:
    """The run's loop-closure pipeline (``loops.pipeline``) with its settings on the scans' sensor
    (`placerec.sensor_presets`, the sensor of the first scan) under the config's."""
    sensor = seq[0].sensor if len(seq) else None
    spec = cfg.loops.pipeline
    name = None if sensor is None else sensor.name
    return make_pipeline(spec.name, spec.params, path="loops.pipeline.params", sensor=name)


def open_prior_map(cfg: SlamConfig, seq: Sequence) -> tuple[MapArtifact, PlaceRecognizer]:
    """The map of ``prior_map.path`` and its database of the run's pipeline, once checked to serve this run (the
    same pipeline and front end, intensity and, unless allowed, sensor, poses that fit its clouds:
    `MapMismatchError` naming what differs; a pose graph when ``prior_map.anchor`` is ``anchored``)."""
    from placerec.artifacts.map import intensity_label

    assert cfg.prior_map.path is not None
    prior = MapArtifact.open(cfg.prior_map.path)
    spec = cfg.loops.pipeline
    prior.check_pipeline(spec.name, spec.params)
    sensor = seq[0].sensor if len(seq) else None
    prior.check_query(sensor, intensity_label(cfg.preprocess), cfg.prior_map.allow_other_sensor)
    prior.check_pose_fit()
    if cfg.prior_map.anchor == "anchored" and "graph.npz" not in prior.manifest.files:
        raise ConfigError(
            f"prior_map.anchor 'anchored' holds the map by its own pose graph; {prior.path} has none (it was not "
            "saved by placerec slam): use prior_map.anchor=fixed"
        )
    for name in cfg.prior_map.join_pipelines:
        prior.pipeline(name)  # MapMismatchError naming the map's pipelines
    mismatch = prior.places_mismatch(cfg.loops.keyframes is not None)
    if mismatch:
        log.warning("%s (loops.keyframes): closures between them compare unlike places", mismatch)
    return prior, prior.recognizer(spec.name)


def _map_searches(cfg: SlamConfig, prior: MapArtifact | None) -> list[Localizer]:
    """Global search of the map with each of ``prior_map.join_pipelines`` (its databases loaded now), at
    ``prior_map.join_threshold`` and with ``prior_map.join_ambiguity``."""
    if prior is None:
        return []
    pm = cfg.prior_map
    return [
        Localizer(
            prior,
            LocalizerParams(
                pipeline=n,
                allow_other_sensor=pm.allow_other_sensor,
                threshold=pm.join_threshold,
                ambiguity=pm.join_ambiguity,
            ),
        )
        for n in pm.join_pipelines
    ]


def _map_closures(searches: list[Localizer], raw: Scan, query_id: int) -> list[LoopFactor]:
    """The inter-session closures of the raw scan ``query_id`` (a detector id) found by ``searches``: each
    accepted global fix as a loop from its map keyframe (`Localizer.localize` without a prior)."""
    loops = []
    for search in searches:
        fix = search.localize(raw)
        if fix.accepted and fix.T_world_query is not None:
            T = np.linalg.inv(search.map.poses[fix.keyframe_id]) @ fix.T_world_query
            loops.append(LoopFactor(fix.keyframe_id, query_id, T, fix.score))
    return loops


def _own_frame(odometry: Odometry) -> Odometry:
    """``odometry`` re-expressed from its first pose (the identity): a new session knows nothing of the map's frame
    (the simulator's drift and KISS-ICP start at the sequence's true first pose otherwise)."""
    first: list[np.ndarray] = []

    def own(i: int, scan: Scan) -> np.ndarray:
        T = odometry(i, scan)
        if not first:
            first.append(np.linalg.inv(T))
        return first[0] @ T

    return own


def slam_sequence(
    cfg: SlamConfig,
    seq: Sequence,
    recognizer: PlaceRecognizer | None = None,
    odometry: Odometry | None = None,
    map_writer: MapWriter | None = None,
    prior: MapArtifact | None = None,
) -> SlamResult:
    """Run the online loop over ``seq`` and the final batch optimisation (see the module docstring).
    ``map_writer`` (from `map_writer_for`) gets every scan as a keyframe and is finished at the optimised poses.
    With ``prior`` (`open_prior_map`; ``recognizer`` is then its database) the run is a second session: its
    odometry starts at the identity, its closures against the map join it to the map when enough agree, and
    ``map_writer`` (holding the map's keyframes) writes the merged map only if they were joined."""
    rec = recognizer if recognizer is not None else loop_pipeline(cfg, seq)
    odometry = odometry or odometry_source(cfg, seq)
    prior_graph = None
    if prior is not None:
        odometry = _own_frame(odometry)
        prior_graph = prior.graph()
    slam = _backend(cfg, rec, prior, prior_graph)
    n = len(seq)
    stamps = _timestamps(seq)
    injected = _injected(cfg, seq)
    pre = cfg.preprocess
    realtime = ("wait",) if cfg.loops.realtime is not None else ()  # the detector's wait for its worker
    searches = _map_searches(cfg, prior)
    searched = ("map_search",) if searches else ()  # the join pipelines' global search of the map
    built = ("keyframe",) if cfg.loops.keyframes is not None else ()  # accumulating the scan into a keyframe
    timing: dict[str, list[float]] = {
        s: [] for s in (*ONLINE_STAGES, *realtime, *searched, *built, "odometry", "cpu")
    }
    odo = np.empty((n, 4, 4))
    queried = []
    map_at: list[int] = []  # with keyframes: the scan each saved map keyframe stands at
    viewer = active()
    label = cfg.loops.pipeline.display_name
    with progress_bars(cfg.output.progress) as progress, _closing(slam), contextlib.ExitStack() as stack:
        task = progress.add_task(f"slam ({label})", total=n)
        if viewer is not None:
            stack.enter_context(viewer.watching(label, rec))
            viewer.matches_in = "scan" if prior is None else "prior map"  # its ids are not this run's scans
            if seq.poses is not None:
                viewer.trajectory("gt", seq.poses, static=True)
        for i in range(n):
            raw = seq[i]
            if i == 0:
                _warn_single_frames(cfg, seq.name, raw)
            t0 = time.perf_counter()
            odo[i] = odometry(i, raw)
            t1, c1 = time.perf_counter(), time.process_time()
            scan = preprocess_scan(raw, pre, keep_organized=True)
            t2 = time.perf_counter()
            stamp = None if stamps is None else float(stamps[i])
            desc: Description | None = None
            describe_ms: dict[str, float] = {}
            # a keyframe is described when it completes, inside the detector
            if viewer is not None and cfg.loops.keyframes is None:
                desc, describe_ms = _described(rec, scan)
            extra = injected.get(i)
            t3 = time.perf_counter()
            if searches:
                extra = [*(extra or []), *_map_closures(searches, raw, len(searches[0].map) + i)]
            search_ms = (time.perf_counter() - t3) * 1e3
            added = slam.process(scan, odo[i], stamp, description=desc, extra_loops=extra)
            cpu = (time.process_time() - c1) * 1e3
            if viewer is not None:  # after the times: they are the run's, not the recording's
                viewer.scan(i, scan, odo[i], stamp)
                _log_slam_step(viewer, label, slam, rec, scan, desc, added, odo[: i + 1], i, n)
            if map_writer is not None and cfg.loops.keyframes is None:
                kf = map_writer.add_keyframe(odo[i], scan.xyz[valid_points(scan)], stamp, scan_index=i)
                _add_to_map_pipelines(cfg, map_writer, kf, scan, odo[i])
            elif map_writer is not None:
                map_at += _add_keyframes_to_map(cfg, map_writer, slam.detector, odo, i)
            queried.append(slam.detector.last_max_id >= 0)
            stages = dict(slam.last_timing_ms, **describe_ms, odometry=(t1 - t0) * 1e3, preprocess=(t2 - t1) * 1e3,
                          cpu=cpu, map_search=search_ms)  # fmt: skip
            for s in timing:
                timing[s].append(stages.get(s, 0.0))
            progress.advance(task)
    online = slam.poses()  # before the closures a real-time detector still owes (finish adds them)
    common: dict[str, Any] = dict(name=seq.name, odometry=odo, timing_ms=timing, ground_truth=seq.poses, timestamps=stamps,
                  candidates=slam.candidates, queried=queried)  # fmt: skip
    if isinstance(slam, OnlineSlam):
        before = len(slam.loops)
        optimized = slam.finish()
        if viewer is not None:
            _log_slam_end(viewer, label, slam, optimized, slam.loops[before:])
        common["realtime"] = _realtime_stats(slam)
        common["refused_by_gate"] = _gate_refusals(slam)
        if map_writer is not None and cfg.loops.keyframes is None:
            map_writer.finish(poses=optimized, graph=slam.graph)
        elif map_writer is not None:  # the last, partial keyframe came with finish
            map_at += _add_keyframes_to_map(cfg, map_writer, slam.detector, odo, n - 1)
            graph = _keyframe_factors(MapGraph.from_pose_graph(slam.graph), map_at)
            map_writer.finish(poses=optimized[np.asarray(map_at, np.int64)], graph=graph)
        return SlamResult(
            online=online, optimized=optimized, loops=slam.loops, batch=slam.batch_info, graph=slam.graph,
            isam2_ms=list(slam.graph.update_ms), isam2_loop_ms=list(slam.graph.loop_update_ms), **common,
        )  # fmt: skip
    assert prior is not None
    ms = slam.finish()
    if viewer is not None:
        _log_slam_end(viewer, label, slam, ms.session_poses, [])
    common["realtime"] = _realtime_stats(slam)
    common["refused_by_gate"] = _gate_refusals(slam)
    M = len(prior)
    graph_poses = np.concatenate([ms.map_poses, ms.session_poses]) if ms.joined else ms.session_poses
    if map_writer is not None:
        if ms.joined and cfg.loops.keyframes is not None:  # the last, partial keyframe came with finish
            map_at += _add_keyframes_to_map(cfg, map_writer, slam.detector, odo, n - 1)
            prior_factors = prior_graph or MapGraph()
            session = _keyframe_factors(MapGraph.from_pose_graph(ms.graph), map_at, M)
            merged = MapGraph(
                prior_factors.odometry + session.odometry,
                prior_factors.loops + session.loops,
                session.loop_sigmas,
            )
            poses = np.concatenate([ms.map_poses, ms.session_poses[np.asarray(map_at, np.int64)]])
            map_writer.finish(poses=poses, graph=merged)
        elif ms.joined:
            map_writer.finish(poses=graph_poses, graph=_merged_graph(prior_graph, ms.graph, M))
        else:
            map_writer.abort()
            log.warning("%s: %s; no merged map written", seq.name, ms.summary())
    own = [replace(lp, match_id=lp.match_id - M, query_id=lp.query_id - M) for lp in ms.intra_loops]
    return SlamResult(
        online=online, optimized=ms.session_poses, loops=own, batch=ms.batch, graph=ms.graph,
        isam2_ms=list(ms.graph.update_ms), isam2_loop_ms=list(ms.graph.loop_update_ms), multisession=ms,
        graph_poses=graph_poses, **common,
    )  # fmt: skip


def _add_keyframes_to_map(
    cfg: SlamConfig, writer: MapWriter, detector: LoopClosureDetector, odometry: np.ndarray, i: int
) -> list[int]:
    """With ``loops.keyframes``: the places the detector added up to scan ``i``, added to the saved map under the
    same ids (its database is the detector's recognizer): a completed keyframe at its last scan's odometry pose
    with its cloud, a place of no scans (a scan the keyframe builder refused) at scan ``i`` with none. Returns the
    scan each added map keyframe stands at."""
    added = []
    P = detector.prior_entries  # a prior map's places, already in the writer
    while len(writer) - P < detector.n_processed:
        kf = detector.last_keyframe if len(writer) - P == detector.n_processed - 1 else None
        if kf is None:
            writer.add_keyframe(odometry[i], np.zeros((0, 3)), None, scan_index=i)
            added.append(i)
            continue
        last = int(kf.scan_indices[-1])
        k = writer.add_keyframe(
            odometry[last], kf.scan.xyz[valid_points(kf.scan)], kf.timestamp, scan_index=last
        )
        _add_to_map_pipelines(cfg, writer, k, kf.scan, odometry[last])
        added.append(last)
    return added


def _keyframe_factors(graph: MapGraph, at: list[int], offset: int = 0) -> MapGraph:
    """The factors of a map of keyframes from those of a graph with a pose a scan (``loops.keyframes``): ``at``,
    the scan each keyframe stands at (keys ``offset + s`` in ``graph``, ``offset + k`` in the map; keys below
    ``offset``, a prior map's places, stay). The scans' odometry factors composed from one keyframe's scan to the
    next (their sigmas summed: an upper bound of the composition's), the loops between keyframes or from one to a
    prior map's place (an injected edge between other scans is left out). A prior map's own factors are not
    repeated."""
    steps = {i: (T, sig) for i, _, T, sig in graph.odometry if i >= offset}  # scan key i -> i + 1
    odometry = []
    for k in range(len(at) - 1):
        T, sig = np.eye(4), np.zeros(6)
        for step in range(offset + at[k], offset + at[k + 1]):
            T, sig = T @ steps[step][0], sig + steps[step][1]
        odometry.append((offset + k, offset + k + 1, T, sig))
    ids = {offset + s: offset + k for k, s in enumerate(at)}

    def key(i: int) -> int | None:
        return i if i < offset else ids.get(i)

    loops = []
    for lp in graph.loops:
        m, q = key(lp.match_id), key(lp.query_id)
        if max(lp.match_id, lp.query_id) >= offset and m is not None and q is not None:
            loops.append(replace(lp, match_id=m, query_id=q))
    return MapGraph(odometry, loops, graph.loop_sigmas)


def _add_to_map_pipelines(
    cfg: SlamConfig, writer: MapWriter, keyframe: int, scan: Scan, pose: np.ndarray
) -> None:
    """Keyframe ``keyframe`` added to the saved map's ``output.map_pipelines`` databases (a scan one of them cannot
    describe is left out of that one: the map never proposes it)."""
    for name in cfg.output.map_pipelines:
        try:
            writer.pipelines[name][0].add(keyframe, scan, pose)
        except ScanDataError as exc:
            log.warning("map pipeline %s: keyframe %d left out (%s)", name, keyframe, exc)


def _described(rec: PlaceRecognizer, scan: Scan) -> tuple[Description | None, dict[str, float]]:
    """With a recording on, the scan is described before the back end gets it, so the recording can show what
    the front end found (the detector takes the description instead of describing again): (description, its
    ``describe`` time); (None, {}) when the front end refuses the scan (the detector then skips it)."""
    t0 = time.perf_counter()
    try:
        desc = rec.describe(scan)
    except ScanDataError:
        return None, {}
    return desc, {"describe": (time.perf_counter() - t0) * 1e3}


def _log_slam_step(
    viewer: Recorder,
    label: str,
    slam: OnlineSlam | MultiSessionSlam,
    rec: PlaceRecognizer,
    scan: Scan,
    desc: Description | None,
    added: list[LoopFactor],
    odometry: np.ndarray,
    i: int,
    n: int,
) -> None:
    """One scan of the online loop in the recording: the front end's findings, the queries completed (their
    candidates; the best one's rejection as a ``rejected`` edge), the loops the graph took (``accepted``, or
    ``injected`` for `false_loops`) and, every ``n // 50`` scans and at the last, the odometry and the online
    estimate so far (each is logged whole: at every scan the file would grow with the square of the scans)."""
    if desc is not None:
        viewer.description(label, rec, scan, desc)
    for cands in slam.ids.completed():
        viewer.candidates(label, cands, slam.detector.threshold, edges=False)
        if cands and cands[0].accepted is False:
            viewer.edge(label, "rejected", cands[0].match_id, cands[0].query_id)
    for loop in added:
        viewer.edge(label, "injected" if loop.injected else "accepted", loop.match_id, loop.query_id)
    if i % max(1, n // 50) == 0 or i == n - 1:
        viewer.trajectory("odometry", odometry)
        viewer.trajectory("online", slam.poses())


def _log_slam_end(
    viewer: Recorder,
    label: str,
    slam: OnlineSlam | MultiSessionSlam,
    optimized: np.ndarray,
    late: list[LoopFactor],
) -> None:
    """The end of the run in the recording: the queries a real-time detector completed last and their loops
    (``late``), the final optimised trajectory, and every loop edge moved onto it."""
    for cands in slam.ids.completed():
        viewer.candidates(label, cands, slam.detector.threshold, edges=False)
    for loop in late:
        viewer.edge(label, "accepted", loop.match_id, loop.query_id)
    viewer.trajectory("optimized", optimized)
    viewer.replace_positions(optimized)


@contextlib.contextmanager
def _closing(slam: OnlineSlam | MultiSessionSlam) -> Iterator[None]:
    """End a real-time detector's worker thread when the online loop fails (`finish` ends it otherwise)."""
    try:
        yield
    except BaseException:
        slam.detector.abort()
        raise


def _realtime_stats(slam: OnlineSlam | MultiSessionSlam) -> dict[str, Any] | None:
    """The detector's real-time counters (`placerec.realtime.RealtimeStats.as_dict`); None when sequential."""
    stats = slam.detector.realtime_stats
    return None if stats is None else stats.as_dict()


def _gate_refusals(slam: OnlineSlam | MultiSessionSlam) -> int | None:
    """How many closures over the threshold the detector's odometry gate refused (after the stream's end, so a
    real-time detector's late ones count); None without a gate."""
    detector = slam.detector
    return None if detector.odometry_gate is None else len(detector.refused_by_gate)


def _merged_graph(prior_graph: MapGraph | None, joined: PoseGraph, M: int) -> MapGraph:
    """The merged map's graph: the prior map's own factors (``prior_graph``), then the joined graph's factors that
    touch the session (keys M..): its odometry and its loops (intra- and inter-session). The joined graph's
    factors among map keys alone are the prior map's own again (``anchored`` adds them), so they are not repeated."""
    own = prior_graph or MapGraph()
    merged = MapGraph.from_pose_graph(joined)
    session_odometry = [f for f in merged.odometry if f[0] >= M and f[1] >= M]
    session_loops = [lp for lp in merged.loops if max(lp.match_id, lp.query_id) >= M]
    return MapGraph(own.odometry + session_odometry, own.loops + session_loops, merged.loop_sigmas)


def map_writer_for(
    cfg: SlamConfig, seq: Sequence, recognizer: PlaceRecognizer, prior: MapArtifact | None = None
) -> MapWriter:
    """The writer of ``output.save_map`` (`ConfigError` at once when a map is there and ``overwrite_map`` is off):
    the run's recognizer is the map's database, its preprocessing and intensity the map's. With ``prior`` it
    starts with the prior map's keyframes, sessions and clouds (the merged map's first keyframes)."""
    from placerec.artifacts.map import intensity_label

    assert cfg.output.save_map is not None
    spec = cfg.loops.pipeline
    sensor = seq[0].sensor if len(seq) else None
    pipelines: dict[str, tuple[PlaceRecognizer, float | None]] = {
        spec.name: (recognizer, cfg.loops.threshold)
    }
    for name in cfg.output.map_pipelines:
        if prior is not None:  # the prior map's database of it, extended by this session's scans
            pipelines[name] = (prior.recognizer(name, fresh=True), prior.pipeline(name).threshold)
        else:
            extra = PipelineSpec(name=name)
            model = None if sensor is None else sensor.name
            params = cfg.output.map_pipeline_params.get(name)
            built = make_pipeline(name, params, path=f"output.map_pipeline_params.{name}", sensor=model)
            pipelines[name] = (built, extra.threshold_for(model))
    writer = MapWriter(
        cfg.output.save_map,
        pipelines,
        name=seq.name if prior is None else f"{prior.manifest.name} + {seq.name}",
        sensor=sensor,
        intensity=intensity_label(cfg.preprocess),
        preprocess=cfg.preprocess.saved_dump(),
        config=cfg.model_dump(mode="json"),
        poses_source="slam" if prior is None else "merged",
        overwrite=cfg.output.overwrite_map,
    )
    if prior is not None:
        for s in prior.manifest.sessions:
            writer.add_session(s.name)
            for i in range(s.first, s.first + s.count):
                stamp = float(prior.timestamps[i])
                writer.add_keyframe(prior.poses[i], prior.cloud(i), None if np.isnan(stamp) else stamp,
                                    scan_index=int(prior.scan_index[i]))  # fmt: skip
    writer.add_session(seq.name)
    return writer


def run_slam(
    cfg: SlamConfig, out_dir: str | Path | None = None, seq: Sequence | None = None
) -> tuple[Path, dict[str, Any]]:
    """Run ``cfg`` and write its results folder; returns (folder, metrics dict). The pipeline, dataset and
    odometry are set up before the folder is made, so a config that cannot run leaves none behind; nor does it
    leave a half-written map (``output.save_map``)."""
    if seq is None:
        if cfg.dataset.source == "path":
            assert cfg.dataset.path is not None  # DatasetConfig requires it for source 'path'
            if not Path(cfg.dataset.path).expanduser().exists():
                raise ConfigError(
                    f"dataset.path {cfg.dataset.path}: no such folder or file (point it at your sequence: "
                    "--set dataset.path=/path/to/sequence)"
                )
        seq = open_dataset(cfg.dataset)
    prior = None
    if cfg.prior_map.path is None:
        rec = loop_pipeline(cfg, seq)
    else:
        prior, rec = open_prior_map(cfg, seq)
    odometry = odometry_source(cfg, seq)
    _injected(cfg, seq)
    _timestamps(seq)
    writer = None if cfg.output.save_map is None else map_writer_for(cfg, seq, rec, prior)
    run = make_run_dir(cfg, out_dir)
    with interruptible(run), writer or contextlib.nullcontext():
        result = slam_sequence(cfg, seq, rec, odometry, writer, prior)
        return run, report_slam(cfg, run, seq, result, prior)
