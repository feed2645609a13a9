"""The results folder of ``placerec slam``.

* ``config.yaml`` — the resolved config;
* ``poses_kitti.txt`` / ``poses_tum.txt`` — the batch-optimised trajectory (TUM timestamps: the dataset's, else
  the scan index); ``odometry_kitti.txt`` and ``online_kitti.txt`` (iSAM2's estimate at the last scan) beside it,
  ``ground_truth_kitti.txt`` when the dataset has poses;
* ``graph.g2o`` — the pose graph (vertices at the optimised poses, odometry and loop edges with information);
* ``closures.mcap`` — the optimised poses and the loop edges for Foxglove (`placerec.io.mcap_export`, docs/slam.md):
  the graph's loops (rejected when the batch step weighs them below 0.5) and the candidates verification rejected
  (`loop_edges`), at the scans' times;
* ``loops.csv`` — one row per loop edge: ``match_id, query_id, score, injected, x, y, z, roll, pitch, yaw``
  (``T_match_query`` as in `placerec.experiment.candidates`), ``residual_sigmas, weight`` (`BATCH_COLUMNS`), and
  with ground truth ``true_distance``,
  ``translation_error``, ``rotation_error_deg``, ``false`` (off by more than the evaluation's limits) and
  ``opposite`` (headings more than 135 deg apart: a reverse-direction revisit);
* ``metrics.json`` — ATE / RPE of the odometry, the online and the optimised trajectory, the loop counts, per-scan
  times (online loop with and without odometry, each stage, iSAM2 updates) and the batch optimiser's summary;
  with ``loops.realtime`` also ``realtime`` (`placerec.realtime.RealtimeStats.as_dict`: scans over budget,
  closures deferred, the detector's and its worker's time per scan) and the ``wait`` stage;
* ``trajectory.png`` (before / after with the loop edges), ``index.html``; ``map.ply`` with ``output.map_ply``.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from placerec.eval.metrics import timing_summary
from placerec.eval.pose_error import pose_errors
from placerec.eval.trajectory import trajectory_errors
from placerec.experiment import figures
from placerec.experiment.candidates import pose_to_xyzrpy
from placerec.experiment.run_folder import finite_or_null, json_default, point_latest
from placerec.experiment.tables import print_rows, write_html_page
from placerec.io import write_kitti_poses, write_tum_poses
from placerec.io.atomic import atomic_write
from placerec.io.mcap_export import LoopEdge, write_closures_mcap
from placerec.maps.artifact import MapArtifact
from placerec.preprocess import preprocess_scan
from placerec.slam.multisession import MultiSessionResult
from placerec.slam.result import ONLINE_STAGES, SlamResult
from placerec.slam_app.config import SlamConfig
from placerec.types import Candidate, Scan, Sequence, relative_pose, rigid_problem

__all__ = [
    "report_slam",
    "loop_table",
    "loop_edges",
    "slam_metrics",
    "print_slam_table",
    "write_map_ply",
    "prior_map_metrics",
]

LOOP_COLUMNS = ("match_id", "query_id", "score", "injected", "x", "y", "z", "roll", "pitch", "yaw")
#: After the batch step (not with ``graph.batch: none``): each loop's error at the solution, in sigmas of the loop
#: noise, and its weight (GNC's, or the robust kernel's at that error); below 0.5: rejected by the back end.
BATCH_COLUMNS = ("residual_sigmas", "weight")
TRUTH_COLUMNS = ("true_distance", "translation_error", "rotation_error_deg", "false", "opposite")


def loop_table(cfg: SlamConfig, result: SlamResult) -> dict[str, np.ndarray]:
    """The loop edges as columns (`LOOP_COLUMNS`, and `TRUTH_COLUMNS` when the run has ground truth)."""
    loops = result.loops
    L = len(loops)
    cols: dict[str, np.ndarray] = {
        "match_id": np.array([lp.match_id for lp in loops], dtype=np.int64),
        "query_id": np.array([lp.query_id for lp in loops], dtype=np.int64),
        "score": np.array([lp.score for lp in loops], dtype=np.float64),
        "injected": np.array([lp.injected for lp in loops], dtype=bool),
    }
    T = np.stack([lp.T_match_query for lp in loops]) if L else np.zeros((0, 4, 4))
    xyzrpy = np.stack([pose_to_xyzrpy(t) for t in T]) if L else np.zeros((0, 6))
    for j, key in enumerate(("x", "y", "z", "roll", "pitch", "yaw")):
        cols[key] = xyzrpy[:, j]
    for key, name in (("loop_residuals", "residual_sigmas"), ("loop_weights", "weight")):
        values = result.batch.get(key)
        if values is not None and len(values) == L:
            cols[name] = np.asarray(values, dtype=np.float64)
    gt = result.ground_truth
    if gt is not None:
        m, q = cols["match_id"], cols["query_id"]
        true_rel = np.stack([relative_pose(gt[a], gt[b]) for a, b in zip(m, q, strict=True)]) if L else T
        te, re = pose_errors(T, true_rel) if L else (np.zeros(0), np.zeros(0))
        ev = cfg.evaluation
        cols["true_distance"] = np.linalg.norm(gt[q, :3, 3] - gt[m, :3, 3], axis=1)
        cols["translation_error"] = te
        cols["rotation_error_deg"] = re
        cols["false"] = (te > ev.false_loop_translation) | (re > ev.false_loop_rotation_deg)
        heading = np.einsum("nij,j->ni", gt[:, :3, :3], np.array([1.0, 0.0, 0.0]))
        cos = np.einsum("ni,ni->n", heading[q, :2], heading[m, :2]) / np.maximum(
            np.linalg.norm(heading[q, :2], axis=1) * np.linalg.norm(heading[m, :2], axis=1), 1e-12
        )
        cols["opposite"] = cos < np.cos(np.radians(135.0))
    return cols


def loop_edges(result: SlamResult, cols: dict[str, np.ndarray]) -> list[LoopEdge]:
    """The edges of ``closures.mcap``: every loop of the graph, in `loop_table`'s order (``cols``), accepted unless
    the batch step weighed it below 0.5 (rejection ``back-end``), with its candidate's inlier count; then every
    candidate verification rejected between two scans of the run, with its rejection stage and its pose when it
    has a rigid one (a run against a prior map: between two of the session's scans)."""
    n = len(result.optimized)
    # the detector's ids: a prior map's keyframes first, then the session's scans
    offset = 0 if result.multisession is None else len(result.multisession.map_poses)
    loops = {(lp.query_id, lp.match_id) for lp in result.loops}
    found: dict[tuple[int, int], Candidate] = {}
    rejected: list[LoopEdge] = []
    for cands in result.candidates:
        for c in cands:
            q, m = c.query_id - offset, c.match_id - offset
            if not (0 <= q < n and 0 <= m < n):
                continue
            v = c.verification
            if c.accepted is not False or v is None:
                found[(q, m)] = c
            elif (q, m) not in loops:
                T = c.relative_pose if c.relative_pose is not None else v.T_match_query
                T = T if T is not None and rigid_problem(np.asarray(T)[None]) is None else None
                rejected.append(LoopEdge(q, m, c.score, T, c.inliers, False, c.rejection))
    weight = cols.get("weight")
    edges = []
    for k, lp in enumerate(result.loops):
        c = found.get((lp.query_id, lp.match_id))
        back = weight is not None and bool(weight[k] < 0.5)
        edges.append(LoopEdge(lp.query_id, lp.match_id, lp.score, lp.T_match_query, None if c is None else c.inliers,
                              not back, "back-end" if back else None, lp.injected))  # fmt: skip
    return edges + rejected


def _write_loops(path: Path, cols: dict[str, np.ndarray]) -> None:
    keys = list(cols)
    with atomic_write(path, "w") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(keys)
        for i in range(len(cols["match_id"])):
            row = []
            for k in keys:
                v = cols[k][i]
                row.append(
                    int(v) if cols[k].dtype == bool else (f"{v:.6g}" if cols[k].dtype.kind == "f" else v)
                )
            w.writerow(row)


def slam_metrics(cfg: SlamConfig, result: SlamResult, cols: dict[str, np.ndarray]) -> dict[str, Any]:
    """The ``metrics.json`` payload (see the module docstring)."""
    gt = result.ground_truth
    n = len(result.odometry)
    traj: dict[str, Any] = {}
    if gt is not None and n >= 3:
        for key, poses in (
            ("odometry", result.odometry),
            ("online", result.online),
            ("optimized", result.optimized),
        ):
            traj[key] = trajectory_errors(poses, gt, cfg.evaluation.rpe_delta).as_dict()
    injected = cols["injected"]
    loops: dict[str, Any] = {
        "accepted": int((~injected).sum()),
        "injected": int(injected.sum()),
    }
    if result.refused_by_gate is not None:
        loops["refused_by_odometry_gate"] = result.refused_by_gate
    if "weight" in cols:
        rejected = cols["weight"] < 0.5
        loops["rejected_by_back_end"] = int((rejected & ~injected).sum())
        loops["injected_rejected_by_back_end"] = int((rejected & injected).sum())
    if "false" in cols:
        real = ~injected
        loops["false_accepted"] = int((cols["false"] & real).sum())
        loops["opposite_direction"] = int((cols["opposite"] & real & ~cols["false"]).sum())
        te = cols["translation_error"][real]
        loops["max_translation_error"] = float(te.max()) if te.size else None
        loops["median_translation_error"] = float(np.median(te)) if te.size else None
    t = result.timing_ms
    # wait: a real-time detector's; map_search: the prior map's join pipelines; keyframe: loops.keyframes' building
    stages = (*ONLINE_STAGES, *(x for x in ("wait", "map_search", "keyframe") if x in t))
    per_scan = np.sum([t[s] for s in stages], axis=0) if n else np.zeros(0)
    queried = np.asarray(result.queried, dtype=bool) if len(result.queried) == n else np.ones(n, bool)
    timing = {
        "online_without_odometry": timing_summary(per_scan),
        "online_without_odometry_querying": timing_summary(per_scan[queried]),
        "online_with_odometry": timing_summary(per_scan + np.asarray(t["odometry"])),
        "online_without_odometry_cpu": timing_summary(t["cpu"]) if "cpu" in t else None,
        "stages": {s: timing_summary(t[s]) for s in (*stages, "odometry")},
        "isam2_update": timing_summary(result.isam2_ms),
        "isam2_loop_update": timing_summary(result.isam2_loop_ms),
        "batch_ms": result.batch.get("time_ms"),
    }
    payload: dict[str, Any] = {
        "mode": "slam",
        "dataset": result.name,
        "n_scans": n,
        "pipeline": cfg.loops.pipeline.display_name,
        "odometry_source": cfg.odometry.source,
        "trajectory": traj,
        "loops": loops,
        "time_ms": timing,
        "batch": {k: v for k, v in result.batch.items() if k not in ("loop_weights", "loop_residuals")},
    }
    if result.realtime is not None:
        payload["realtime"] = result.realtime
    if traj:
        opt = traj["optimized"]["ate_rmse"]
        payload["ate_reduction"] = traj["odometry"]["ate_rmse"] / opt if opt > 0 else None
    return payload


def _fmt(v: Any) -> str:
    """A figure as printed: ``-`` for none or not finite (e.g. no loop closed, so no iSAM2 loop update to time)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def _rows(payload: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    header = ["trajectory", "ATE RMSE [m]", "ATE max [m]", "RPE t RMSE [m]", "RPE rot RMSE [deg]"]
    rows = []
    for key, label in (
        ("odometry", "odometry"),
        ("online", "iSAM2 online"),
        ("optimized", "batch optimised"),
    ):
        e = payload["trajectory"].get(key)
        if e:
            keys = ("ate_rmse", "ate_max", "rpe_translation_rmse", "rpe_rotation_rmse_deg")
            rows.append([label] + [_fmt(e.get(k)) for k in keys])
    return header, rows


def _loop_rows(payload: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    """The loop closures and times (one row, the pipeline's): the HTML report's table; the console prints it as
    two (`print_slam_table`)."""
    lp, tm = payload["loops"], payload["time_ms"]
    header = ["loops", "accepted", "false", "opposite dir.", "injected", "refused by gate",
              "rejected by graph (real / injected)", "median t err [m]", "per-scan ms (no odom) median", "with odom",
              "iSAM2 ms", "iSAM2 loop ms"]  # fmt: skip
    rejected = (
        f"{lp['rejected_by_back_end']} / {lp['injected_rejected_by_back_end']}"
        if "rejected_by_back_end" in lp
        else "-"
    )
    row = [
        payload["pipeline"],
        _fmt(lp["accepted"]),
        _fmt(lp.get("false_accepted")),
        _fmt(lp.get("opposite_direction")),
        _fmt(lp["injected"]),
        _fmt(lp.get("refused_by_odometry_gate")),
        rejected,
        _fmt(lp.get("median_translation_error")),
        _fmt(tm["online_without_odometry"]["median"]),
        _fmt(tm["online_with_odometry"]["median"]),
        _fmt(tm["isam2_update"]["median"]),
        _fmt(tm["isam2_loop_update"]["median"]),
    ]
    rt = payload.get("realtime")
    if rt is not None:  # the real-time mode's budget
        header.append(f"scans over budget ({rt['budget_ms']:g} ms)")
        row.append(f"{rt['over_budget']} / {rt['scans']}")
    return header, [row]


#: where `_loop_rows`' time columns start (the console prints them as a table of their own)
_TIME_FROM = 8


def print_slam_table(payload: dict[str, Any], title: str) -> None:
    """The trajectory errors, the loop closures and the times as console tables (each fits 100 columns), each
    with the legend of its abbreviations."""
    title = f"{title}, odometry: {payload['odometry_source']}"
    if payload["trajectory"]:
        print_rows(*_rows(payload), title)
    header, rows = _loop_rows(payload)
    print_rows(header[:_TIME_FROM], [r[:_TIME_FROM] for r in rows], f"{title}: loop closures")
    times = [
        "median ms",
        "per scan, no odom",
        "with odom",
        "iSAM2 update",
        "iSAM2 loop update",
        *header[_TIME_FROM + 4 :],
    ]
    print_rows(times, [[r[0], *r[_TIME_FROM:]] for r in rows], f"{title}: time")


def write_map_ply(cfg: SlamConfig, seq: Sequence, poses: np.ndarray, path: Path) -> Path:
    """The corrected map: every preprocessed scan moved by its optimised pose, one point per ``map_voxel``
    (the first that falls in it, in scan order), as PLY."""
    from placerec.io.ply import write_ply

    voxel = cfg.output.map_voxel
    pre = cfg.preprocess
    cells, xyz, inten = [], [], []
    for i in range(len(seq)):
        scan = preprocess_scan(seq[i], pre)
        world = scan.xyz.astype(np.float64) @ poses[i][:3, :3].T + poses[i][:3, 3]
        c = np.floor(world / voxel).astype(np.int64)
        _, first = np.unique(c, axis=0, return_index=True)  # one point per voxel and scan first
        first.sort()
        cells.append(c[first])
        xyz.append(world[first])
        inten.append(scan.intensity[first])
    if cells:
        _, keep = np.unique(np.concatenate(cells), axis=0, return_index=True)
        keep.sort()  # the earliest scan's point of each voxel
        points, values = np.concatenate(xyz)[keep], np.concatenate(inten)[keep]
    else:
        points, values = np.zeros((0, 3)), np.zeros(0)
    write_ply(path, Scan(points.astype(np.float32), values, source=str(path)))
    return path


def prior_map_metrics(cfg: SlamConfig, result: SlamResult, prior: MapArtifact) -> dict[str, Any]:
    """``metrics.json``'s ``prior_map`` section of a second session: whether and how it was joined, its closures
    against the map, and with ground truth in the map's frame (a map built from true poses or a poses file) the
    session's error there without any alignment and the inter-session closures' pose errors."""
    ms = result.multisession
    assert ms is not None
    M = len(prior)
    inter = ms.inter_loops if ms.joined else ms.pending
    out: dict[str, Any] = {
        "path": str(prior.path),
        "keyframes": M,
        "anchor": ms.anchor,
        "joined": ms.joined,
        "summary": ms.summary(),
        "joined_at_scan": ms.joined_at,
        "T_map_session": None if ms.T_map_session is None else ms.T_map_session.tolist(),
        "inter_session_closures": len(inter),
        "rejected_at_join": len(ms.rejected_at_join),
        "rejected_by_graph": ms.rejected_by_graph,
        "refused_by_odometry_gate": len(ms.refused_by_gate),
        "map_poses_source": prior.manifest.poses_source,
    }
    gt = result.ground_truth
    if gt is None or prior.manifest.poses_source not in ("ground-truth", "file"):
        return out
    ev = cfg.evaluation
    if inter:
        est = np.stack([lp.T_match_query for lp in inter])
        truth = np.stack([relative_pose(prior.poses[lp.match_id], gt[lp.query_id - M]) for lp in inter])
        te, re = pose_errors(est, truth)
        false = (te > ev.false_loop_translation) | (re > ev.false_loop_rotation_deg)
        out["inter_session_false"] = int(false.sum())
        out["inter_session_median_translation_error"] = float(np.median(te))
    if ms.joined:
        te, re = pose_errors(result.optimized, gt)
        out["session_error_in_map_frame"] = {
            "translation_rmse": float(np.sqrt(np.mean(te**2))),
            "translation_max": float(te.max()),
            "rotation_max_deg": float(re.max()),
        }
    return out


def _sessions_figure(
    path: Path, prior_poses: np.ndarray, ms: MultiSessionResult, session_poses: np.ndarray, title: str
) -> None:
    """The prior map's keyframes (``prior_poses``, as saved) and the session (``session_poses``: in the map's frame
    when joined) with its inter-session closures and, dashed red, those the odometry gate refused after the join
    (a refused closure joins a keyframe to a query far from it)."""
    fig, ax = figures._pyplot().subplots(figsize=(7, 7), dpi=100)
    mp = (ms.map_poses if ms.joined else prior_poses)[:, :3, 3]
    sp = session_poses[:, :3, 3]
    ax.plot(mp[:, 0], mp[:, 1], ".", ms=2, color="0.6", label=f"prior map ({len(mp)} keyframes)")
    frame = "map frame" if ms.joined else "own frame: not joined"
    ax.plot(sp[:, 0], sp[:, 1], "-", lw=1.2, color="tab:blue", label=f"session ({frame})")
    if ms.joined:
        M = len(prior_poses)
        for lp in ms.inter_loops:
            a, b = mp[lp.match_id], sp[lp.query_id - M]
            ax.plot([a[0], b[0]], [a[1], b[1]], "-", lw=0.5, color="tab:green", alpha=0.6)
        for n, lp in enumerate(ms.refused_by_gate):
            a, b = mp[lp.match_id], sp[lp.query_id - M]
            label = f"refused by the odometry gate ({len(ms.refused_by_gate)})" if n == 0 else None
            ax.plot([a[0], b[0]], [a[1], b[1]], "--", lw=1.5, color="tab:red", label=label)
    ax.set(xlabel="x [m]", ylabel="y [m]")
    ax.set_title(title, fontsize=9)
    figures._frame(ax, mp, sp)
    figures._finish(fig, ax, path, loc="best")


def report_slam(
    cfg: SlamConfig, run: Path, seq: Sequence, result: SlamResult, prior: MapArtifact | None = None
) -> dict[str, Any]:
    """Write every output of a SLAM run into ``run``; returns the metrics dict (with ``prior``: a second
    session's, with its ``prior_map`` section and ``sessions.png``)."""
    stamps = (
        result.timestamps if result.timestamps is not None else np.arange(len(result.optimized), dtype=float)
    )
    write_kitti_poses(run / "poses_kitti.txt", result.optimized)
    write_tum_poses(run / "poses_tum.txt", result.optimized, stamps)
    write_kitti_poses(run / "odometry_kitti.txt", result.odometry)
    write_kitti_poses(run / "online_kitti.txt", result.online)
    if result.ground_truth is not None:
        write_kitti_poses(run / "ground_truth_kitti.txt", result.ground_truth)
    result.graph.write_g2o(
        run / "graph.g2o", result.optimized if result.graph_poses is None else result.graph_poses
    )
    cols = loop_table(cfg, result)
    _write_loops(run / "loops.csv", cols)
    write_closures_mcap(
        run / "closures.mcap",
        result.optimized,
        loop_edges(result, cols),
        timestamps=result.timestamps,
        ground_truth=result.ground_truth,
    )
    payload = slam_metrics(cfg, result, cols)
    if prior is not None:
        payload["prior_map"] = prior_map_metrics(cfg, result, prior)
    with atomic_write(run / "metrics.json", "w") as fh:
        json.dump(finite_or_null(payload), fh, indent=2, default=json_default, allow_nan=False)
    if cfg.output.figures:
        traj = {}
        if result.ground_truth is not None:
            traj["ground truth"] = result.ground_truth[:, :3, 3]
        traj["odometry"] = result.odometry[:, :3, 3]
        traj["optimised"] = result.optimized[:, :3, 3]
        ok = ~cols.get("false", np.zeros(len(cols["match_id"]), bool))
        e = payload["trajectory"]
        title = f"{cfg.name}: {cfg.loops.pipeline.display_name}, {len(result.loops)} loop edges"
        if e:
            title += (
                f"\nATE {e['odometry']['ate_rmse']:.2f} m (odometry) -> {e['optimized']['ate_rmse']:.3f} m"
            )
        loops = np.stack([cols["match_id"], cols["query_id"]], axis=1)
        figures.plot_slam_trajectories(traj, loops, ok, run / "trajectory.png", title, loops_on="optimised")
        tables = [_rows(payload), _loop_rows(payload)] if e else [_loop_rows(payload)]
        first: tuple[str, ...] = ("trajectory.png",)
        if prior is not None:
            assert result.multisession is not None  # a run with a prior map
            _sessions_figure(
                run / "sessions.png", prior.poses, result.multisession, result.optimized,
                f"{cfg.name}: {payload['prior_map']['summary']}",
            )  # fmt: skip
            first = ("sessions.png", "trajectory.png")
        write_html_page(run, cfg.name, "mode: slam", tables, first=first, last=())
    if cfg.output.map_ply:
        write_map_ply(cfg, seq, result.optimized, run / "map.ply")
    point_latest(run)
    return payload
