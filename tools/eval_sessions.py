"""Maps that outlive a session, on the held-out test split (issue #29, part 4): relocalisation, kidnap and
multi-session SLAM over simulated session pairs (`placerec.sim.sessions`).

For each world x seed x kind (``--worlds``, ``--seeds``, ``--kinds``; the map session is the same for every
kind of a world and seed, so its two maps are built once and kept under ``--work``):

1. **Relocalisation.** The map is session 1 built with `placerec.artifacts.map.write_map` from its **true** poses
   (keyframes every 0.5 m; the map default's databases, ORB-HBST and Scan Context, global search asking them in
   turn, or only ``--pipeline``'s). Session 2 is localised in order with
   `Localizer.track`, given its own drifting odometry (the simulator's default `OdometryDrift`, seeded by the
   query's seed, re-based to start at the identity: only its relative motion reaches the localiser).
   `localize_sequence` offers only no odometry or KISS-ICP, so the loop is the few lines of `Localizer.track`
   here and the result a `LocalizeRun` (its ``correct()``: accepted and within 1 m / 5 deg). Reported: the scans in
   the overlap (`SessionPair.overlap`, within 5 m of a map scan), the share of them localised correctly, accepted
   wrong fixes, fixes on scans outside the overlap (and how many of those are wrong), tracking ms (median, p95)
   and global-search ms (median).
2. **Kidnap.** `kidnap_trials` (``--kidnaps`` per cell, seeded by the seed): after `Localizer.reset`, ``before``
   scans tracked, then a teleport of >= 50 m the localiser is not told about (its odometry goes on by one ordinary
   step and then follows the new place's relative motion). Success: the first accepted fix after the teleport is
   correct and comes within 3 scans; a wrong first fix is a kidnap false fix.
3. **Multi-session.** Session 1 through `slam_sequence` with ``configs/slam_demo.yaml`` (its drift, seeded by the
   map's seed; ``--sensor``) writing a map (``output.save_map``), then session 2 through `slam_sequence` against it
   (``prior=open_prior_map``; drift seeded by the query's seed). Merged ATE (RMSE, one rigid alignment) over both
   sessions: session 1 = ``multisession.map_poses``, session 2 = ``multisession.session_poses``, against their true
   poses (only when joined: otherwise the session is in its own frame). Inter-session false loops: closures in the
   joined graph whose ``T_match_query`` is more than 1 m / 5 deg from ``inv(GT1[m]) @ GT2[q]``; ``disjoint`` must
   not join. Two diagnostics beside it: the **join error** (each overlapping session-2 pose against where the map
   puts it: the nearest keyframe's estimate moved by the true relative pose; the join's own error, free of the
   map's drift) and the same session 2 run against the **true-pose map** of 1. (its merged ATE: the join with a
   map that has no drift of its own). ``--slam-odometry kiss-icp`` runs both SLAM sessions on KISS-ICP odometry
   over the scans instead of the demo's drift (whose scale error no loop closure can see); ``--odometry-gate``
   runs both SLAM sessions with ``loops.odometry_gate`` (`placerec.odometry_gate`: after the join the
   inter-session closures are checked against the joined estimate; those refused are counted, and how many of
   them were false).

**Keyframes** (``--keyframes``, a Livox-style or solid-state sensor): both sessions are driven as the sensor
benchmark captures the sensor (`placerec.experiment.protocol.CAPTURE`: frames at 10 Hz taken while moving), the
true-pose map's places are keyframes (`placerec.artifacts.map.MapBuild.keyframes`), relocalisation and the kidnaps
localise session 2's keyframes (accumulated along its drifting odometry; each stands at its last frame: its truth,
overlap and odometry), and both SLAM sessions run `SLAM_CONFIG_KEYFRAMES` with the sensor's keyframes and its
loop pipeline's operating threshold on the sensor (`placerec.sensor_presets`). Kidnap trials count keyframes.

Map load time and size by keyframe count are ``tools/bench_map_scale.py``'s, not redone here.

**The default seeds are the TEST seeds** (`placerec.experiment.protocol.TEST_SEEDS`): this tool only reports;
nothing here is tuned and no default may be chosen from its output. Each cell is cached as JSON in
``--out`` (default ``results/eval_sessions``) with the settings that made it, so a rerun resumes (a cell made with
other settings is recomputed). A line per stage, then a table, then one JSON line (with the load: ``uptime``).

    python tools/eval_sessions.py                                   # the full test split (tens of minutes)
    python tools/eval_sessions.py --scans 40 --worlds town --kinds revisit disjoint
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from placerec.artifacts.map import MapBuild, write_map
from placerec.config import PipelineSpec, apply_overrides, read_config_file
from placerec.errors import ConfigError
from placerec.eval.metrics import timing_summary
from placerec.eval.pose_error import pose_errors
from placerec.eval.trajectory import trajectory_errors
from placerec.experiment.protocol import CAPTURE, TEST_SEEDS, TEST_WORLDS
from placerec.hashing import stable_hash
from placerec.keyframes import KeyframeParams, KeyframeSequence
from placerec.maps import Fix, Localizer, LocalizerParams, MapArtifact
from placerec.params import resolve
from placerec.recognizer import PIPELINES, pipeline_params
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.sim.sessions import SessionPair, kidnap_trials, make_session_pair
from placerec.slam_app.localize import CORRECT_DEG, CORRECT_M, LocalizeRun
from placerec.types import Sequence

KINDS = ("revisit", "partial", "opposite", "disjoint")
SLAM_CONFIG = "configs/slam_demo.yaml"
#: both SLAM sessions' config in keyframe cells (``--keyframes``)
SLAM_CONFIG_KEYFRAMES = "configs/slam_livox.yaml"
VERSION = 2  # of a cell's JSON: bump when what a cell measures changes


def load() -> str:
    """The 1-minute load average (``uptime``'s first figure)."""
    return f"{os.getloadavg()[0]:.2f}"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def map_build(
    folder: Path,
    pipeline: str | None,
    map_config: Path | None = None,
    keyframes: KeyframeParams | None = None,
) -> MapBuild:
    """How the true-pose map at ``folder`` is built: the pipelines and preprocessing of the MapBuild YAML
    ``map_config`` (e.g. configs/map_cross_sensor.yaml), else ``pipeline`` alone, or (None) the map default's;
    its places ``keyframes`` when given."""
    base: dict[str, Any] = {} if map_config is None else read_config_file(map_config)
    if map_config is None and pipeline is not None:
        base["pipelines"] = [{"name": pipeline}]
    if keyframes is not None:
        base["keyframes"] = keyframes.model_dump(mode="json")
    return resolve(MapBuild, {**base, "source": {}, "out": str(folder), "overwrite": True}, where="map build")


def map_pipelines(pipeline: str | None, map_config: Path | None = None) -> list[PipelineSpec]:
    """The true-pose map's pipelines (`map_build`)."""
    return list(map_build(Path("."), pipeline, map_config).pipelines)


def map_thresholds(
    pipeline: str | None, sensor: str, map_config: Path | None = None
) -> dict[str, float | None]:
    """The operating thresholds the true-pose map records for its pipelines on ``sensor`` (global search's)."""
    return {p.name: p.threshold_for(sensor) for p in map_pipelines(pipeline, map_config)}


def map_params(pipeline: str | None, sensor: str, map_config: Path | None = None) -> str:
    """A key of the parameters the true-pose map's pipelines run with on ``sensor`` (`placerec.sensor_presets`):
    a map or cell made with other parameters (the same thresholds) is not reused. (A map config's preprocessing is
    in the map folder's name and the cells' settings.)"""
    return stable_hash(
        {
            p.name: pipeline_params(p.name, p.params, sensor=sensor).saved_dump()
            for p in map_pipelines(pipeline, map_config)
        }
    )


def pipeline_label(pipeline: str | None, map_config: Path | None = None) -> str:
    label = "+".join(p.name for p in map_pipelines(pipeline, map_config))
    return label if map_config is None else f"{label}-{Path(map_config).stem}"


def settings(
    sensor: str,
    pipeline: str | None,
    scans: int | None,
    kidnaps: int,
    map_closes_loop: bool = False,
    join_pipelines: tuple[str, ...] = (),
    slam_odometry: str = "dataset",
    odometry_gate: bool = False,
    map_config: Path | None = None,
    localize_sets: tuple[str, ...] = (),
    slam_map_sets: tuple[str, ...] = (),
    slam_join_sets: tuple[str, ...] = (),
    keyframes: KeyframeParams | None = None,
) -> dict[str, Any]:
    """What a cell depends on besides its world, seed and kind (stored with it; a mismatch recomputes it)."""
    out = {"version": VERSION, "sensor": sensor, "pipeline": pipeline_label(pipeline, map_config), "scans": scans,
           "kidnaps": kidnaps, "slam_config": slam_config(keyframes), "correct_within": [CORRECT_M, CORRECT_DEG],
           "thresholds": map_thresholds(pipeline, sensor, map_config),
           "params": map_params(pipeline, sensor, map_config)}  # fmt: skip
    if map_config is not None:
        out["map_config"] = {"path": str(map_config), "content": read_config_file(map_config)}
    if localize_sets:
        out["localize_sets"] = list(localize_sets)
    if slam_map_sets:
        out["slam_map_sets"] = list(slam_map_sets)
    if slam_join_sets:
        out["slam_join_sets"] = list(slam_join_sets)
    if map_closes_loop:
        out["map_closes_loop"] = True
    if join_pipelines:
        out["join_pipelines"] = list(join_pipelines)
    if slam_odometry != "dataset":
        out["slam_odometry"] = slam_odometry
    if odometry_gate:
        out["odometry_gate"] = True
    if keyframes is not None:
        out["keyframes"] = keyframes.model_dump(mode="json")
    return out


def slam_config(keyframes: KeyframeParams | None) -> str:
    """Both SLAM sessions' config: `SLAM_CONFIG`, or with keyframes `SLAM_CONFIG_KEYFRAMES`."""
    return SLAM_CONFIG if keyframes is None else SLAM_CONFIG_KEYFRAMES


def slam_loop_pipeline(keyframes: KeyframeParams | None) -> str:
    """The loop pipeline of both SLAM sessions (`slam_config`), which a join searches the map with."""
    from placerec.slam_app.config import load_slam_config

    return load_slam_config(slam_config(keyframes), []).loops.pipeline.name


def capture(sensor: str) -> KeyframeParams:
    """The keyframes the sensor benchmark accumulates ``sensor``'s frames into (`CAPTURE`); `ConfigError` for a
    sensor it drives one scan a metre."""
    if sensor not in CAPTURE:
        raise ConfigError(f"--keyframes: {sensor!r} is not captured in keyframes; one of {sorted(CAPTURE)}")
    return KeyframeParams(**CAPTURE[sensor]["keyframes"])


def slam_suffix(slam_odometry: str, odometry_gate: bool) -> str:
    """What names a cell's file and its SLAM map apart by how the SLAM sessions ran (the demo's drift, ungated: "")."""
    return ("" if slam_odometry == "dataset" else f"-{slam_odometry}") + ("-gate" if odometry_gate else "")


def odometry(pair: SessionPair) -> np.ndarray:
    """Session 2's drifting odometry (the simulator's default drift, seeded by the query's seed), re-based so that
    its first pose is the identity."""
    odo = drift_poses(np.asarray(pair.query.poses), OdometryDrift(), pair.query.seed)
    return np.linalg.inv(odo[0]) @ odo


@dataclass(frozen=True)
class Queries:
    """What relocalisation and the kidnaps localise in session 2: ``seq``, its scans or its keyframes, each
    standing at the scan ``places[i]`` of ``pair.query`` (its truth, overlap and nearest map scan; a keyframe's
    last scan), with the session's drifting ``odometry`` there."""

    seq: Sequence
    places: np.ndarray
    odometry: np.ndarray


def queries(pair: SessionPair, keyframes: KeyframeParams | None = None) -> Queries:
    """Session 2's scans, or its ``keyframes`` accumulated along its drifting odometry (`odometry`)."""
    odo = odometry(pair)
    if keyframes is None:
        return Queries(pair.query, np.arange(len(pair.query)), odo)
    kseq = KeyframeSequence(pair.query, keyframes, odo)
    return Queries(kseq, kseq.reference_indices, kseq.keyframe_poses)


# -- the two maps of a world and seed -------------------------------------------------------------------------
def true_map(
    pair: SessionPair,
    pipeline: str | None,
    folder: Path,
    map_config: Path | None = None,
    keyframes: KeyframeParams | None = None,
) -> Path:
    """Session 1's map at its true poses, of ``keyframes`` when given (built once; reused when ``folder`` holds one
    with the same thresholds and parameters; a map config's and keyframe maps have folders of their own)."""
    places = None if keyframes is None else keyframes.model_dump(mode="json")
    made = MapArtifact.open(folder) if (folder / "manifest.json").is_file() else None
    if made is not None and made.places == places:
        held = made.manifest.pipelines
        sensor = pair.map.sensor.name
        if {p.name: p.threshold for p in held} == map_thresholds(
            pipeline, sensor, map_config
        ) and stable_hash({p.name: p.params for p in held}) == map_params(pipeline, sensor, map_config):
            return folder
    return write_map(pair.map, map_build(folder, pipeline, map_config, keyframes))


def slam_overrides(
    pair: SessionPair,
    role: str,
    odometry: str = "dataset",
    gate: bool = False,
    keyframes: KeyframeParams | None = None,
) -> list[str]:
    """The SLAM config's overrides for session ``role`` (``map`` or ``query``) of ``pair``; ``odometry``: the
    config's ``odometry.source`` (``dataset``: the demo's drift on the true poses; ``kiss-icp``: on the scans);
    ``gate``: ``loops.odometry_gate`` at its defaults (`placerec.odometry_gate`); ``keyframes``: the loops'
    places (`SLAM_CONFIG_KEYFRAMES`'s pipeline at its operating threshold on the sensor)."""
    seq = pair.map if role == "map" else pair.query
    world = pair.map.world
    sets = [f"dataset.simulator.world={world.preset}", f"dataset.simulator.sensor={seq.sensor.name}",
            f"dataset.simulator.seed={seq.seed}", f"dataset.simulator.world_seed={world.seed}",
            f"dataset.simulator.unit_seed={pair.map.seed}", f"odometry.drift.seed={seq.seed}",
            f"odometry.source={odometry}", "output.progress=false", "output.figures=false",
            *(["loops.odometry_gate={}"] if gate else [])]  # fmt: skip
    if keyframes is not None:
        threshold = PIPELINES[slam_loop_pipeline(keyframes)].threshold_for(seq.sensor.name)
        sets += [
            f"loops.keyframes={json.dumps(keyframes.model_dump(mode='json'))}",
            f"loops.threshold={threshold}",
        ]
    return sets


def slam_map(
    pair: SessionPair,
    folder: Path,
    map_pipelines: tuple[str, ...] = (),
    odometry: str = "dataset",
    gate: bool = False,
    slam_sets: tuple[str, ...] = (),
    keyframes: KeyframeParams | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Session 1 through `slam_sequence` with its map saved (run once; its ATE kept beside it), holding the
    ``map_pipelines`` databases as well (``output.map_pipelines``), its SLAM config overridden by ``slam_sets``
    (`slam_overrides` for ``keyframes``)."""
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import loop_pipeline, map_writer_for, slam_sequence

    info_path = folder.parent / f"{folder.name}.json"
    sets = [
        *slam_overrides(pair, "map", odometry, gate, keyframes),
        f"output.save_map={folder}",
        "output.overwrite_map=true",
        *slam_sets,
    ]
    if map_pipelines:
        sets.append(f"output.map_pipelines={list(map_pipelines)}")
    cfg = load_slam_config(slam_config(keyframes), sets)
    sensor = pair.map.sensor.name
    specs = [cfg.loops.pipeline, *(PipelineSpec(name=n) for n in map_pipelines)]
    params = [pipeline_params(p.name, p.params, sensor=sensor).saved_dump() for p in specs]
    key = stable_hash({"config": cfg.model_dump(mode="json"), "params": params})
    if (folder / "manifest.json").is_file() and info_path.is_file():
        info = json.loads(info_path.read_text())
        if info.get("key") == key:  # made with the same config and pipeline parameters on the sensor
            return folder, info
    t0 = time.perf_counter()
    rec = loop_pipeline(cfg, pair.map)
    with map_writer_for(cfg, pair.map, rec) as writer:
        result = slam_sequence(cfg, pair.map, rec, None, writer)
    err = trajectory_errors(result.optimized, pair.map.poses)
    info = {"scans": len(pair.map), "ate_rmse": err.ate_rmse, "loops": len(result.loops),
            "seconds": round(time.perf_counter() - t0, 1), "key": key}  # fmt: skip
    info_path.write_text(json.dumps(info))
    return folder, info


# -- 1. relocalisation ------------------------------------------------------------------------------------------
def relocalise(
    pair: SessionPair, map_folder: Path, params: LocalizerParams, q: Queries | None = None
) -> tuple[dict[str, Any], Localizer]:
    """Session 2 (``q``: its scans or keyframes, default its scans) tracked in order against the true-pose map
    with its drifting odometry (module docstring)."""
    loc = Localizer(map_folder, params)
    q = q or queries(pair)
    fixes = [loc.track(q.seq[i], q.odometry[i]) for i in range(len(q.seq))]
    truth = np.asarray(pair.query.poses)[q.places]
    run = LocalizeRun(q.seq.name, loc.map, fixes, np.asarray(pair.query.timestamps)[q.places], truth, "tracking",
                      "simulated drift", params)  # fmt: skip
    correct = run.correct()
    assert correct is not None
    te, re = run.errors()
    accepted = np.array([f.accepted for f in fixes], bool)
    wrong = accepted & ~correct
    inside = np.asarray(pair.overlap, bool)[q.places]
    modes = np.array([f.mode for f in fixes])
    times = np.array([f.time_ms for f in fixes])
    n_in = int(inside.sum())
    kf = np.asarray(loc.map.poses)
    out = {
        "scans": len(q.seq),
        "map_keyframes": len(loc.map),
        "overlap_scans": n_in,
        "correct_in_overlap": int((correct & inside).sum()),
        "success": float((correct & inside).sum()) / n_in if n_in else None,
        "accepted": int(accepted.sum()),
        "wrong": int(wrong.sum()),
        "outside_accepted": int((accepted & ~inside).sum()),
        "outside_wrong": int((wrong & ~inside).sum()),
        "tracking_ms": timing_summary(times[modes == "tracking"]),
        "global_ms": timing_summary(times[modes == "global"]),
        "by_mode": {m: int((accepted & (modes == m)).sum()) for m in ("tracking", "global")},
        # the scores of the accepted global fixes, right and wrong: what a global threshold is chosen on (tuning)
        "global_scores": _global_scores(fixes, correct),
        "max_error_accepted": [float(np.nanmax(te[accepted])), float(np.nanmax(re[accepted]))]
        if accepted.any()
        else None,
        # the failures, for the report: every overlapping scan without a correct fix, and every wrong fix
        "missed": [
            _row(i, f, te[i], re[i], pair, kf, int(q.places[i]))
            for i, f in enumerate(fixes)
            if inside[i] and not correct[i]
        ],
        "wrong_fixes": [
            _row(i, f, te[i], re[i], pair, kf, int(q.places[i])) for i, f in enumerate(fixes) if wrong[i]
        ],
    }
    return out, loc


def _global_scores(fixes: list[Fix], correct: np.ndarray) -> dict[str, list[float]]:
    """The verified scores of the accepted global fixes among ``fixes``: ``right`` (``correct``) and ``wrong``."""
    out: dict[str, list[float]] = {"right": [], "wrong": []}
    for f, ok in zip(fixes, correct, strict=True):
        if f.accepted and f.mode == "global":
            out["right" if ok else "wrong"].append(round(float(f.score), 4))
    return out


def _row(
    i: int, f: Fix, te: float, re: float, pair: SessionPair, keyframes: np.ndarray, scan: int
) -> dict[str, Any]:
    """Query ``i``'s fix for the report (``scan``: the scan of ``pair.query`` it stands at); ``keyframe_m``: how
    far (horizontally) the keyframe its answer was verified against lies from its true position (the retrieval
    was right when it is small)."""
    idx, dist = pair.nearest_map
    kf_m = None
    if f.keyframe_id >= 0:
        kf_m = round(
            float(np.linalg.norm(keyframes[f.keyframe_id, :2, 3] - pair.query.poses[scan][:2, 3])), 2
        )
    return {"scan": i, "accepted": f.accepted, "mode": f.mode, "reason": f.reason,
            "error": None if np.isnan(te) else [round(float(te), 3), round(float(re), 2)],
            "score": None if np.isnan(f.score) else round(f.score, 3),
            "fitness": None if np.isnan(f.fitness) else round(f.fitness, 3), "keyframe_m": kf_m,
            "map_dist": round(float(dist[scan]), 2), "heading_diff": round(float(pair.heading_diff[scan]), 1)}  # fmt: skip


# -- 2. kidnap --------------------------------------------------------------------------------------------------
def kidnap(
    pair: SessionPair, loc: Localizer, n_trials: int, seed: int, q: Queries | None = None
) -> dict[str, Any]:
    """`kidnap_trials` against ``loc`` over ``q`` (default: session 2's scans; keyframes: over their places,
    module docstring); ``skipped`` says why there are none."""
    q = q or queries(pair)
    framewise = q.seq is pair.query
    try:
        trials = kidnap_trials(pair, n_trials, seed, places=None if framewise else q.places)
    except ConfigError as exc:
        return {"trials": 0, "skipped": str(exc)}
    odo = q.odometry
    truth = np.asarray(pair.query.poses)[q.places]
    found, false_first, first = 0, 0, []
    failures: list[dict[str, Any]] = []
    scores: dict[str, list[float]] = {"right": [], "wrong": []}  # of the first fixes by global search
    for t in trials:
        loc.reset()
        seen = [odo[i] for i in t.tracking]
        for i, T in zip(t.tracking, seen, strict=True):
            loc.track(q.seq[int(i)], T)
        # the odometry does not see the teleport: one ordinary step on, then the new place's relative motion
        step = np.linalg.inv(odo[t.tracking[-2]]) @ odo[t.tracking[-1]] if t.teleport > 1 else np.eye(4)
        start = seen[-1] @ step
        hit, why = None, []
        for n, i in enumerate(t.after):
            f = loc.track(q.seq[int(i)], start @ np.linalg.inv(odo[t.after[0]]) @ odo[i])
            if f.accepted:
                hit = (n, int(i), f)
                break
            why.append(f.reason)
        if hit is None:
            failures.append({"after": [int(i) for i in t.after], "reason": "no fix", "reasons": why})
            continue
        n, i, f = hit
        assert f.T_world_query is not None
        te, re = pose_errors(f.T_world_query, truth[i])
        right = bool(te[0] <= CORRECT_M and re[0] <= CORRECT_DEG)
        if f.mode == "global":
            scores["right" if right else "wrong"].append(round(float(f.score), 4))
        if not right:
            false_first += 1
            failures.append(
                {"scan": i, "reason": f"wrong first fix {te[0]:.2f} m {re[0]:.1f} deg ({f.mode})"}
            )
        elif n < 3:
            found += 1
            first.append(n + 1)
        else:
            failures.append(
                {"scan": i, "reason": f"first fix at scan {n + 1} after the teleport", "reasons": why}
            )
    return {"trials": len(trials), "fixed_within_3": found, "success": found / len(trials),
            "false_first_fixes": false_first, "median_scans_to_fix": float(np.median(first)) if first else None,
            "global_scores": scores, "failures": failures}  # fmt: skip


# -- 3. multi-session -------------------------------------------------------------------------------------------
def multisession(
    pair: SessionPair,
    map_folder: Path,
    join_pipelines: tuple[str, ...] = (),
    odometry: str = "dataset",
    gate: bool = False,
    slam_sets: tuple[str, ...] = (),
    keyframes: KeyframeParams | None = None,
) -> dict[str, Any]:
    """Session 2 through `slam_sequence` against the map at ``map_folder`` (module docstring), with the map's
    ``join_pipelines`` searching it too (``prior_map.join_pipelines``), on ``odometry`` with or without the
    odometry ``gate`` (`slam_overrides`), then ``slam_sets`` (its SLAM config's ``key=value`` overrides)."""
    from placerec.slam_app.config import load_slam_config
    from placerec.slam_app.run import open_prior_map, slam_sequence

    sets = [*slam_overrides(pair, "query", odometry, gate, keyframes), f"prior_map.path={map_folder}"]
    if join_pipelines:
        sets.append(f"prior_map.join_pipelines={list(join_pipelines)}")
    if pair.kind == "sensor":
        sets.append("prior_map.allow_other_sensor=true")
    cfg = load_slam_config(slam_config(keyframes), [*sets, *slam_sets])
    t0 = time.perf_counter()
    prior, rec = open_prior_map(cfg, pair.query)
    result = slam_sequence(cfg, pair.query, rec, None, None, prior)
    ms = result.multisession
    assert ms is not None
    gt1 = np.asarray(pair.map.poses)[np.asarray(prior.scan_index)]  # the map's keyframes' true poses
    gt2 = np.asarray(pair.query.poses)
    M = len(prior)
    out: dict[str, Any] = {
        "joined": bool(ms.joined), "summary": ms.summary(), "map_keyframes": M,
        "inter_loops": len(ms.inter_loops), "rejected_at_join": len(ms.rejected_at_join),
        "pending": len(ms.pending), "rejected_by_graph": int(ms.rejected_by_graph),
        "refused_by_gate": len(ms.refused_by_gate), "seconds": round(time.perf_counter() - t0, 1),
    }  # fmt: skip
    out["false_inter_loops"] = _false(ms.inter_loops, gt1, gt2, M)
    out["false_inter_loops_kept"] = sum(  # in the graph at a weight >= 0.5
        1
        for lp, w in zip(ms.inter_loops, ms.inter_weights, strict=True)
        if w >= 0.5 and _false([lp], gt1, gt2, M)
    )
    out["false_rejected_at_join"] = _false(ms.rejected_at_join, gt1, gt2, M)
    out["false_pending"] = _false(ms.pending, gt1, gt2, M)
    out["false_refused_by_gate"] = _false(ms.refused_by_gate, gt1, gt2, M)
    out["session_ate_rmse"] = trajectory_errors(ms.session_poses, gt2).ate_rmse
    out.update(merged_ate_rmse=None, merged_ate_max=None, map_ate_rmse=None, join_error_m=None)
    if ms.joined:
        merged = trajectory_errors(
            np.concatenate([ms.map_poses, ms.session_poses]), np.concatenate([gt1, gt2])
        )
        out.update(merged_ate_rmse=merged.ate_rmse, merged_ate_max=merged.ate_max,
                   map_ate_rmse=trajectory_errors(ms.map_poses, gt1).ate_rmse,
                   join_error_m=_join_error(pair, ms.map_poses, ms.session_poses, prior.scan_index))  # fmt: skip
    return out


def _join_error(pair: SessionPair, map_poses: np.ndarray, session_poses: np.ndarray, scan_index: Any) -> Any:
    """How far each overlapping session-2 pose is from where the map puts it: the nearest map keyframe's estimate
    moved by the true relative pose, ``map_poses[k] @ inv(GT1[m]) @ GT2[q]`` (m: its scan). This is the join's own
    error, free of the map's drift (a map drifted by 2 m with the session joined exactly onto it gives 0).
    ``{"median", "p95", "max"}`` in metres over the overlap (None: no overlap)."""
    kf_of_scan = {int(s): k for k, s in enumerate(np.asarray(scan_index))}
    gt1, gt2 = np.asarray(pair.map.poses), np.asarray(pair.query.poses)
    idx, _ = pair.nearest_map
    errs = []
    for q in np.flatnonzero(pair.overlap):
        m = int(idx[q])
        k = kf_of_scan.get(m)
        if k is None:
            continue
        predicted = map_poses[k] @ np.linalg.inv(gt1[m]) @ gt2[q]
        errs.append(float(np.linalg.norm(predicted[:3, 3] - session_poses[q][:3, 3])))
    if not errs:
        return None
    e = np.asarray(errs)
    return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "max": float(e.max())}


def _false(loops: list, gt1: np.ndarray, gt2: np.ndarray, M: int) -> int:
    """Loops (map place m, session scan M + s) more than 1 m / 5 deg from the truth ``inv(GT1[m]) @ GT2[s]``."""
    bad = 0
    for lp in loops:
        m, s = int(lp.match_id), int(lp.query_id) - M
        truth = np.linalg.inv(gt1[m]) @ gt2[s]
        te, re = pose_errors(np.asarray(lp.T_match_query), truth)
        bad += int(not (te[0] <= CORRECT_M and re[0] <= CORRECT_DEG))
    return bad


def localizer_params(
    pipeline: str | None, kind: str, sets: list[str] | tuple[str, ...] = ()
) -> LocalizerParams:
    """Relocalisation's and the kidnaps' settings: global search on ``pipeline`` (None: each of the map's), another
    sensor allowed for the ``sensor`` kind, then ``sets`` (``key=value``, `placerec.config.apply_overrides`)."""
    base: dict[str, Any] = {"pipeline": pipeline, "allow_other_sensor": kind == "sensor"}
    return resolve(LocalizerParams, apply_overrides(base, list(sets)), where="--localize-set")


# -- a cell -----------------------------------------------------------------------------------------------------
def run_cell(
    world: str,
    seed: int,
    kind: str,
    sensor: str = "vlp16",
    pipeline: str | None = None,
    scans: int | None = None,
    kidnaps: int = 10,
    work: Path = Path("results/eval_sessions/maps"),
    params: LocalizerParams | None = None,
    map_closes_loop: bool = False,
    join_pipelines: tuple[str, ...] = (),
    slam_odometry: str = "dataset",
    odometry_gate: bool = False,
    map_config: Path | None = None,
    slam_map_sets: tuple[str, ...] = (),
    slam_join_sets: tuple[str, ...] = (),
    keyframes: KeyframeParams | None = None,
) -> dict[str, Any]:
    """One world x seed x kind: relocalisation, kidnap and multi-session (module docstring), of ``keyframes``
    when given (`capture`). The maps of session 1 are built under ``work`` once per world, seed, sensor, pipeline
    (or ``map_config``), cut, keyframes, SLAM odometry and odometry gate."""
    frames = {} if keyframes is None else {k: CAPTURE[sensor][k] for k in ("rate_hz", "sweep_motion")}
    pair = make_session_pair(
        world, sensor, seed, kind, n_scans=scans, map_closes_loop=map_closes_loop, **frames
    )
    tag = f"{world}-{sensor}-s{seed}-n{scans or 'all'}{'-closed' if map_closes_loop else ''}"
    tag += "" if keyframes is None else "-kf"
    params = params or LocalizerParams(pipeline=pipeline, allow_other_sensor=kind == "sensor")
    t0 = time.perf_counter()
    out: dict[str, Any] = {
        "world": world,
        "seed": seed,
        "kind": kind,
        **pair.describe(),
        "query_seed": pair.query.seed,
    }
    log(f"{tag} {kind}: true-pose map ({len(pair.map)} scans)")
    label = pipeline_label(pipeline, map_config)
    tmap = true_map(pair, pipeline, work / f"{tag}-{label}-truth", map_config, keyframes)
    q = queries(pair, keyframes)
    inside = int(pair.overlap[q.places].sum())
    log(
        f"{tag} {kind}: relocalisation ({len(q.seq)} {'scans' if keyframes is None else 'keyframes'}, {inside} in the overlap)"
    )
    out["relocalisation"], loc = relocalise(pair, tmap, params, q)
    log(f"{tag} {kind}: kidnap")
    out["kidnap"] = kidnap(pair, loc, kidnaps, seed, q)
    log(f"{tag} {kind}: SLAM session 1")
    joined_by = "".join(f"-{name}" for name in join_pipelines)  # a map holding those databases too
    on = slam_suffix(slam_odometry, odometry_gate)
    smap, out["slam_session1"] = slam_map(
        pair,
        work / f"{tag}-slam{joined_by}{on}",
        join_pipelines,
        slam_odometry,
        odometry_gate,
        slam_map_sets,
        keyframes,
    )
    log(f"{tag} {kind}: SLAM session 2 against it")
    out["multisession"] = multisession(
        pair, smap, join_pipelines, slam_odometry, odometry_gate, slam_join_sets, keyframes
    )
    if slam_loop_pipeline(keyframes) in {p.name for p in map_pipelines(pipeline, map_config)}:
        log(
            f"{tag} {kind}: SLAM session 2 against the true-pose map (diagnostic: the join without the map's drift)"
        )
        out["multisession_truth_map"] = multisession(
            pair, tmap, join_pipelines, slam_odometry, odometry_gate, slam_join_sets, keyframes
        )
    else:  # that map holds other pipelines than the SLAM loop pipeline a join searches (a map config's, ...)
        out["multisession_truth_map"] = None
    out["seconds"] = round(time.perf_counter() - t0, 1)
    out["load"] = load()
    return out


def cell_line(c: dict[str, Any]) -> str:
    """One markdown table row of a cell."""
    r, k, m, t = c["relocalisation"], c["kidnap"], c["multisession"], c["multisession_truth_map"]

    def pct(x: float | None) -> str:
        return "-" if x is None else f"{100 * x:.1f} %"

    def num(x: float | None, f: str = ".2f") -> str:
        return "-" if x is None or x != x else format(x, f)

    kid = "-" if not k["trials"] else f"{k['fixed_within_3']}/{k['trials']} ({k['false_first_fixes']} false)"
    join = "-" if m["join_error_m"] is None else num(m["join_error_m"]["median"])
    refused = m.get("refused_by_gate", 0)  # cells run with --odometry-gate: the closures it kept out
    gated = f", {refused} refused by the gate ({m['false_refused_by_gate']} false)" if refused else ""
    return (
        f"| {c['world']} | {c['seed']} | {c['kind']} | {r['overlap_scans']}/{r['scans']} | "
        f"{r['correct_in_overlap']} ({pct(r['success'])}) | {r['wrong']} | "
        f"{r['outside_accepted']} ({r['outside_wrong']} wrong) | "
        f"{num(r['tracking_ms']['median'], '.1f')} / {num(r['tracking_ms']['p95'], '.1f')} | "
        f"{num(r['global_ms']['median'], '.0f')} | {kid} | {'yes' if m['joined'] else 'no'} | "
        f"{m['inter_loops']} ({m['false_inter_loops']} false{gated}) | {num(c['slam_session1']['ate_rmse'])} | "
        f"{num(m['merged_ate_rmse'])} | {join} | "
        + ("- |" if t is None else f"{num(t['merged_ate_rmse'])} ({t['false_inter_loops']} false) |")
    )


HEADER = (
    "| world | seed | kind | overlap / scans | correct in overlap | wrong fixes | fixes outside overlap | "
    "tracking ms median / p95 | global ms median | kidnap fixed <= 3 scans | joined | inter-session loops | "
    "session 1 ATE m | merged ATE m | join error m (median) | merged ATE on the true-pose map m |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--worlds", nargs="+", default=list(TEST_WORLDS))
    ap.add_argument("--seeds", nargs="+", type=int, default=list(TEST_SEEDS), help="default: the TEST seeds")
    ap.add_argument(
        "--kinds", nargs="+", default=list(KINDS), help="also: sensor (another sensor for session 2)"
    )
    ap.add_argument(
        "--scans", type=int, default=None, help="cut each session to this many scans (quick runs)"
    )
    ap.add_argument("--sensor", default="vlp16")
    ap.add_argument("--pipeline", default=None, help="the map's one pipeline (default: the map default's)")
    ap.add_argument("--kidnaps", type=int, default=10, help="kidnap trials per cell")
    ap.add_argument("--out", type=Path, default=Path("results/eval_sessions"), help="cell JSON cache")
    ap.add_argument("--work", type=Path, default=None, help="session 1's maps (default OUT/maps)")
    ap.add_argument("--fresh", action="store_true", help="recompute cached cells (maps are kept)")
    ap.add_argument(
        "--map-closes-loop",
        action="store_true",
        help="session 1 drives its loop's first street again at the end (a loop its SLAM can close)",
    )
    ap.add_argument(
        "--join-pipelines",
        nargs="+",
        default=[],
        help="more map pipelines that also search the maps for inter-session closures in the SLAM runs against"
        " them (prior_map.join_pipelines; session 1's SLAM then saves their databases too: output.map_pipelines)",
    )
    ap.add_argument(
        "--slam-odometry",
        choices=["dataset", "kiss-icp"],
        default="dataset",
        help="the odometry of both SLAM sessions: dataset (the demo config's drift on the true poses) or kiss-icp"
        " (KISS-ICP on the scans); relocalisation and kidnaps keep the simulated drift",
    )
    ap.add_argument(
        "--odometry-gate",
        action="store_true",
        help="both SLAM sessions with loops.odometry_gate at its defaults: intra-session closures checked against"
        " the odometry, inter-session ones after the join against the joined estimate",
    )
    ap.add_argument(
        "--map-config",
        type=Path,
        default=None,
        help="the true-pose map's pipelines and preprocessing from this MapBuild YAML (e.g."
        " configs/map_cross_sensor.yaml) instead of --pipeline; relocalisation and kidnaps search it",
    )
    ap.add_argument(
        "--localize-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a LocalizerParams field for relocalisation and kidnaps, e.g. threshold=0.05 (repeatable)",
    )
    ap.add_argument(
        "--slam-map-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an override of session 1's SLAM config (the map session), e.g."
        " output.map_pipeline_params={scan-context: {...}} (repeatable)",
    )
    ap.add_argument(
        "--slam-join-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an override of session 2's SLAM config (the session joined to the map), e.g."
        " prior_map.join_threshold=0.05 (repeatable)",
    )
    ap.add_argument(
        "--keyframes",
        action="store_true",
        help="a Livox-style or solid-state sensor's sessions in keyframes, as the sensor benchmark captures it"
        " (module docstring)",
    )
    args = ap.parse_args(argv)
    keyframes = capture(args.sensor) if args.keyframes else None
    if args.map_config is not None and args.pipeline is not None:
        raise SystemExit("--map-config names the map's pipelines: not with --pipeline")
    work = args.work or args.out / "maps"
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    join = tuple(args.join_pipelines)
    want = settings(
        args.sensor,
        args.pipeline,
        args.scans,
        args.kidnaps,
        args.map_closes_loop,
        join,
        args.slam_odometry,
        args.odometry_gate,
        args.map_config,
        tuple(args.localize_set),
        tuple(args.slam_map_set),
        tuple(args.slam_join_set),
        keyframes,
    )
    cells = []
    t0 = time.perf_counter()
    for world in args.worlds:
        for seed in args.seeds:
            for kind in args.kinds:
                closed = "-closed" if args.map_closes_loop else ""
                on = slam_suffix(args.slam_odometry, args.odometry_gate)
                label = pipeline_label(args.pipeline, args.map_config)
                kf = "" if keyframes is None else "-kf"
                name = f"{world}-{args.sensor}-s{seed}-{kind}-{label}-n{args.scans or 'all'}{closed}{on}{kf}.json"
                path = args.out / name
                if path.is_file() and not args.fresh:
                    cached = json.loads(path.read_text())
                    if cached.get("settings") == want:
                        log(f"{name}: cached")
                        cells.append(cached)
                        continue
                params = localizer_params(args.pipeline, kind, args.localize_set)
                cell = run_cell(world, seed, kind, args.sensor, args.pipeline, args.scans, args.kidnaps, work,
                                params, map_closes_loop=args.map_closes_loop, join_pipelines=join,
                                slam_odometry=args.slam_odometry, odometry_gate=args.odometry_gate,
                                map_config=args.map_config, slam_map_sets=tuple(args.slam_map_set),
                                slam_join_sets=tuple(args.slam_join_set), keyframes=keyframes)  # fmt: skip
                cell["settings"] = want
                tmp = path.with_suffix(".tmp")
                tmp.write_text(json.dumps(cell, indent=1))
                tmp.replace(path)
                cells.append(cell)
                log(f"{name}: done in {cell['seconds']:.0f} s (load {cell['load']})")
                print(HEADER.splitlines()[0] + "\n" + cell_line(cell), flush=True)
    print(HEADER)
    for c in cells:
        print(cell_line(c))
    summary = _summary(cells)
    print(json.dumps({"tool": "eval_sessions", **want, "worlds": args.worlds, "seeds": args.seeds,
                      "kinds": args.kinds, "cells": len(cells), **summary,
                      "seconds": round(time.perf_counter() - t0), "load": load(), "cpus": os.cpu_count()}))  # fmt: skip
    return summary


def _summary(cells: list[dict[str, Any]]) -> dict[str, Any]:
    """The issue's targets over every cell (the overlap's success per world, kidnaps, ATE, false loops)."""
    over = [c for c in cells if c["relocalisation"]["overlap_scans"]]
    kid = [c["kidnap"] for c in cells if c["kidnap"]["trials"]]
    ates = [
        c["multisession"]["merged_ate_rmse"]
        for c in cells
        if c["multisession"]["merged_ate_rmse"] is not None
    ]
    disjoint = [c for c in cells if c["kind"] == "disjoint"]
    by_world: dict[str, list[int]] = {}
    for c in over:  # #29's relocalisation target is per world: the overlap of all its cells together
        got = by_world.setdefault(c["world"], [0, 0])
        got[0] += c["relocalisation"]["correct_in_overlap"]
        got[1] += c["relocalisation"]["overlap_scans"]
    return {
        "min_success": min((c["relocalisation"]["success"] for c in over), default=None),
        "success_by_world": {w: n / total for w, (n, total) in by_world.items()},
        "wrong_fixes": sum(c["relocalisation"]["wrong"] for c in cells),
        "kidnap_success": sum(k["fixed_within_3"] for k in kid) / max(sum(k["trials"] for k in kid), 1),
        "kidnap_false": sum(k["false_first_fixes"] for k in kid),
        "max_merged_ate": max(ates, default=None),
        "false_inter_loops": sum(c["multisession"]["false_inter_loops"] for c in cells),
        "refused_by_gate": sum(c["multisession"].get("refused_by_gate", 0) for c in cells),
        "false_refused_by_gate": sum(c["multisession"].get("false_refused_by_gate", 0) for c in cells),
        "max_merged_ate_truth_map": max(
            (
                c["multisession_truth_map"]["merged_ate_rmse"] or 0.0
                for c in cells
                if c["multisession_truth_map"] is not None
            ),
            default=None,
        ),
        "max_join_error_median": max(
            (c["multisession"]["join_error_m"]["median"] for c in cells if c["multisession"]["join_error_m"]),
            default=None,
        ),
        "disjoint_joined": sum(c["multisession"]["joined"] for c in disjoint),
        "not_joined": [
            f"{c['world']}-{c['seed']}-{c['kind']}"
            for c in cells
            if c["kind"] != "disjoint" and not c["multisession"]["joined"]
        ],  # fmt: skip
    }


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
