"""The SLAM back end on configs/slam_demo.yaml: trajectory error, robustness to injected false loops, per-scan cost.

1. The online loop over the config's sequence (`placerec.slam_app.run.slam_sequence`): per-scan cost of preprocess +
   loop closure (describe, query, verify, insert) + graph + iSAM2, odometry excluded (the config's odometry is
   the simulator's drift model, which costs nothing) and the iSAM2 update times (with and without a loop); ATE of
   odometry, iSAM2 and batch estimates; loops accepted, false (pose off by > 1 m / 5 deg), opposite-direction.
2. Robustness: the same odometry and accepted loops replayed into a fresh graph scan by scan (what `OnlineSlam`
   does; the loop closures do not depend on the graph), plus ``--false-loops`` injected wrong edges
   (`placerec.slam_app.run.false_loops`) for ``--seeds`` seeds, with the config's graph (Cauchy loop factors in
   iSAM2, GNC batch), with an LM batch instead, and with the peer: plain least squares (no kernel, LM).
   Target: ATE within 10 % of clean.
3. With odometry: KISS-ICP registering the first ``--kiss-scans`` scans, its time added to the online cost of
   the same scans.
4. Drift models: the same loops replayed with odometry from other drift settings (`DRIFTS`, seeds 0-2): what
   loop closures can and cannot correct (a scale error they cannot).

    .venv/bin/python tools/bench_slam.py [--config configs/slam_demo.yaml] [--set key=value ...] [--false-loops 10]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from placerec.eval.trajectory import trajectory_errors
from placerec.experiment.datasets import open_dataset
from placerec.sim.odometry import OdometryDrift, drift_poses
from placerec.slam.graph import GraphParams, LoopFactor, PoseGraph
from placerec.slam.odometry import KissIcpOdometry
from placerec.slam_app.config import load_slam_config
from placerec.slam_app.report import loop_table, slam_metrics
from placerec.slam_app.run import false_loops, slam_sequence

#: (label, translation, rotation_deg, yaw_bias_deg_per_100m, scale_bias) of `placerec.sim.odometry.OdometryDrift`
DRIFTS = (
    ("simulator default", 0.01, 0.03, 0.5, 0.005),
    ("simulator default, no scale error", 0.01, 0.03, 0.5, 0.0),
    ("slam_demo", 0.01, 0.03, 2.0, 0.002),
    ("slam_demo, 1 % scale error", 0.01, 0.03, 2.0, 0.01),
    ("slam_demo x 5", 0.05, 0.15, 10.0, 0.01),
)


def replay(odometry: np.ndarray, loops: list[LoopFactor], params: GraphParams) -> np.ndarray:
    """The graph rebuilt scan by scan as `OnlineSlam` builds it (iSAM2 after each scan), then the batch step."""
    by_query: dict[int, list[LoopFactor]] = {}
    for lp in loops:
        by_query.setdefault(lp.query_id, []).append(lp)
    g = PoseGraph(params)
    for i, T in enumerate(odometry):
        g.add_pose(T)
        for lp in by_query.get(i, []):
            g.add_loop(lp)
        g.update()
    return g.optimize()[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/slam_demo.yaml")
    ap.add_argument("--set", action="append", default=[], help="config override key.path=value")
    ap.add_argument("--false-loops", type=int, default=10)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--kiss-scans", type=int, default=100)
    args = ap.parse_args()

    cfg = load_slam_config(args.config, ["output.progress=false", *args.set])
    seq = open_dataset(cfg.dataset)
    t0 = time.perf_counter()
    result = slam_sequence(cfg, seq)
    run_s = time.perf_counter() - t0
    m = slam_metrics(cfg, result, loop_table(cfg, result))
    gt = result.ground_truth
    tm, lp, tr = m["time_ms"], m["loops"], m["trajectory"]
    print(
        f"{seq.name}: {len(seq)} scans, {cfg.loops.pipeline.display_name}, odometry '{cfg.odometry.source}' ({run_s:.0f} s)"
    )
    for key in ("odometry", "online", "optimized"):
        e = tr[key]
        print(
            f"  ATE {key:9s} {e['ate_rmse']:.3f} m (max {e['ate_max']:.3f}), RPE {e['rpe_translation_rmse']:.3f} m / {e['rpe_rotation_rmse_deg']:.3f} deg"
        )
    print(f"  ATE reduction {m['ate_reduction']:.1f}x (target >= 5x, ATE <= 0.3 m)")
    print(
        f"  loops: {lp['accepted']} accepted, {lp['false_accepted']} false, {lp['opposite_direction']} opposite-direction"
    )
    online, querying = tm["online_without_odometry"], tm["online_without_odometry_querying"]
    print(
        f"  online loop without odometry: median {online['median']:.1f} ms / scan, p95 {online['p95']:.1f} (target "
        f"<= 50 ms); over the {querying['n']} scans that query: median {querying['median']:.1f}, p95 {querying['p95']:.1f}"
    )
    cpu = tm["online_without_odometry_cpu"]
    print(f"  the same, process CPU time: median {cpu['median']:.1f} ms / scan, p95 {cpu['p95']:.1f}")
    for s, v in tm["stages"].items():
        print(f"    {s:10s} median {v['median']:.2f} ms, mean {v['mean']:.2f}")
    iu, il = tm["isam2_update"], tm["isam2_loop_update"]
    print(
        f"  iSAM2 update: median {iu['median']:.2f} ms (p95 {iu['p95']:.2f}); with a loop {il['median']:.2f} ms (p95 {il['p95']:.2f}); batch {tm['batch_ms']:.0f} ms"
    )

    real = [x for x in result.loops if not x.injected]
    robust: dict[str, dict[str, float | list[float]]] = {}
    for label, params in (
        ("config's graph", cfg.graph),
        ("Cauchy + LM batch", cfg.graph.model_copy(update={"batch": "lm"})),
        ("no kernel, LM (peer)", cfg.graph.model_copy(update={"robust": "none", "batch": "lm"})),
    ):
        clean = trajectory_errors(replay(result.odometry, real, params), gt).ate_rmse
        dirty = []
        for seed in range(args.seeds):
            c = cfg.model_copy(
                update={
                    "robustness": cfg.robustness.model_copy(
                        update={"false_loops": args.false_loops, "seed": seed}
                    )
                }
            )
            injected = [x for v in false_loops(c, gt, len(gt)).values() for x in v]
            dirty.append(trajectory_errors(replay(result.odometry, real + injected, params), gt).ate_rmse)
        worst = max(dirty) / clean
        robust[label] = {"clean": clean, "injected": dirty, "worst_ratio": worst}
        print(
            f"  {args.false_loops} false loops, {label:17s}: ATE clean {clean:.3f} m, injected {', '.join(f'{d:.3f}' for d in dirty)} (worst {worst:.2f}x clean)"
        )

    n_kiss = min(args.kiss_scans, len(seq))
    kiss = KissIcpOdometry(cfg.odometry.kiss_icp, gt[0] if gt is not None else None)
    kiss_ms, kiss_cpu = [], []
    for i in range(n_kiss):
        scan = seq[i]
        t, c = time.perf_counter(), time.process_time()
        kiss.register(scan)
        kiss_ms.append((time.perf_counter() - t) * 1e3)
        kiss_cpu.append((time.process_time() - c) * 1e3)
    per_scan = np.sum([result.timing_ms[s][:n_kiss] for s in tm["stages"] if s != "odometry"], axis=0)
    with_odo = per_scan + np.asarray(kiss_ms)
    print(
        f"  with KISS-ICP odometry (first {n_kiss} scans): KISS-ICP median {np.median(kiss_ms):.1f} ms (CPU {np.median(kiss_cpu):.1f}), online loop {np.median(with_odo):.1f} ms / scan"
    )
    drift_rows = {}
    for label, *values in DRIFTS:
        row = []
        for seed in range(3):
            odo = drift_poses(
                gt, OdometryDrift(**dict(zip(OdometryDrift.model_fields, values, strict=True))), seed
            )
            row.append(
                (
                    trajectory_errors(odo, gt).ate_rmse,
                    trajectory_errors(replay(odo, real, cfg.graph), gt).ate_rmse,
                )
            )
        drift_rows[label] = row
        print(
            f"  drift {label:36s} {values}: ATE "
            + ", ".join(f"{a:.3f} -> {b:.3f} ({a / b:.1f}x)" for a, b in row)
        )
    load = os.getloadavg()[0]
    print(f"  load average {load:.2f} ({os.cpu_count()} cores, {platform.processor() or platform.machine()})")
    print(
        json.dumps(
            {
                "bench": "slam",
                "config": args.config,
                "scans": len(seq),
                "pipeline": cfg.loops.pipeline.display_name,
                "ate_odometry_m": round(tr["odometry"]["ate_rmse"], 4),
                "ate_online_m": round(tr["online"]["ate_rmse"], 4),
                "ate_optimized_m": round(tr["optimized"]["ate_rmse"], 4),
                "ate_reduction": round(m["ate_reduction"], 2),
                "loops": lp["accepted"],
                "false_loops_accepted": lp["false_accepted"],
                "opposite_direction_loops": lp["opposite_direction"],
                "false_loops_injected": args.false_loops,
                "worst_ate_ratio_injected": {k: round(v["worst_ratio"], 3) for k, v in robust.items()},
                "ms_per_scan_without_odometry_median": round(online["median"], 2),
                "ms_per_querying_scan_without_odometry_median": round(querying["median"], 2),
                "cpu_ms_per_scan_without_odometry_median": round(cpu["median"], 2),
                "ms_per_scan_with_kiss_icp_median": round(float(np.median(with_odo)), 2),
                "kiss_icp_ms_median": round(float(np.median(kiss_ms)), 2),
                "kiss_icp_cpu_ms_median": round(float(np.median(kiss_cpu)), 2),
                "isam2_update_ms_median": round(iu["median"], 3),
                "isam2_loop_update_ms_median": round(il["median"], 3),
                "ate_reduction_by_drift": {k: [round(a / b, 1) for a, b in v] for k, v in drift_rows.items()},
                "load_average": round(load, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
